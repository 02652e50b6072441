"""usmswitch.runtime: how the service's processes and threads run, shared by all of them.

Real-time scheduling and priority (`realtime`: SCHED_FIFO, affinity, locked memory for the loop;
nice and SCHED_OTHER for the helpers and child processes), the logs' format (`logsetup`, structlog),
waiting for a child process without polling (`children`) and leaving a process without the
interpreter's teardown (`process_exit`). The daemon, the socket's server process and the shipper
process each set themselves up with these; it imports nothing of ours but `usmswitch.protocol`
(units in the logs).
"""

"""usmswitch.server: the daemon's sockets, served by a process of their own.

`RpcServer` (`rpc`) is the daemon's side: it binds the sockets, spawns, watches and restarts the
server process, and runs the handlers the daemon gives it, on threads of the daemon's process. The
server process (`rpc_process`, `python -m usmswitch.server.rpc_process`) speaks msgpack-RPC to the
clients (framing, limits, subscriptions, answers from the published snapshots and the records file)
and mounts the HTTP face (`usmswitch.web`). `EstopSocket` (`estop_socket`) is the emergency stop's
own socket, on a thread of the daemon that no other call can hold up. Nothing here knows the control
loop: the daemon hands it handlers, snapshots and the name of its records reader. See
docs/protocol.md, "Architecture".
"""

"""usmswitch.fleet: what reaches beyond one machine, and what reads it back.

The PostgreSQL copy of the records (`pg_schema`: its tables; `shipper`: the copying, in a process
the daemon starts), the Prometheus figures counted from committed strokes (`metrics`), and their
hooks on the daemon's record writer and loop (`hooks`). It imports `usmswitch.protocol` and
nothing else of ours: never the daemon. See docs/fleet.md.
"""

"""Each HTTP door's budget (web/door.py), apart from aiohttp so that the server process can size its
descriptors from them without importing the web stack (server/rpc_process.py, docs/service.md)."""

from __future__ import annotations

#: The panel: connections at once (a page and its assets take a few, a live feed one), the time a
#: request head begun may take, and how long a silent connection is kept.
PANEL_CONNECTIONS = 128
PANEL_HEAD_S = 10.0
PANEL_IDLE_S = 60.0
#: /metrics: Prometheus keeps one connection per target and scrapes every 5-60 s.
METRICS_CONNECTIONS = 16
METRICS_HEAD_S = 5.0
METRICS_IDLE_S = 120.0
#: Both HTTP doors' listen backlog, bound so by the daemon (server/rpc.py) and given again to the
#: event loop's create_server, which listens anew (with its default of 100 otherwise). Deep: past
#: it the kernel drops a SYN and the client tries again a second later; the door takes every
#: connection at once and sheds or refuses it there.
HTTP_BACKLOG = 128

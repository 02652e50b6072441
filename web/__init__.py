"""usmswitch.web: the HTTP face of the socket's server process.

Today the Prometheus page (`metrics_page`), served with aiohttp on the server process's event loop,
never the loop's. It imports `usmswitch.protocol` and `usmswitch.fleet` (the figures it shows),
never the daemon. See docs/fleet.md.
"""

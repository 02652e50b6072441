"""usmswitch.protocol: what both ends of the daemon's socket agree on, and nothing that runs the rig.

The msgpack-RPC framing and error codes (`wire`), each method's parameter schema (`rpc_params`), the
cycle and run records' fields (`record`) and the records file's layout (`records_schema`), units
(`units`), the statistics (`stats`), where the socket is and whether to trust it (`sockets`), and the
package's version (`version`). It imports nothing else of ours. See docs/protocol.md.
"""

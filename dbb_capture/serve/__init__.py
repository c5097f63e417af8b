"""dbb-serve: billboards redrawn live for moving viewers (docs/serve.md, docs/protocol.md)."""

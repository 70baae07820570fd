"""The tile service: multi-scale specimens, their tiles and queries over gRPC (`servicer`, with
`messages` converting between the API's messages and the core's types, and `admission` costing
each call). The same over plain HTTP is the `http` package's."""

__all__ = ["admission", "messages", "servicer"]

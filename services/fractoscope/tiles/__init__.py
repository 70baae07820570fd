"""The tile service: multi-scale specimens, their tiles and queries over gRPC (`servicer`, with
`messages` converting between the API's messages and the core's types), and the same over plain
HTTP (`http`: tilesets, the installed web viewer and the JSON API of `api`, which reads its inputs
with `http_requests`, answers with `http_json`, keeps `uploads` and runs `build_jobs`)."""

__all__ = ["api", "build_jobs", "http", "http_json", "http_requests", "messages", "openapi", "servicer", "uploads"]

"""HTTP, the specimens' front end beside gRPC: `server` serves tilesets, the installed web viewer
and the JSON API of `api`, described by `openapi` (its schemas in `openapi_schemas`). The API
reads its inputs with `inputs` into the API's messages, which the tile service's own `messages`
checks as it checks gRPC requests; it answers with `responses`, keeps `uploads` and runs
`build_jobs`."""

__all__ = ["api", "build_jobs", "inputs", "openapi", "openapi_schemas", "responses", "server", "uploads"]

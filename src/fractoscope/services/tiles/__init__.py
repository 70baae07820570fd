"""The tile service: multi-scale specimens, their tiles and queries over gRPC (`servicer`), the
same over plain HTTP with the web viewer (`http`; the viewer's files are the package data `web/`)."""

"""`fracto`, the command line: one module per verb group, `main` puts them together."""

__all__ = ["common", "demo", "export", "height", "main", "mesh", "specimen"]

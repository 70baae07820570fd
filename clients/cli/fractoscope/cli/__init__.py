"""`fracto`, the command line: one module per verb group, `main` puts them together."""

"""The gRPC server: `main` puts the services of `matching`, `meshing` and `tiles` together with
health checking, reflection and the process settings (`config`); `healthcheck` probes it."""

__all__ = ["config", "healthcheck", "main"]

"""The gRPC servers: `server` puts the services of `matching`, `meshing` and `tiles` together with
health checking, reflection, authentication (`auth`) and the process settings of a server."""

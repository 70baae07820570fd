"""The gRPC API's Python side, between the generated fractoscope.v1 stubs and the rest.

`wire`: numpy arrays, reports and query values to and from messages (numpy and protobuf only,
for both ends); `calls`: requests and the reading of streamed responses, shared by the client and
the services that call each other; `status`: exceptions to gRPC statuses and back; `channel` and
`limits`: channel options. `matching`, `meshing` and `tiles` convert the core's own types (options,
strips, meshes, specimens) for the servicers; the client never imports them.
"""

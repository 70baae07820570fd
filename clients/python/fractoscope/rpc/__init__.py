"""The gRPC API's Python side that both ends of the wire share, between the generated
fractoscope.v1 stubs and the rest.

`wire`: numpy arrays, reports and query values to and from messages (numpy and protobuf only);
`calls`: requests and the reading of streamed responses, shared by the client and the services
that call each other; `status`: exceptions to gRPC statuses (by errors.OUTCOMES) and back;
`manifest`: specimen manifests; `channel` and `limits`: channel options. Each service converts the
core's own types in its own `messages` module.
"""

__all__ = ["calls", "channel", "limits", "manifest", "status", "wire"]

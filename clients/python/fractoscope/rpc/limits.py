"""Limits shared by servers and clients: message sizes (images and height maps exceed gRPC's 4 MiB),
request ids and the ROIs of one specimen."""

from __future__ import annotations

DEFAULT_MAX_MESSAGE_MB = 512
# A request id is a caller's key for retries and logs, not a payload (HTTP and gRPC alike).
MAX_REQUEST_ID_CHARS = 128
# A specimen is an overview and its zooms: tens of ROIs, not thousands; each ROI carries its own copy
# of its images through the build, so the count bounds what one request can multiply.
MAX_ROIS = 64


def message_size_options(max_message_mb: int) -> list[tuple[str, int]]:
    """Channel and server options that lift gRPC's 4 MiB default for images and height maps."""
    limit = max_message_mb * 1024 * 1024
    return [("grpc.max_receive_message_length", limit), ("grpc.max_send_message_length", limit)]

"""Reading a file stream (Export, GetReport) at the caller: the file appears complete or not at
all, and a file already at the path stays as it was when the stream breaks off."""

from __future__ import annotations

import grpc
import pytest

from fractoscope.rpc.calls import read_file
from fractoscope.rpc.status import ClientError
from fractoscope.v1 import tiles_pb2

CONTENT = bytes(range(256)) * 40


class _Broken(grpc.RpcError):
    """A stream that ended with UNAVAILABLE, as a stub raises it when the server goes away."""

    def code(self):
        return grpc.StatusCode.UNAVAILABLE


def _stream(content: bytes, *, size_bytes: int, fail: bool = False):
    yield tiles_pb2.ExportResponse(
        file=tiles_pb2.FileHeader(file_name="x.stl", media_type="model/stl", size_bytes=size_bytes)
    )
    for start in range(0, len(content), 1000):
        yield tiles_pb2.ExportResponse(chunk=content[start : start + 1000])
        if fail and start >= 3000:
            raise _Broken()


def test_a_whole_stream_is_renamed_into_place(tmp_path):
    first = read_file(_stream(CONTENT, size_bytes=len(CONTENT)), tmp_path / "out.stl")
    assert first.file.file_name == "x.stl"
    assert (tmp_path / "out.stl").read_bytes() == CONTENT and [p.name for p in tmp_path.iterdir()] == ["out.stl"]


@pytest.mark.parametrize("fail", [True, False], ids=["call breaks off", "fewer bytes than announced"])
def test_a_stream_that_breaks_off_leaves_nothing_half_written(tmp_path, fail):
    size = len(CONTENT) + (0 if fail else 1)
    with pytest.raises((grpc.RpcError, ClientError)) as raised:
        read_file(_stream(CONTENT, size_bytes=size, fail=fail), tmp_path / "new.stl")
    if not fail:
        assert f"carried {len(CONTENT)} of the file's {size} bytes" in str(raised.value)
    assert list(tmp_path.iterdir()) == []
    # An earlier export at the same path is neither truncated nor replaced.
    (tmp_path / "old.stl").write_bytes(b"earlier export")
    with pytest.raises((grpc.RpcError, ClientError)):
        read_file(_stream(CONTENT, size_bytes=size, fail=fail), tmp_path / "old.stl")
    assert (tmp_path / "old.stl").read_bytes() == b"earlier export" and [p.name for p in tmp_path.iterdir()] == [
        "old.stl"
    ]


def test_a_stream_without_a_file_header_writes_nothing(tmp_path):
    with pytest.raises(ClientError, match="without a file"):
        read_file(iter([tiles_pb2.ExportResponse(chunk=b"orphan")]), tmp_path / "out.x3p")
    assert list(tmp_path.iterdir()) == []

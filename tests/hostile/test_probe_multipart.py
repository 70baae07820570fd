"""Multipart bodies a hostile user sends (issue 49, items 5 and 7): a part that is itself a
multipart body, and an upload of 20,000 tiny parts. Each is refused at once as the caller's error
(400 or 413 naming the body), nothing stored; never a 500."""

from __future__ import annotations

import json
import uuid

import pytest
import requests
from probe_servers import READ, WRITE

from fractoscope.http.uploads import MAX_UPLOAD_PARTS

MANIFEST = {
    "specimen": "probe",
    "rois": [{"id": "overview", "left": "l.png", "right": "r.png", "tilt_deg": [-5, 5], "pixel_size_um": 0.1}],
}


def multipart_body(parts: list[tuple[dict[str, str], bytes]]) -> tuple[bytes, str]:
    """A multipart/form-data body of (headers, content) parts written by hand, and its
    Content-Type, so that any structure can be sent."""
    boundary = uuid.uuid4().hex
    chunks = []
    for headers, content in parts:
        head = "".join(f"{name}: {value}\r\n" for name, value in headers.items())
        chunks.append(f"--{boundary}\r\n{head}\r\n".encode() + content + b"\r\n")
    chunks.append(f"--{boundary}--\r\n".encode())
    return b"".join(chunks), f"multipart/form-data; boundary={boundary}"


def _field(name: str, content: bytes, filename: str | None = None) -> tuple[dict[str, str], bytes]:
    disposition = f'form-data; name="{name}"' + (f'; filename="{filename}"' if filename else "")
    return {"Content-Disposition": disposition}, content


def _nested(name: str) -> tuple[dict[str, str], bytes]:
    """A part that is a multipart/mixed body of one text part."""
    inner, inner_type = multipart_body([({"Content-Type": "text/plain"}, b"hello")])
    return {
        "Content-Disposition": f'form-data; name="{name}"',
        "Content-Type": inner_type.replace("form-data", "mixed"),
    }, inner


def _uploads(live) -> list[str]:
    folder = live.data / "uploads"
    return sorted(path.name for path in folder.iterdir()) if folder.is_dir() else []


@pytest.mark.parametrize(
    "path, headers, first",
    [
        ("/api/uploads", WRITE, _field("manifest", json.dumps(MANIFEST).encode())),
        ("/api/exports", READ, _field("format", b"x3p")),
    ],
)
def test_a_nested_multipart_part_is_refused_naming_the_body(live, path, headers, first):
    """Once a 500 (AttributeError: a MultipartReader has no read_chunk)."""
    before = _uploads(live)
    body, content_type = multipart_body([first, _nested("images")])
    answer = requests.post(
        f"{live.http}{path}", data=body, headers={**headers, "Content-Type": content_type}, timeout=60
    )
    assert answer.status_code == 400, answer.text
    assert answer.json()["field"] == "body" and "multipart" in answer.json()["error"]
    assert _uploads(live) == before


def test_an_upload_of_20000_tiny_parts_is_refused_as_too_many_parts(live):
    """Once a 400 after 17 s, every part written to a file on the event loop meanwhile (/healthz
    took 14.8 s); now refused at the first part beyond MAX_UPLOAD_PARTS, before it costs a file."""
    before = _uploads(live)
    parts = [_field("manifest", json.dumps(MANIFEST).encode())]
    parts += [_field("images", b"x", f"f{index}.png") for index in range(20_000)]
    body, content_type = multipart_body(parts)
    answer = requests.post(
        f"{live.http}/api/uploads", data=body, headers={**WRITE, "Content-Type": content_type}, timeout=120
    )
    assert answer.status_code == 413, answer.text
    assert answer.json()["field"] == "body" and str(MAX_UPLOAD_PARTS) in answer.json()["error"]
    assert _uploads(live) == before
    assert requests.get(f"{live.http}/healthz", timeout=10).status_code == 200

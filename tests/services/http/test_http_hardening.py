"""What a hostile probe of the HTTP/JSON API found, each on a real server on loopback: height maps
larger than an image may be (413 before the array is allocated, decoded off the event loop),
inputs that once answered a plain-text 500 (JSON 4xx, 507 on a full disk, JSON 500 for the
unforeseen), credentials in aiohttp's log, CORS for the Authorization header, and DELETE for
uploads and specimens."""

from __future__ import annotations

import errno
import io
import json
import logging
import os
import socket
import threading
import zipfile

import numpy as np
import pytest
import requests
from conftest import write_small_specimen

from fractoscope.http import api, openapi, uploads
from fractoscope.http.server import start_http_server
from fractoscope.runtime.auth import TokenTable
from fractoscope.sem import image as sem_image
from fractoscope.store.folder import SpecimenStore

TOKENS = TokenTable.from_text("lims:write-secret:write,viewer:read-secret:read")
READ, WRITE = {"Authorization": "Bearer read-secret"}, {"Authorization": "Bearer write-secret"}


@pytest.fixture()
def served(tmp_path):
    """(base URL, data folder) of an endpoint with tokens, its store holding the small specimen
    `steel-1`; builds would go to a gRPC address nothing listens on (none is sent in these tests)."""
    store = SpecimenStore(tmp_path / "data")
    write_small_specimen(store, "steel-1")
    endpoint = start_http_server(store, tokens=TOKENS, grpc_address="127.0.0.1:9")
    yield f"http://127.0.0.1:{endpoint.server_port}", tmp_path / "data"
    endpoint.shutdown()


def _npz(**arrays) -> bytes:
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    return buffer.getvalue()


def _npz_declaring(shape: tuple[int, ...]) -> bytes:
    """An npz whose z_um .npy header declares float32 `shape`, followed by 16 bytes of data."""
    member = io.BytesIO()
    np.lib.format.write_array_header_1_0(member, {"descr": "<f4", "fortran_order": False, "shape": shape})
    member.write(bytes(16))
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        archive.writestr("z_um.npy", member.getvalue())
    return buffer.getvalue()


def _export(base: str, height_map: bytes) -> requests.Response:
    files = {"height_map": ("map.npz", height_map), "format": (None, "x3p"), "map_pixel_size_um": (None, "0.5")}
    return requests.post(f"{base}/api/exports", files=files, headers=READ, timeout=60)


# Height maps ######################################################################################


def test_a_height_map_declaring_more_pixels_than_an_image_may_have_is_refused_before_it_is_allocated(served):
    """100000² float32 declared in 1 kB: once a 37 GiB allocation and a plain-text 500."""
    base, _ = served
    answer = _export(base, _npz_declaring((100_000, 100_000)))
    assert answer.status_code == 413 and answer.json()["field"] == "height_map", answer.text
    assert "100000x100000" in answer.json()["error"]


def test_a_height_map_is_held_to_the_pixel_limit_of_images(served, monkeypatch):
    base, _ = served
    height_map = _npz(z_um=np.zeros((48, 64), np.float32))
    assert _export(base, height_map).status_code == 200
    monkeypatch.setattr(sem_image, "MAX_IMAGE_PIXELS", 48 * 64 - 1)
    answer = _export(base, height_map)
    assert answer.status_code == 413 and answer.json()["field"] == "height_map", answer.text


def test_a_height_map_is_decoded_off_the_event_loop(served, monkeypatch):
    """A 16000² map took 4.5 s to decode on the event loop, which answered nothing else meanwhile."""
    base, _ = served
    threads = []
    decode = api.npz_height_map

    def recorded(content):
        threads.append(threading.current_thread().name)
        return decode(content)

    monkeypatch.setattr(api, "npz_height_map", recorded)
    assert _export(base, _npz(z_um=np.zeros((48, 64), np.float32))).status_code == 200
    assert len(threads) == 1 and threads[0] != "fractoscope-http"  # the event loop's thread (http.HttpTileServer)


def _zip(**members: bytes) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        for name, content in members.items():
            archive.writestr(name, content)
    return buffer.getvalue()


@pytest.mark.parametrize(
    "height_map",
    [
        b"PK\x03\x04" + bytes(range(256)) * 4,  # once zipfile.BadZipFile, a plain-text 500
        _zip(**{"z_um.npy": b"not an array"}),
        _zip(**{"z_um.npy": b"\x93NUMPY\x01\x00\x10\x00{'descr': 1}    \n"}),
        _zip(**{"sigma_um.npy": np.lib.format.MAGIC_PREFIX}),
        _npz(pixel_size_um=np.float64(0.5)),
        _npz(z_um=np.array(["a", "b"])),
    ],
    ids=["corrupt-zip", "not-npy", "bad-header", "truncated-header", "no-z_um", "text"],
)
def test_an_npz_whose_arrays_cannot_be_read_is_a_json_400_naming_height_map(served, height_map):
    base, _ = served
    answer = _export(base, height_map)
    assert answer.status_code == 400 and answer.json()["field"] == "height_map", answer.text


# JSON, never a plain-text 500 #####################################################################


def test_an_integer_of_more_digits_than_python_converts_in_a_job_body_is_a_json_400(served):
    base, _ = served
    body = '{"upload_id": ' + "9" * 5000 + "}"
    answer = requests.post(
        f"{base}/api/jobs", data=body, headers={**WRITE, "Content-Type": "application/json"}, timeout=30
    )
    assert answer.status_code == 400 and answer.json()["field"] == "body", answer.text


class _FullDiskFile:
    """A file opened on a full disk (or over quota): every write fails, as the OS fails it."""

    def __init__(self, code: int):
        self.code = code

    def __enter__(self):
        return self

    def __exit__(self, *exception):
        return False

    def write(self, data: bytes):
        raise OSError(self.code, os.strerror(self.code))


@pytest.mark.parametrize("code", [errno.ENOSPC, errno.EDQUOT], ids=["ENOSPC", "EDQUOT"])
def test_an_upload_on_a_full_disk_is_a_json_507_and_leaves_nothing(served, monkeypatch, code):
    base, data = served
    monkeypatch.setattr(uploads, "open", lambda *args, **kwargs: _FullDiskFile(code), raising=False)
    manifest = {"manifest": (None, json.dumps({"specimen": "full"}), "application/json")}
    answer = requests.post(f"{base}/api/uploads", files=manifest, headers=WRITE, timeout=30)
    assert answer.status_code == 507 and answer.headers["Content-Type"] == "application/json", answer.text
    assert answer.json()["field"] is None and answer.json()["error"]
    assert list((data / "uploads").iterdir()) == []


def test_an_unforeseen_failure_is_a_json_500_naming_only_its_class_with_the_traceback_in_the_log(
    served, monkeypatch, caplog
):
    base, _ = served

    def broken():
        raise RuntimeError("a detail for the log only")

    monkeypatch.setattr(openapi, "document", broken)
    answer = requests.get(f"{base}/api/openapi.json", timeout=30)
    assert answer.status_code == 500 and answer.headers["Content-Type"] == "application/json", answer.text
    assert answer.json() == {"error": "internal error (RuntimeError)", "field": None}
    logged = [record for record in caplog.records if record.exc_info and record.exc_info[0] is RuntimeError]
    assert len(logged) == 1 and logged[0].levelno == logging.ERROR and logged[0].name == api.__name__


# Logs and CORS ####################################################################################


@pytest.mark.parametrize(
    "request_bytes",
    [
        b"GET /api/specimens HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer s3cret\x01x\r\n\r\n",
        b"GET /api/specimens HTTP/1.1\r\nHost: x\r\nAuthorization: Basic s3cret\x7f\r\n\r\n",
        b"GET /api/specimens?token=s3cret\x01 HTTP/1.1\r\nHost: x\r\n\r\n",
    ],
    ids=["bearer", "basic", "query"],
)
def test_a_credential_in_a_request_the_parser_refuses_reaches_no_log(served, caplog, request_bytes):
    """aiohttp once logged the refused header, token and all, at ERROR with a traceback."""
    base, _ = served
    caplog.set_level(logging.DEBUG, logger="aiohttp")
    with socket.create_connection(base.removeprefix("http://").split(":"), timeout=10) as connection:
        connection.sendall(request_bytes)
        status_line = connection.recv(4096).split(b"\r\n")[0]
    assert status_line.split()[1] == b"400"
    refused = [record for record in caplog.records if record.name.startswith("aiohttp")]
    assert refused and all(record.levelno == logging.DEBUG and not record.exc_info for record in refused)
    assert not [record for record in caplog.records if record.levelno >= logging.ERROR]
    assert "s3cret" not in caplog.text and not any("s3cret" in record.getMessage() for record in caplog.records)


def test_a_cors_preflight_names_the_authorization_header_and_every_method(served):
    """`Access-Control-Allow-Headers: *` does not cover Authorization (Fetch standard)."""
    base, _ = served
    answer = requests.options(
        f"{base}/api/specimens/steel-1",
        headers={
            "Origin": "https://lims.example",
            "Access-Control-Request-Method": "DELETE",
            "Access-Control-Request-Headers": "authorization,content-type",
        },
        timeout=30,
    )
    allowed = {name.strip().lower() for name in answer.headers["Access-Control-Allow-Headers"].split(",")}
    methods = {name.strip() for name in answer.headers["Access-Control-Allow-Methods"].split(",")}
    assert answer.status_code == 204 and {"authorization", "content-type"} <= allowed and "*" not in allowed
    assert {"GET", "POST", "DELETE"} <= methods


# DELETE ###########################################################################################


def test_a_specimen_is_deleted_with_a_write_token(served):
    base, data = served
    url = f"{base}/api/specimens/steel-1"
    assert requests.delete(url, timeout=30).status_code == 401
    refused = requests.delete(url, headers=READ, timeout=30)
    assert refused.status_code == 403 and refused.json()["field"] == "authorization"
    assert requests.get(url, headers=READ, timeout=30).status_code == 200
    deleted = requests.delete(url, headers=WRITE, timeout=30)
    assert deleted.status_code == 204 and deleted.content == b"", deleted.text
    assert requests.get(url, headers=READ, timeout=30).status_code == 404
    assert SpecimenStore(data).ids() == []
    again = requests.delete(url, headers=WRITE, timeout=30)
    assert again.status_code == 404 and again.json()["field"] == "specimen_id" and "steel-1" in again.json()["error"]
    malformed = requests.delete(f"{base}/api/specimens/steel.1", headers=WRITE, timeout=30)
    assert malformed.status_code == 400 and malformed.json()["field"] == "specimen_id"


def test_an_upload_is_deleted_with_a_write_token(served, built):
    base, data = served
    _, _, built_data, _ = built
    input_directory = built_data.parent / "input"
    parts = [("manifest", (None, (input_directory / "manifest.json").read_text(), "application/json"))] + [
        ("images", (path.name, path.read_bytes(), "image/png")) for path in sorted(input_directory.glob("*.png"))
    ]
    uploaded = requests.post(f"{base}/api/uploads", files=parts, headers=WRITE, timeout=60)
    assert uploaded.status_code == 201, uploaded.text
    upload_id = uploaded.json()["upload_id"]
    url = f"{base}/api/uploads/{upload_id}"
    assert requests.delete(url, timeout=30).status_code == 401
    assert requests.delete(url, headers=READ, timeout=30).status_code == 403
    deleted = requests.delete(url, headers=WRITE, timeout=30)
    assert deleted.status_code == 204 and deleted.content == b"", deleted.text
    assert list((data / "uploads").iterdir()) == []
    job = requests.post(f"{base}/api/jobs", json={"upload_id": upload_id}, headers=WRITE, timeout=30)
    assert job.status_code == 404 and job.json()["field"] == "upload_id"
    again = requests.delete(url, headers=WRITE, timeout=30)
    assert again.status_code == 404 and again.json()["field"] == "upload_id" and upload_id in again.json()["error"]
    malformed = requests.delete(f"{base}/api/uploads/not-an-id", headers=WRITE, timeout=30)
    assert malformed.status_code == 400 and malformed.json()["field"] == "upload_id"

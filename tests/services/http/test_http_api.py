"""The HTTP/JSON API on a real server on loopback: its OpenAPI document validates, an upload
builds a specimen through a job, tokens and scopes are gRPC's, and schemathesis fuzzes every
documented operation (bounded: a few examples each, no shrinking) without a 5xx, a non-JSON error
or anything half-written."""

from __future__ import annotations

import http.client
import io
import json
import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest
import requests
import schemathesis
import trimesh
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis.errors import Unsatisfiable
from openapi_spec_validator import validate
from schemathesis.checks import not_a_server_error
from schemathesis.generation.modes import GenerationMode
from schemathesis.specs.openapi.checks import (
    content_type_conformance,
    negative_data_rejection,
    response_schema_conformance,
    status_code_conformance,
)
from surfalize import Surface

from fractoscope.formats.x3p import read_x3p
from fractoscope.http import openapi
from fractoscope.http.server import start_http_server
from fractoscope.runtime.auth import TokenTable
from fractoscope.runtime.budget import Budget
from fractoscope.server.config import ServerConfig
from fractoscope.server.main import create_server
from fractoscope.store.folder import SpecimenStore

# Per operation and generation mode; FRACTO_FUZZ_EXAMPLES asks for a deeper run.
FUZZ_EXAMPLES = int(os.environ.get("FRACTO_FUZZ_EXAMPLES", "8"))
TOKENS = TokenTable.from_text("lims:write-secret:write,viewer:read-secret:read")


def _serve(data: Path, tokens: TokenTable | None = None):
    store = SpecimenStore(data)
    server, port = create_server(ServerConfig(address="127.0.0.1:0"), store=store, tokens=tokens)
    server.start()
    endpoint = start_http_server(store, tokens=tokens, grpc_address=f"127.0.0.1:{port}")
    return server, endpoint, f"http://127.0.0.1:{endpoint.server_port}"


@pytest.fixture(scope="module")
def api(built, tmp_path_factory):
    """A server on a copy of the example specimen's data (builds and uploads go there)."""
    _, _, data, _ = built
    copy = tmp_path_factory.mktemp("api") / "data"
    shutil.copytree(data, copy)
    server, endpoint, base = _serve(copy)
    yield base, copy
    endpoint.shutdown()
    server.stop(grace=None)


def _upload_parts(input_directory: Path, specimen_id: str) -> list:
    manifest = json.loads((input_directory / "manifest.json").read_text())
    manifest["specimen"] = specimen_id
    return [("manifest", (None, json.dumps(manifest), "application/json"))] + [
        ("images", (path.name, path.read_bytes(), "image/png")) for path in sorted(input_directory.glob("*.png"))
    ]


@pytest.fixture(scope="module")
def input_directory(built) -> Path:
    _, _, data, _ = built
    return data.parent / "input"


def test_the_openapi_document_is_valid_openapi_3_1_and_served(api):
    base, _ = api
    served = requests.get(f"{base}/api/openapi.json", timeout=30)
    assert served.status_code == 200 and served.json() == openapi.document()
    validate(served.json())  # raises unless the document is valid OpenAPI 3.1
    assert served.json()["openapi"] == "3.1.0"


def test_an_upload_builds_a_specimen_through_a_job_that_reports_progress(api, input_directory):
    base, data = api
    uploaded = requests.post(f"{base}/api/uploads", files=_upload_parts(input_directory, "from-upload"), timeout=60)
    assert uploaded.status_code == 201 and uploaded.json()["rois"] == ["overview", "zoom"]
    submitted = requests.post(
        f"{base}/api/jobs", json={"upload_id": uploaded.json()["upload_id"], "request_id": "lims-7"}, timeout=30
    )
    assert submitted.status_code == 202 and submitted.json()["state"] in ("queued", "running")
    seen = []
    deadline = time.monotonic() + 240
    while time.monotonic() < deadline:
        job = requests.get(base + submitted.headers["Location"], timeout=30).json()
        seen.append(job["progress"]["fraction"])
        if job["state"] in ("succeeded", "failed"):
            break
        time.sleep(0.5)
    assert job["state"] == "succeeded", job["error"]
    assert (
        job["specimen"]["id"] == "from-upload"
        and job["request_id"] == "lims-7"
        and seen == sorted(seen)
        and seen[-1] == 1.0
    )
    specimen = requests.get(f"{base}/api/specimens/from-upload", timeout=30).json()
    assert [roi["id"] for roi in specimen["rois"]] == ["overview", "zoom"]
    assert specimen["rois"][1]["matching"]["tilt_source"] == ["argument", "argument"]
    assert not list((data / "uploads").glob(".staging-*"))


def test_a_bad_upload_names_the_field_and_stores_nothing(api, input_directory):
    base, data = api
    before = sorted(path.name for path in (data / "uploads").iterdir())
    parts = [part for part in _upload_parts(input_directory, "missing-image") if part[1][0] != "zoom_right.png"]
    answer = requests.post(f"{base}/api/uploads", files=parts, timeout=60)
    assert answer.status_code == 400 and answer.json()["field"] == "manifest.rois[1].right"
    answer = requests.post(f"{base}/api/jobs", json={"upload_id": "0" * 32}, timeout=30)
    assert answer.status_code == 404 and answer.json()["field"] == "upload_id"
    parts = [
        (name, (file, b"not an image" if file == "zoom_right.png" else content, kind))
        for name, (file, content, kind) in _upload_parts(input_directory, "unreadable-image")
    ]
    answer = requests.post(f"{base}/api/uploads", files=parts, timeout=60)  # once named rois[1].images[1].image
    assert answer.status_code == 400 and answer.json()["field"] == "manifest.rois[1].right", answer.text
    assert sorted(path.name for path in (data / "uploads").iterdir()) == before


@pytest.mark.parametrize(
    "setting, field",
    [
        ({"matching": {"window_px": 4}}, "manifest.rois[0].matching.window_px"),
        ({"matching": {"max_disparity_px": 100_000}}, "manifest.rois[0].matching.max_disparity_px"),
        ({"tilt_axis_deg": 500}, "manifest.rois[0].tilt_axis_deg"),
        ({"parent": 7}, "manifest.rois[0].parent"),  # once a TypeError from protobuf, HTTP 500
    ],
)
def test_a_manifest_the_build_would_refuse_is_refused_before_a_job_is_accepted(api, input_directory, setting, field):
    """Matching parameters out of range fail the upload (400, naming the manifest's key), not a
    job accepted with 202 that fails later."""
    base, data = api
    before = sorted(path.name for path in (data / "uploads").iterdir())
    parts = _upload_parts(input_directory, "bad-setting")
    manifest = json.loads(parts[0][1][1])
    manifest["rois"][0].update(setting)
    parts[0] = ("manifest", (None, json.dumps(manifest), "application/json"))
    for path in ("/api/uploads", "/api/jobs"):
        answer = requests.post(base + path, files=parts, timeout=60)
        assert answer.status_code == 400 and answer.json()["field"] == field, answer.text
    assert sorted(path.name for path in (data / "uploads").iterdir()) == before


def test_json_nested_too_deeply_is_refused_naming_it(api, input_directory):
    """60 kB of brackets, within the body limit: Python's JSON parser raises RecursionError, once
    an HTTP 500."""
    base, _ = api
    nested = "[" * 30_000 + "]" * 30_000
    answer = requests.post(f"{base}/api/jobs", data=nested, headers={"Content-Type": "application/json"}, timeout=30)
    assert answer.status_code == 400 and answer.json()["field"] == "body", answer.text
    parts = [("manifest", (None, nested, "application/json"))] + _upload_parts(input_directory, "nested")[1:]
    answer = requests.post(f"{base}/api/uploads", files=parts, timeout=60)
    assert answer.status_code == 400 and answer.json()["field"] == "manifest", answer.text


def test_analyses_have_threads_of_their_own_and_too_many_get_429(built, monkeypatch):
    """With the one analysis thread held and no queue, another analysis gets 429 at once while
    lookups and tiles are answered; twelve roughness queries once held a specimen lookup for 77 s."""
    import concurrent.futures
    import threading

    from fractoscope.specimen import queries

    _, _, data, _ = built
    release, started = threading.Event(), threading.Event()
    statistics = queries.height_statistics

    def held(*args, **kwargs):
        started.set()
        release.wait(timeout=120)
        return statistics(*args, **kwargs)

    monkeypatch.setattr(queries, "height_statistics", held)
    one_at_a_time = Budget(memory_bytes=1 << 40, request_limit_bytes=1 << 40, cpu_slots=1, queue_limit=0)
    endpoint = start_http_server(SpecimenStore(data), budget=one_at_a_time)
    base = f"http://127.0.0.1:{endpoint.server_port}"
    specimen = requests.get(f"{base}/api/specimens", timeout=30).json()[0]["id"]
    heights = f"{base}/api/specimens/{specimen}/heights?region=0,0,10,10"
    try:
        with concurrent.futures.ThreadPoolExecutor(1) as caller:
            running = caller.submit(requests.get, heights, timeout=120)
            assert started.wait(timeout=60)
            refused = requests.get(heights, timeout=30)
            assert refused.status_code == 429 and refused.headers["Retry-After"] and refused.json()["field"] is None
            assert requests.get(f"{base}/api/specimens/{specimen}", timeout=30).status_code == 200
            assert requests.get(f"{base}/specimens/{specimen}/tileset.json", timeout=30).status_code == 200
            assert not running.done()
            release.set()
            assert running.result().status_code == 200
    finally:
        release.set()
        endpoint.shutdown()


@pytest.mark.parametrize("path", ["/api/uploads", "/api/exports"])
def test_a_body_declared_too_large_is_refused_before_it_is_sent(api, path):
    """10 GB declared, headers only: the answer comes without the server waiting for the body."""
    base, _ = api
    host, port = base.removeprefix("http://").split(":")
    connection = http.client.HTTPConnection(host, int(port), timeout=30)
    try:
        connection.putrequest("POST", path)
        connection.putheader("Content-Type", "multipart/form-data; boundary=x")
        connection.putheader("Content-Length", str(10**10))
        connection.endheaders()
        answer = connection.getresponse()
        assert answer.status == 413 and json.loads(answer.read())["field"] == "body"
    finally:
        connection.close()


def test_a_height_map_export_over_http_is_the_file_of_the_map(api):
    base, _ = api
    z_um = np.arange(48 * 64, dtype=np.float32).reshape(48, 64) / 100
    buffer = io.BytesIO()
    np.savez(buffer, z_um=z_um, pixel_size_um=np.float64(0.5))
    answer = requests.post(
        f"{base}/api/exports", files={"height_map": ("map.npz", buffer.getvalue()), "format": (None, "tif")}, timeout=60
    )
    assert answer.status_code == 200 and answer.headers["Content-Type"] == "image/tiff"
    import tifffile

    np.testing.assert_array_equal(tifffile.imread(io.BytesIO(answer.content)), z_um)


@pytest.mark.parametrize(
    "stored_um, form, field",
    [
        (None, {"map_pixel_size_um": "1e308"}, "map_pixel_size_um"),  # once an STL of inf coordinates
        (None, {"map_pixel_size_um": "0"}, "map_pixel_size_um"),
        (None, {}, "map_pixel_size_um"),
        (1e-300, {}, "height_map.pixel_size_um"),
        ("tiff", {}, "height_map"),  # once "pickled data" from np.load
    ],
)
def test_a_height_map_export_over_http_checks_the_map_as_grpc_does(api, stored_um, form, field):
    base, _ = api
    buffer = io.BytesIO()
    if stored_um == "tiff":
        import tifffile

        tifffile.imwrite(buffer, np.zeros((32, 32), np.float32))
    else:
        np.savez(
            buffer,
            z_um=np.zeros((32, 32), np.float32),
            **({} if stored_um is None else {"pixel_size_um": np.float64(stored_um)}),
        )
    files = {
        "height_map": ("map.npz", buffer.getvalue()),
        "format": (None, "stl"),
        **{key: (None, value) for key, value in form.items()},
    }
    answer = requests.post(f"{base}/api/exports", files=files, timeout=60)
    assert answer.status_code == 400 and answer.json()["field"] == field, answer.text


def test_a_region_export_over_http_at_a_chosen_pixel_size_is_grpcs(api, built, tmp_path, monkeypatch):
    """GET .../export with region= and pixel_size_um=: the X3P holds the same heights as the
    Export RPC's on the 0.25 µm grid asked for, with the API's Sa after surfalize's plane; a solid
    STL in mm is a watertight block of the region's extent; a failed export answers 400 naming the
    field and leaves nothing behind in the folder it was being written in."""
    base, _ = api
    _, client, _, summary = built
    region = summary["rois"][1]["region"]
    box = (
        region["min"]["x_um"] + 16,
        region["min"]["y_um"] + 16,
        region["min"]["x_um"] + 56,
        region["min"]["y_um"] + 46,
    )
    query = {"region": ",".join(map(str, box)), "pixel_size_um": "0.25"}
    answer = requests.get(f"{base}/api/specimens/synthetic/export", params={**query, "format": "x3p"}, timeout=120)
    assert answer.status_code == 200, answer.text
    (tmp_path / "http.x3p").write_bytes(answer.content)
    client.export_area("synthetic", tmp_path / "grpc.x3p", region_um=box, pixel_size_um=0.25)
    over_http, over_grpc = read_x3p(tmp_path / "http.x3p"), read_x3p(tmp_path / "grpc.x3p")
    assert over_http.z_um.shape == (121, 161) and over_http.step_x_um == pytest.approx(0.25)
    np.testing.assert_array_equal(over_http.z_um, over_grpc.z_um)
    assert over_http.origin_um == pytest.approx(box[:2])
    assert Surface.load(tmp_path / "http.x3p").level().Sa() == pytest.approx(
        client.roughness("synthetic", region_um=box)["Sa"], rel=1e-6
    )

    answer = requests.get(
        f"{base}/api/specimens/synthetic/export",
        params={**query, "format": "stl", "solid": "true", "units": "mm"},
        timeout=120,
    )
    assert answer.status_code == 200 and int(answer.headers["Content-Length"]) == len(answer.content)
    mesh = trimesh.load(io.BytesIO(answer.content), file_type="stl", force="mesh")
    assert mesh.is_watertight and mesh.is_volume
    assert (mesh.bounds[1] - mesh.bounds[0])[:2] == pytest.approx(
        [0.04, 0.03], rel=1e-4
    )  # 160 and 120 steps of 0.25 µm, in mm

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "scratch"))  # where the endpoint writes before it streams
    (tmp_path / "scratch").mkdir()
    refused = requests.get(
        f"{base}/api/specimens/synthetic/export", params={**query, "format": "tif", "solid": "true"}, timeout=120
    )
    assert refused.status_code == 400 and refused.json()["field"] == "solid"
    assert list((tmp_path / "scratch").iterdir()) == []


def test_tokens_and_scopes_are_grpcs_and_checked_before_the_body(built, tmp_path, input_directory):
    _, _, data, _ = built
    copy = tmp_path / "data"
    shutil.copytree(data, copy)
    server, endpoint, base = _serve(copy, TOKENS)
    try:
        read, write = {"Authorization": "Bearer read-secret"}, {"Authorization": "Bearer write-secret"}
        assert requests.get(f"{base}/api/specimens/synthetic/roughness?roi=zoom", timeout=60).status_code == 401
        assert (
            requests.get(f"{base}/api/specimens/synthetic/roughness?roi=zoom&token=read-secret", timeout=60).status_code
            == 200
        )
        assert requests.get(f"{base}/api/openapi.json", timeout=30).status_code == 200  # the document is public

        # A gigabyte announced and a few bytes sent: the refusal comes without waiting for the rest.
        connection = http.client.HTTPConnection("127.0.0.1", endpoint.server_port, timeout=10)
        connection.putrequest("POST", "/api/uploads")
        for name, value in {
            **read,
            "Content-Type": "multipart/form-data; boundary=x",
            "Content-Length": str(10**9),
        }.items():
            connection.putheader(name, value)
        connection.endheaders(b"--x\r\n")
        early = connection.getresponse()
        assert early.status == 403 and json.loads(early.read())["field"] == "authorization"
        connection.close()
        refused = requests.post(
            f"{base}/api/uploads", files=_upload_parts(input_directory, "refused"), headers=read, timeout=60
        )
        assert refused.status_code == 403 and refused.json()["field"] == "authorization"
        assert (
            requests.post(f"{base}/api/jobs", json={"upload_id": "0" * 32}, headers=read, timeout=30).status_code == 403
        )
        accepted = requests.post(
            f"{base}/api/uploads", files=_upload_parts(input_directory, "accepted"), headers=write, timeout=60
        )
        assert accepted.status_code == 201
        assert sorted(path.name for path in (copy / "uploads").iterdir()) == [accepted.json()["upload_id"]]
    finally:
        endpoint.shutdown()
        server.stop(grace=None)


# Fuzzing ###########################################################################################
# Every operation of the document, positive and negative examples, a few each (no shrinking): run
# with hypothesis directly, as schemathesis' lazy pytest loader does not run under pytest 9.


@pytest.fixture(scope="module")
def operations(api):
    base, _ = api
    schema = schemathesis.openapi.from_url(f"{base}/api/openapi.json")
    return [result.ok() for result in schema.get_all_operations()]


def test_the_fuzzer_sees_every_documented_operation(operations):
    """All but the document's own, which schemathesis, having loaded the schema from it, leaves out."""
    assert {operation.label for operation in operations} == {
        f"{method.upper()} {path}" for path, item in openapi.document()["paths"].items() for method in item
    } - {"GET /api/openapi.json"}


@pytest.mark.parametrize("mode", list(GenerationMode))
def test_every_operation_answers_bad_input_with_a_json_4xx_naming_the_field(api, operations, mode):
    """Positive examples run twice: as generated, and with the example specimen's id, so that the
    queries, exports and reports run on real data with the generated parameters."""
    _, data = api
    statuses: dict[int, int] = {}
    unsatisfiable = []

    def check(case, operation):
        response = case.call(timeout=300)
        statuses[response.status_code] = statuses.get(response.status_code, 0) + 1
        case.validate_response(
            response,
            checks=[
                not_a_server_error,
                status_code_conformance,
                content_type_conformance,
                response_schema_conformance,
                *([negative_data_rejection] if mode is GenerationMode.NEGATIVE else []),
            ],
        )
        if 400 <= response.status_code < 500:
            error = response.json()
            assert set(error) == {"error", "field"} and error["error"], (operation.label, error)
            if response.status_code == 400:
                assert error["field"], (operation.label, error)

    def fuzzer(operation):
        @given(case=operation.as_strategy(generation_mode=mode))
        @settings(
            max_examples=FUZZ_EXAMPLES,
            deadline=None,
            phases=[Phase.explicit, Phase.generate],
            database=None,
            suppress_health_check=list(HealthCheck),
        )
        def fuzz(case):
            check(case, operation)
            # The example specimen stands in for a generated id, but is not deleted: later operations query it.
            if (
                mode is GenerationMode.POSITIVE
                and "specimen_id" in (case.path_parameters or {})
                and case.method.upper() != "DELETE"
            ):
                case.path_parameters["specimen_id"] = "synthetic"
                check(case, operation)

        return fuzz

    for operation in operations:
        try:
            fuzzer(operation)()
        except Unsatisfiable:  # nothing in the operation can be made invalid (no parameters, no body)
            unsatisfiable.append(operation.label)
    print(
        f"\nschemathesis, {mode} examples: {sum(statuses.values())} requests over {len(operations)} operations, "
        f"statuses {dict(sorted(statuses.items()))}; none possible for {unsatisfiable or 'none'}"
    )
    assert set(unsatisfiable) <= {"GET /api/specimens", "GET /api/jobs"}  # no parameters, no body
    assert not list((data / "uploads").glob(".staging-*")) and not list((data / "specimens").glob(".staging-*"))
    store = SpecimenStore(data)
    for specimen_id in store.ids():  # nothing half-written: every stored specimen loads whole
        assert store.load(specimen_id).surface.rois

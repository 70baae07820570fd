"""What a hostile probe of a live server found, fixed: a request id reused for other content is
refused (gRPC and the HTTP job API), exports and reports leave no temporaries outside the data
directory and a killed one's are removed at the next start, profiles blame the points when the
points are at fault, meshes refuse negative uncertainties, and specimens can be deleted."""

from __future__ import annotations

import asyncio
import hashlib
import json
import os
import signal
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import grpc
import numpy as np
import pytest
import requests
from aiohttp import web
from aiohttp.test_utils import TestClient, TestServer
from conftest import fracture_pair, rough_with_hole, tiff_bytes, write_small_specimen

from fractoscope import report
from fractoscope.client import ClientError
from fractoscope.errors import InvalidInputError, NotFoundError
from fractoscope.formats import exports as export_formats
from fractoscope.http.responses import file_response, off_loop
from fractoscope.http.server import start_http_server
from fractoscope.server.config import ServerConfig
from fractoscope.server.main import create_server
from fractoscope.specimen.exports import export_height_map
from fractoscope.specimen.quadtree import TileKey
from fractoscope.store.folder import SpecimenStore
from fractoscope.store.scratch import scratch_folder
from fractoscope.tiles import messages as tile_messages
from fractoscope.tiles import servicer as tile_servicer
from fractoscope.v1 import common_pb2, tiles_pb2

ROOT_TILE = TileKey(0, 0, 0)


def _overview(pixel_size_um: float = 0.1, seed: int = 21) -> tiles_pb2.RoiSpec:
    """A 128 px pair as one ROI, quick to build."""
    pair = fracture_pair(size_px=128, seed=seed)
    spec = tiles_pb2.RoiSpec(id="overview", pixel_size_um=pixel_size_um)
    for image, tilt_deg in ((pair.first, -5.0), (pair.second, 5.0)):
        item = spec.images.add(tilt_deg=tilt_deg)
        item.image.content = tiff_bytes(image)
    return spec


# --- A request id names one content ---


def test_the_content_digest_is_that_of_the_whole_request_without_its_id():
    """request_digest feeds the request one ROI at a time; it must hash the same bytes as the
    whole request serialized without its id, and feed every field the request has."""
    request = tiles_pb2.ReconstructSpecimenRequest(specimen_id="steel-1", request_id="lims-1")
    request.rois.add(id="overview", pixel_size_um=0.1, magnification=100.0)
    request.rois.add(id="zoom", parent="overview", magnification=400.0).images.add(tilt_deg=5.0)
    request.unmeasured = common_pb2.UNMEASURED_AREAS_FLAT
    whole = tiles_pb2.ReconstructSpecimenRequest()
    whole.CopyFrom(request)
    whole.ClearField("request_id")
    expected = hashlib.sha256(whole.SerializeToString(deterministic=True)).hexdigest()
    assert tile_messages.request_digest(request) == expected
    assert {field.name for field in tiles_pb2.ReconstructSpecimenRequest.DESCRIPTOR.fields} == {
        "specimen_id",
        "rois",
        "request_id",
        "unmeasured",
    }, "request_digest feeds specimen_id and rois: feed a new field too"
    request.rois[1].magnification = 401.0
    assert tile_messages.request_digest(request) != expected


@pytest.mark.timeout(300)
def test_a_reused_request_id_with_other_content_is_refused_and_the_same_content_gets_the_stored_build(client, tmp_path):
    description = tmp_path / "data" / "specimens" / "steel-r" / "specimen.json"
    first = client.reconstruct_specimen("steel-r", [_overview()], request_id="lims-r")
    built_at = description.stat().st_mtime_ns
    assert client.reconstruct_specimen("steel-r", [_overview()], request_id="lims-r") == first
    with pytest.raises(ClientError) as refused:
        client.reconstruct_specimen("steel-r", [_overview(pixel_size_um=0.12)], request_id="lims-r")
    assert refused.value.code == grpc.StatusCode.ALREADY_EXISTS and "request_id 'lims-r'" in str(refused.value)
    with pytest.raises(ClientError) as emptied:  # no ROIs is other content too, not a way to look the build up
        client.reconstruct_specimen("steel-r", [], request_id="lims-r")
    assert emptied.value.code == grpc.StatusCode.ALREADY_EXISTS
    assert description.stat().st_mtime_ns == built_at and client.get_specimen("steel-r") == first


@pytest.mark.timeout(300)
def test_a_concurrent_repeat_with_other_content_is_refused_instead_of_joining_the_build(client, monkeypatch):
    started, release, builds = threading.Event(), threading.Event(), []
    build = tile_servicer.reconstruct_specimen

    def held(*args, **kwargs):
        builds.append(kwargs["request_id"])
        started.set()
        release.wait(30)
        return build(*args, **kwargs)

    monkeypatch.setattr(tile_servicer, "reconstruct_specimen", held)
    with ThreadPoolExecutor(2) as pool:
        first = pool.submit(client.reconstruct_specimen, "steel-c", [_overview()], request_id="lims-c")
        assert started.wait(60)
        try:
            with pytest.raises(ClientError) as refused:
                client.reconstruct_specimen("steel-c", [_overview(pixel_size_um=0.12)], request_id="lims-c")
            joined = pool.submit(client.reconstruct_specimen, "steel-c", [_overview()], request_id="lims-c")
        finally:
            release.set()
        assert first.result() == joined.result()
    assert refused.value.code == grpc.StatusCode.ALREADY_EXISTS and "request_id 'lims-c'" in str(refused.value)
    assert builds == ["lims-c"]  # the repeat with the same content joined the one build


def _upload(base: str, manifest: dict, images: dict[str, bytes]) -> str:
    parts = [("manifest", (None, json.dumps(manifest), "application/json"))] + [
        ("images", (name, content, "image/tiff")) for name, content in images.items()
    ]
    uploaded = requests.post(f"{base}/api/uploads", files=parts, timeout=60)
    assert uploaded.status_code == 201, uploaded.text
    return uploaded.json()["upload_id"]


def _finished_job(base: str, upload_id: str, request_id: str) -> dict:
    submitted = requests.post(f"{base}/api/jobs", json={"upload_id": upload_id, "request_id": request_id}, timeout=30)
    assert submitted.status_code == 202, submitted.text
    deadline = time.monotonic() + 240
    while (job := requests.get(base + submitted.headers["Location"], timeout=30).json())["state"] not in (
        "succeeded",
        "failed",
    ):
        assert time.monotonic() < deadline, job
        time.sleep(0.5)
    return job


@pytest.mark.server
@pytest.mark.timeout(300)
def test_the_http_job_api_refuses_a_reused_request_id_with_other_content(tmp_path):
    store = SpecimenStore(tmp_path / "data")
    server, port = create_server(ServerConfig(address="127.0.0.1:0"), store=store)
    server.start()
    endpoint = start_http_server(store, grpc_address=f"127.0.0.1:{port}")
    base = f"http://127.0.0.1:{endpoint.server_port}"
    pair = fracture_pair(size_px=128, seed=21)
    images = {"left.tif": tiff_bytes(pair.first), "right.tif": tiff_bytes(pair.second)}
    roi = {"id": "overview", "left": "left.tif", "right": "right.tif", "tilt_deg": [-5.0, 5.0], "pixel_size_um": 0.1}
    try:
        first = _finished_job(base, _upload(base, {"specimen": "steel-h", "rois": [roi]}, images), "lims-h")
        assert first["state"] == "succeeded", first["error"]
        other = {"specimen": "steel-h", "rois": [{**roi, "pixel_size_um": 0.12}]}
        refused = requests.post(
            f"{base}/api/jobs", json={"upload_id": _upload(base, other, images), "request_id": "lims-h"}, timeout=30
        )
        assert refused.status_code == 409 and refused.json()["field"] == "request_id", refused.text
        assert "request_id 'lims-h'" in refused.json()["error"]
        again = _finished_job(base, _upload(base, {"specimen": "steel-h", "rois": [roi]}, images), "lims-h")
        assert again["state"] == "succeeded" and again["specimen"] == first["specimen"]
    finally:
        endpoint.shutdown()
        server.stop(grace=None)


# --- Temporaries under the data directory ---


def test_grpc_exports_and_reports_write_under_the_data_directory_and_leave_nothing(client, tmp_path, monkeypatch):
    data = tmp_path / "data"
    written = []
    write_surface = export_formats.write_surface

    def recorded_surface(path, *args, **kwargs):
        written.append(Path(path))
        return write_surface(path, *args, **kwargs)

    def recorded_report(specimen, directory, **kwargs):
        written.append(directory / "report.html")
        written[-1].write_text("<html></html>")
        return written[-1]

    monkeypatch.setattr(export_formats, "write_surface", recorded_surface)
    monkeypatch.setattr(report, "write_report", recorded_report)
    write_small_specimen(SpecimenStore(data), "steel-1")
    z_um, _ = rough_with_hole(64)
    client.export_height_map(z_um, tmp_path / "map.x3p", pixel_size_um=0.1)
    client.report("steel-1", tmp_path / "report.html")
    assert [path.parent.parent for path in written] == [data / "tmp"] * 2
    assert [path.parent.name.split("-")[:2] for path in written] == [
        ["export", f"{os.getpid()}.{_start_ticks(os.getpid())}"],
        ["report", f"{os.getpid()}.{_start_ticks(os.getpid())}"],
    ]
    assert (tmp_path / "map.x3p").stat().st_size > 0 and list((data / "tmp").iterdir()) == []


@pytest.mark.server
def test_http_files_are_written_under_the_given_scratch_root_and_removed_once_sent(tmp_path):
    directories = []

    def write(directory: Path) -> tuple[Path, str]:
        directories.append(directory)
        (directory / "height.csv").write_text("1,2\n")
        return directory / "height.csv", "text/csv"

    async def fetch(scratch_root: Path) -> str:
        async def handler(request: web.Request) -> web.StreamResponse:
            return await file_response(request, off_loop, write, scratch_root=scratch_root)

        app = web.Application()
        app.router.add_get("/file", handler)
        async with TestClient(TestServer(app)) as http:
            answer = await http.get("/file")
            return await answer.text()

    assert asyncio.run(fetch(tmp_path / "data" / "tmp")) == "1,2\n"
    assert directories[0].parent == tmp_path / "data" / "tmp" and not directories[0].exists()


# A process that makes a scratch folder, writes part of an export into it and is killed.
_KILLED_EXPORT = """
import os, signal, sys
from pathlib import Path
from fractoscope.store.scratch import scratch_folder

with scratch_folder(Path(sys.argv[1]), "export") as directory:
    (directory / "part.stl").write_bytes(bytes(1000))
    os.kill(os.getpid(), signal.SIGKILL)
"""
# A process that makes a scratch folder and holds it until its input closes.
_RUNNING_EXPORT = """
import sys
from pathlib import Path
from fractoscope.store.scratch import scratch_folder

with scratch_folder(Path(sys.argv[1]), "export") as directory:
    print(directory.name, flush=True)
    sys.stdin.read()
"""


def test_the_scratch_of_a_killed_export_goes_at_the_next_start_and_that_of_running_processes_stays(tmp_path):
    scratch = tmp_path / "data" / "tmp"
    killed = subprocess.run([sys.executable, "-c", _KILLED_EXPORT, str(scratch)], timeout=60)
    assert killed.returncode == -signal.SIGKILL
    (abandoned,) = scratch.iterdir()
    assert (abandoned / "part.stl").is_file()
    reused_pid = scratch / f"export-{os.getpid()}.1-abc"  # this pid, but a process started at another time
    reused_pid.mkdir()
    unknown = scratch / "notes"  # not a scratch folder: not ours to remove
    unknown.mkdir()
    running = subprocess.Popen(
        [sys.executable, "-c", _RUNNING_EXPORT, str(scratch)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    try:
        other = scratch / running.stdout.readline().strip()
        with scratch_folder(scratch, "report") as own:
            store = SpecimenStore(tmp_path / "data")
            assert store.scratch_root == scratch
            assert sorted(scratch.iterdir()) == sorted([other, own, unknown])
    finally:
        running.communicate("", timeout=60)
    assert sorted(scratch.iterdir()) == [unknown]


def _start_ticks(pid: int) -> str:
    return Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()[19]


# --- Profiles blame the points when the points are at fault ---


@pytest.mark.parametrize(
    "points, spacing_um, field",
    [
        ([(1e308, 1e308), (-1e308, -1e308)], 0.0, "points"),
        ([(1e308, 1e308), (-1e308, -1e308)], 1.0, "points"),
        (np.random.default_rng(3).uniform(0.0, 1000.0, (100_000, 2)), 0.0, "points"),
        ([(0.0, 0.0), (1e9, 0.0)], 0.0, "points"),  # far beyond the specimen of 12 x 8 µm
        ([(0.0, 0.0), (1e9, 0.0)], 2.0, "points"),
        ([(2.0, 3.0), (12.0, 3.0)], 1e-6, "spacing_um"),  # the spacing is at fault: the default would do
    ],
)
def test_a_profile_of_too_many_samples_names_the_input_at_fault(client, tmp_path, points, spacing_um, field):
    write_small_specimen(SpecimenStore(tmp_path / "data"), "steel-1")
    with pytest.raises(ClientError) as refused:
        client.profile("steel-1", [tuple(point) for point in points], spacing_um=spacing_um)
    assert refused.value.code == grpc.StatusCode.INVALID_ARGUMENT and refused.value.field == field


# --- Uncertainties are not negative ---


def test_a_mesh_with_a_negative_sigma_is_refused_naming_it(client):
    z_um, texture = rough_with_hole(64)
    sigma_um = np.full(z_um.shape, 0.05, np.float32)
    sigma_um[10, 10] = -0.05
    with pytest.raises(ClientError) as refused:
        client.build_mesh(z_um, texture, pixel_size_um=0.1, max_slope=5.0, sigma_um=sigma_um)
    assert refused.value.code == grpc.StatusCode.INVALID_ARGUMENT and refused.value.field == "height_map.sigma_um"
    sigma_um[10, 10] = np.nan  # unknown is allowed
    tiles, _ = client.build_mesh(z_um, texture, pixel_size_um=0.1, max_slope=5.0, sigma_um=sigma_um)
    assert tiles


def test_an_export_of_a_map_with_a_negative_sigma_is_refused_naming_it(tmp_path):
    z_um, _ = rough_with_hole(64)
    with pytest.raises(InvalidInputError) as refused:
        export_height_map(tmp_path, z_um, file_format="x3p", pixel_size_um=0.1, sigma_um=np.full(z_um.shape, -1.0))
    assert refused.value.field == "height_map.sigma_um" and list(tmp_path.iterdir()) == []


# --- Deleting a specimen ---


def test_a_deleted_specimen_is_gone_whole_and_its_readers_get_not_found(tmp_path):
    store = SpecimenStore(tmp_path)
    write_small_specimen(store, "steel-1", height_um=1.0)
    write_small_specimen(store, "steel-2", height_um=2.0)
    held = store.load("steel-1")
    heights = held.heights("overview").z_um  # read before the deletion: still the reader's
    store.delete("steel-1")
    assert store.ids() == ["steel-2"] and sorted(p.name for p in store.root.iterdir()) == ["steel-2"]
    with pytest.raises(NotFoundError) as gone:
        store.load("steel-1")
    assert gone.value.field == "specimen_id"
    with pytest.raises(NotFoundError) as unread:  # not a FileNotFoundError: a 404, not a 500
        held.tile_bytes(ROOT_TILE.uri)
    assert unread.value.field == "specimen_id"
    np.testing.assert_array_equal(heights, np.full((16, 24), 1.0, np.float32))
    write_small_specimen(store, "steel-1", height_um=3.0)  # the id can be built again
    assert store.load("steel-1").tile_bytes(ROOT_TILE.uri) == b"glTF\x03"


def test_deleting_an_absent_or_malformed_id_names_it_and_removes_nothing(tmp_path):
    store = SpecimenStore(tmp_path)
    write_small_specimen(store, "steel-1")
    with pytest.raises(NotFoundError) as absent:
        store.delete("steel-2")
    assert absent.value.field == "specimen_id"
    with pytest.raises(InvalidInputError) as malformed:
        store.delete("..")
    assert malformed.value.field == "specimen_id" and store.ids() == ["steel-1"]


def test_a_deletion_killed_before_its_removal_is_finished_at_the_next_start_not_undone(tmp_path):
    store = SpecimenStore(tmp_path)
    write_small_specimen(store, "steel-1")
    (store.root / "steel-1").rename(store.root / ".deleted-steel-1-0123abcd")  # what a deletion renames first
    restarted = SpecimenStore(tmp_path)
    assert restarted.recover() == ([], 1)
    assert restarted.ids() == [] and list(restarted.root.iterdir()) == []


def test_a_deleted_specimen_is_not_found_over_grpc(client, tmp_path):
    store = SpecimenStore(tmp_path / "data")
    write_small_specimen(store, "steel-1")
    assert client.get_specimen("steel-1")["id"] == "steel-1"
    store.delete("steel-1")
    with pytest.raises(ClientError) as gone:
        client.get_specimen("steel-1")
    assert gone.value.code == grpc.StatusCode.NOT_FOUND

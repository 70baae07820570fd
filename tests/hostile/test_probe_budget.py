"""One budget for every front end (issue 49, items 1 to 3), probed against fracto-server processes
of their own, whose memory and CPU are read from /proc:

1. an HTTP upload of a 1.1 MB zlib float32 16384² TIFF, twice, decoded with no budget (RSS 0.5 to
   7.7 GB, no answer in 120 s) where gRPC refused it: now refused as ReconstructSpecimen refuses
   it, 413 before any image is decoded;
2. exports and reports of unbounded size (a 995 KB npz exported as a 24 GB STL): now 413 from
   their estimate before a byte is written;
3. slow analyses over gRPC that held every worker (GetTile timed out) and ran on after their
   callers went: now on threads of their own under the budget, stopped when their callers go.

The bombs are made on the fly."""

from __future__ import annotations

import io
import json
import threading
import time

import grpc
import numpy as np
import pytest
import requests
import tifffile
from probe_servers import READ, READ_METADATA, WRITE, write_map_specimen

from fractoscope.rpc import wire
from fractoscope.store.folder import SpecimenStore
from fractoscope.v1 import tiles_pb2, tiles_pb2_grpc

MB = 1 << 20
HANG_S = 120  # a hang bound, not a timing: `make load` measures the times


def zlib_float_tiff(side_px: int) -> bytes:
    """A float32 TIFF of `side_px`² zeros, zlib-compressed tile by tile: about a megabyte that
    declares (and decodes to) gigabytes; never held whole here."""
    tile = np.zeros((512, 512), np.float32)
    tiles = (tile for _ in range((side_px // 512) ** 2))
    buffer = io.BytesIO()
    tifffile.imwrite(buffer, tiles, shape=(side_px, side_px), dtype=np.float32, tile=(512, 512), compression="zlib")
    return buffer.getvalue()


def _idle_cpu_s(server, window_s: float = 3.0) -> float:
    """CPU seconds the server spends over `window_s`."""
    before = server.cpu_s()
    time.sleep(window_s)
    return server.cpu_s() - before


def test_an_upload_of_a_decompression_bomb_is_refused_before_decoding(server_process):
    server = server_process(environment={"FRACTO_MAX_REQUEST_MB": "4096"})
    bomb = zlib_float_tiff(16384)
    assert len(bomb) < 8 * MB
    manifest = {
        "specimen": "bomb",
        "rois": [{"id": "o", "left": "a.tif", "right": "b.tif", "tilt_deg": [-5, 5], "pixel_size_um": 0.1}],
    }
    parts = [("manifest", (None, json.dumps(manifest), "application/json"))]
    parts += [("images", (name, bomb, "image/tiff")) for name in ("a.tif", "b.tif")]
    rss_before = server.rss_bytes()
    answers = []

    def upload():
        answers.append(requests.post(f"{server.http}/api/uploads", files=parts, headers=WRITE, timeout=HANG_S))

    callers = [threading.Thread(target=upload) for _ in range(2)]  # two at once, as the probe sent them
    for caller in callers:
        caller.start()
    for caller in callers:
        caller.join()
    for answer in answers:
        assert answer.status_code == 413, answer.text
        assert "16384 x 16384" in answer.json()["error"] and "FRACTO_MAX_REQUEST_MB" in answer.json()["error"]
    assert server.peak_rss_bytes() - rss_before < 200 * MB
    assert not list((server.data / "uploads").iterdir())


@pytest.fixture
def capped(server_process, tmp_path):
    """A server writing files of 32 MiB at most, with a 256² specimen at 0.5 µm/px."""
    write_map_specimen(SpecimenStore(tmp_path / "data"), "capped", size_px=256)
    return server_process(environment={"FRACTO_MAX_FILE_MB": "32"})


def _scratch_files(server) -> list:
    scratch = server.data / "tmp"
    return [path for path in scratch.rglob("*") if path.is_file()] if scratch.is_dir() else []


@pytest.mark.parametrize(
    "query",
    [
        {"format": "stl", "region": "0,0,127,127", "pixel_size_um": "0.05"},  # 2541² points: ~650 MB
        {"format": "obj", "solid": "true", "region": "0,0,127,127", "pixel_size_um": "0.1"},
        {"format": "csv", "region": "0,0,127,127", "pixel_size_um": "0.02"},
    ],
)
def test_an_export_over_the_file_cap_is_413_before_a_byte_is_written(capped, query):
    """Once 205 s and 24 GB of scratch for a 16000² STL; eighteen at once would fill the disk."""
    answer = requests.get(f"{capped.http}/api/specimens/capped/export", params=query, headers=READ, timeout=HANG_S)
    assert answer.status_code == 413, answer.text
    assert "FRACTO_MAX_FILE_MB" in answer.json()["error"]
    assert _scratch_files(capped) == []
    small = requests.get(
        f"{capped.http}/api/specimens/capped/export", params={"format": "x3p"}, headers=READ, timeout=HANG_S
    )
    assert small.status_code == 200 and small.content[:2] == b"PK"  # within the cap: written and sent


def test_an_uploaded_map_whose_export_exceeds_the_cap_is_413_before_it_is_decoded(capped):
    """A 4000² npz of zeros (a few hundred kB) asked for as STL: 1.6 GB by its headers."""
    buffer = io.BytesIO()
    np.savez_compressed(buffer, z_um=np.zeros((4000, 4000), np.float32), pixel_size_um=np.float64(0.1))
    rss_before = capped.rss_bytes()
    answer = requests.post(
        f"{capped.http}/api/exports",
        files=[("height_map", ("map.npz", buffer.getvalue())), ("format", (None, "stl"))],
        headers=READ,
        timeout=HANG_S,
    )
    assert answer.status_code == 413, answer.text
    assert capped.peak_rss_bytes() - rss_before < 200 * MB  # nothing decoded: 64 MB of heights, 1.6 GB of STL
    assert _scratch_files(capped) == []


def test_a_report_and_an_export_over_the_cap_are_refused_over_grpc_and_http(capped):
    answer = requests.get(f"{capped.http}/api/specimens/capped/report", headers=READ, timeout=HANG_S)
    assert answer.status_code == 413, answer.text
    with grpc.insecure_channel(capped.grpc_address) as channel:
        stub = tiles_pb2_grpc.TileServiceStub(channel)
        report = tiles_pb2.GetReportRequest(area=tiles_pb2.SpecimenArea(specimen_id="capped"))
        area = tiles_pb2.SpecimenArea(specimen_id="capped", region=wire.region_message((0.0, 0.0, 127.0, 127.0)))
        export = tiles_pb2.ExportRequest(specimen=area, format=tiles_pb2.EXPORT_FORMAT_STL, pixel_size_um=0.05)
        for call in (lambda: stub.GetReport(report, metadata=READ_METADATA, timeout=HANG_S),
                     lambda: stub.Export(export, metadata=READ_METADATA, timeout=HANG_S)):  # fmt: skip
            with pytest.raises(grpc.RpcError) as refused:
                list(call())
            assert refused.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
            assert "FRACTO_MAX_FILE_MB" in refused.value.details()
    assert _scratch_files(capped) == []


def _slow_analyses(server, count: int, deadline_s: float) -> tuple[list, list[float]]:
    """`count` cylinder-form GetRoughness calls started at once (futures), and GetTile's answer
    times (s) while they run, three calls."""
    channel = grpc.insecure_channel(server.grpc_address)
    stub = tiles_pb2_grpc.TileServiceStub(channel)
    chain = tiles_pb2.SurfaceChain(form=tiles_pb2.FORM_CYLINDER)
    request = tiles_pb2.GetRoughnessRequest(specimen_id="slow", chain=chain)
    calls = [stub.GetRoughness.future(request, metadata=READ_METADATA, timeout=deadline_s) for _ in range(count)]
    time.sleep(2)  # under way
    tile_s = []
    for _ in range(3):
        started = time.monotonic()
        stub.GetTile(tiles_pb2.GetTileRequest(specimen_id="slow", uri="tiles/0/0/0.glb"), metadata=READ_METADATA,
                     timeout=HANG_S)  # fmt: skip
        stub.GetSpecimen(tiles_pb2.GetSpecimenRequest(specimen_id="slow"), metadata=READ_METADATA, timeout=HANG_S)
        tile_s.append(time.monotonic() - started)
    return calls, tile_s


def _settles(server, within_s: float = 60.0) -> bool:
    """Whether the server's CPU falls idle (< 0.3 s over 3 s) within `within_s` (a hang bound)."""
    deadline = time.monotonic() + within_s
    while time.monotonic() < deadline:
        if _idle_cpu_s(server) < 0.3:
            return True
    return False


def test_slow_analyses_leave_tiles_answering_and_stop_when_their_callers_go(server_process, tmp_path):
    """Four cylinder-form roughness analyses of a 512² map (seconds each, two CPUs): tiles and
    specimens are answered meanwhile, and once the callers cancel, the CPU falls idle (it stayed
    busy a minute after twelve such callers had gone)."""
    write_map_specimen(SpecimenStore(tmp_path / "data"), "slow", size_px=512)
    server = server_process()
    calls, _ = _slow_analyses(server, count=4, deadline_s=HANG_S)
    assert not any(call.done() for call in calls)  # the analyses are still running: the tiles did not wait
    for call in calls:
        call.cancel()
    assert _settles(server)


@pytest.mark.load
def test_twelve_slow_analyses_with_a_deadline_leave_tiles_answering_and_the_cpu_idle_after(server_process, tmp_path):
    """The probe's case: twelve GetRoughness calls with a cylinder form and a 60 s deadline."""
    write_map_specimen(SpecimenStore(tmp_path / "data"), "slow", size_px=1024)
    server = server_process()
    calls, tile_s = _slow_analyses(server, count=12, deadline_s=60)
    codes = []
    for call in calls:
        try:
            call.result()
            codes.append(grpc.StatusCode.OK)
        except grpc.RpcError as error:
            codes.append(error.code())
    gone = time.monotonic()
    assert set(codes) <= {grpc.StatusCode.OK, grpc.StatusCode.DEADLINE_EXCEEDED, grpc.StatusCode.RESOURCE_EXHAUSTED}
    assert _settles(server), "the CPU stayed busy after every caller had gone"
    print(f"GetTile+GetSpecimen while 12 analyses ran: {[round(t, 3) for t in tile_s]} s; "
          f"idle {time.monotonic() - gone:.1f} s after the callers went; {codes}")  # fmt: skip

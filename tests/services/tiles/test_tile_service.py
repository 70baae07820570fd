"""The tile service end to end: a synthetic two-magnification specimen built over real gRPC
servers on loopback, checked against the surface it was rendered from."""

from __future__ import annotations

import gzip
import json
import os
import urllib.error
import urllib.request

import grpc
import numpy as np
import pytest
from conftest import fracture_pair, tiff_bytes, validate_glbs
from scipy import ndimage

from fractoscope import synthetic
from fractoscope.client import ClientError, FractoscopeClient
from fractoscope.client.manifest import load_manifest
from fractoscope.http.server import start_http_server
from fractoscope.rpc import wire
from fractoscope.server.config import ServerConfig
from fractoscope.server.main import create_server
from fractoscope.specimen.tileset import content_uris
from fractoscope.store.folder import SpecimenStore
from fractoscope.synthetic.examples import MULTISCALE_MAGNIFICATIONS
from fractoscope.v1 import common_pb2, tiles_pb2

OVERVIEW_MAG, ZOOM_MAG = MULTISCALE_MAGNIFICATIONS


def true_heights(truth: synthetic.MultiscaleSpecimen, x_um: np.ndarray, y_um: np.ndarray) -> np.ndarray:
    """The rendered surface at specimen points: the ROI's truth where the ROI is, the overview's elsewhere."""
    overview = ndimage.map_coordinates(
        truth.overview.z_seen_um, [y_um / truth.overview_pixel_size_um, x_um / truth.overview_pixel_size_um], order=1
    )
    origin_x, origin_y = (v * truth.overview_pixel_size_um for v in truth.roi_origin_px)
    roi_col, roi_row = (x_um - origin_x) / truth.roi_pixel_size_um, (y_um - origin_y) / truth.roi_pixel_size_um
    inside = (
        (roi_col >= 0)
        & (roi_row >= 0)
        & (roi_col <= truth.roi.z_seen_um.shape[1] - 1)
        & (roi_row <= truth.roi.z_seen_um.shape[0] - 1)
    )
    roi = ndimage.map_coordinates(truth.roi.z_seen_um, [roi_row, roi_col], order=1)
    return np.where(inside, roi, overview)


def test_roi_is_found_automatically_within_one_overview_pixel(built):
    truth, _, _, summary = built
    zoom = summary["rois"][1]
    found = (zoom["region"]["min"]["x_um"], zoom["region"]["min"]["y_um"])
    error_px = (
        np.subtract(found, np.multiply(truth.roi_origin_px, truth.overview_pixel_size_um))
        / truth.overview_pixel_size_um
    )
    assert np.hypot(*error_px) < 1.0, error_px
    assert zoom["registration_score"] > 0.5
    assert zoom["alignment_residual_um"] < 0.05 * np.ptp(truth.roi.z_seen_um)


def test_profile_follows_the_true_surface_across_magnifications(built):
    truth, client, _, _ = built
    start, end = (100.0, 200.0), (450.0, 260.0)  # crosses the ROI (x 236 to 364 µm)
    profile = client.profile("synthetic", [start, end])
    assert {"overview", "zoom"} <= set(profile.source)
    assert np.isclose(profile.distance_um[1] - profile.distance_um[0], truth.roi_pixel_size_um)
    fraction = profile.distance_um / profile.distance_um[-1]
    x_um = start[0] + fraction * (end[0] - start[0])
    y_um = start[1] + fraction * (end[1] - start[1])
    expected = true_heights(truth, x_um, y_um)
    known = np.isfinite(profile.z_um)
    assert known.mean() > 0.97
    difference = profile.z_um[known] - expected[known]
    difference -= difference.mean()  # heights are relative
    height_range = np.ptp(expected)
    assert np.sqrt(np.mean(difference**2)) < 0.02 * height_range
    assert set(profile.parameters) >= {"Ra", "Rq", "Rz", "Rsk", "Rku"}
    assert profile.parameters["Rz"] > profile.parameters["Rq"] > profile.parameters["Ra"] > 0


def test_no_step_where_the_roi_meets_the_overview(built):
    """Across the ROI's left border the surface changes no faster than anywhere else on the line.
    A step from joining the two would show on every line; a matching error shows on one, so the
    lines' medians are compared."""
    _, client, _, summary = built
    region = summary["rois"][1]["region"]
    border_x = region["min"]["x_um"]
    in_blend, elsewhere = [], []
    for y_um in np.linspace(region["min"]["y_um"] + 10, region["max"]["y_um"] - 10, 12):
        line = client.profile("synthetic", [(border_x - 40, y_um), (border_x + 40, y_um)])
        steps = np.abs(np.diff(line.z_um))
        x_um = border_x - 40 + line.distance_um[1:]
        blend = (x_um > border_x - 1) & (x_um < border_x + 12)  # the 32-pixel ramp of the ROI
        in_blend.append(np.nanmax(steps[blend]))
        elsewhere.append(np.nanmax(steps[~blend]))
    assert np.median(in_blend) <= 1.2 * np.median(elsewhere), (in_blend, elsewhere)


def test_profile_at_a_magnification_uses_that_resolution(built):
    _, client, _, _ = built
    profile = client.profile("synthetic", [(250.0, 200.0), (350.0, 200.0)], magnification=OVERVIEW_MAG)
    assert np.isclose(profile.distance_um[1], 1.0)  # the overview's pixel size


def test_sa_of_the_roi_and_of_a_region_match_the_truth(built):
    truth, client, _, summary = built
    zoom = client.roughness("synthetic", roi="zoom")
    true_sa = _sa(truth.roi.z_seen_um)
    assert abs(zoom["Sa"] - true_sa) < 0.03 * true_sa
    region = summary["rois"][1]["region"]
    box = (region["min"]["x_um"] + 8, region["min"]["y_um"] + 8, region["max"]["x_um"] - 8, region["max"]["y_um"] - 8)
    fused = client.roughness("synthetic", region_um=box)
    y_um, x_um = np.mgrid[box[1] : box[3] : 0.25, box[0] : box[2] : 0.25]
    true_region_sa = _sa(true_heights(truth, x_um, y_um))
    assert abs(fused["Sa"] - true_region_sa) < 0.03 * true_region_sa
    assert 0.6 < zoom["hurst_exponent"] < 1.0  # rendered with H = 0.8
    assert zoom["fractal_dimension"] == pytest.approx(3 - zoom["hurst_exponent"])


def test_roughness_carries_an_uncertainty_from_sigma_and_tilt(built):
    """The manifest gives the tilts (±5°) and the default tilt uncertainty is 0.5°: ε_z = 0.5° /
    tan 5° = 10 %, which moves Sa as it moves the heights; matching noise adds a little more."""
    _, client, _, _ = built
    zoom = client.roughness("synthetic", roi="zoom")
    found = zoom["uncertainty"]
    assert zoom["tilt_rel_uncertainty"] == pytest.approx(np.radians(0.5) / np.tan(np.radians(5.0)), rel=1e-6)
    assert found["Sa"]["u_tilt"] == pytest.approx(zoom["tilt_rel_uncertainty"] * zoom["Sa"], rel=1e-6)
    assert found["Sa"]["u_total"] > found["Sa"]["u_tilt"] and 0 < found["Sa"]["u_noise"] < 0.2 * zoom["Sa"]
    assert (
        found["Ssk"]["u_tilt"] == 0 and found["Str"]["u_total"] is None
    )  # a shape parameter; one without a derivative
    assert {"Sal", "Str", "Std", "Sk", "Vmp", "Spd", "Spc"} <= set(zoom)


def test_roughness_without_an_area_is_the_overviews_over_grpc_as_over_http(built):
    _, client, _, _ = built
    overview = client.get_specimen("synthetic")["rois"][0]["id"]
    request = tiles_pb2.GetRoughnessRequest(specimen_id="synthetic")
    default = wire.response_to_roughness(client._tiles.GetRoughness(request))
    assert default["Sa"] == client.roughness("synthetic", roi=overview)["Sa"]
    request.roi = ""  # an empty id is no id, as in the HTTP API
    assert wire.response_to_roughness(client._tiles.GetRoughness(request))["Sa"] == default["Sa"]


def test_a_profile_refuses_settings_only_areal_roughness_takes(built):
    """As the HTTP API refuses their query parameters: a NaN direction was silently ignored."""
    _, client, _, _ = built
    points = [common_pb2.PointUm(x_um=10.0, y_um=10.0), common_pb2.PointUm(x_um=60.0, y_um=10.0)]
    for chain in (tiles_pb2.SurfaceChain(direction_deg=float("nan")), tiles_pb2.SurfaceChain(window_px=-3.0)):
        with pytest.raises(grpc.RpcError) as caught:
            client._tiles.GetProfile(tiles_pb2.GetProfileRequest(specimen_id="synthetic", points=points, chain=chain))
        assert caught.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "chain." in caught.value.details()


def _sa(z: np.ndarray) -> float:
    rows, cols = np.indices(z.shape)
    design = np.column_stack([rows.ravel(), cols.ravel(), np.ones(z.size)])
    plane = design @ np.linalg.lstsq(design, z.ravel(), rcond=None)[0]
    return float(np.mean(np.abs(z.ravel() - plane)))


def _nodes(node: dict):
    yield node
    for child in node.get("children", []):
        yield from _nodes(child)


def test_tileset_is_a_refining_quadtree_with_tile_metadata(built):
    _, client, _, _ = built
    tileset = client.get_tileset("synthetic")
    assert tileset["asset"]["version"] == "1.1"
    root = tileset["root"]
    assert root["content"]["uri"] and root["refine"] == "REPLACE"
    assert tileset["geometricError"] >= root["geometricError"] > 0
    kinds = {}
    for node in _nodes(root):
        assert node["metadata"]["class"] == "tile"
        properties = node["metadata"]["properties"]
        kinds.setdefault(properties["zoom"], set()).add(properties["roi"])
        for child in node.get("children", []):
            assert child["geometricError"] <= node["geometricError"]
        if not node.get("children"):
            assert node["geometricError"] == 0
    # Finest tiles inside the ROI show its data; their siblings outside upsample the overview.
    assert kinds == {"OPTICAL": {"overview", "zoom"}, "DIGITAL": {"overview"}}


def test_every_tile_is_valid_gltf(built, tmp_path):
    _, client, _, _ = built
    uris = content_uris(client.get_tileset("synthetic"))
    reports = validate_glbs([client.get_tile("synthetic", uri) for uri in uris], tmp_path)
    assert all(report["errors"] == 0 for report in reports), [r for r in reports if r["errors"]][:2]


def test_zoom_is_optical_where_the_roi_is_and_digital_elsewhere(built):
    _, client, _, _ = built
    inside = client.zoom("synthetic", (270.0, 200.0, 300.0, 240.0), magnification=ZOOM_MAG)
    assert inside and all(tile["zoom"] == "optical" and tile["roi"] == "zoom" for tile in inside)
    outside = client.zoom("synthetic", (20.0, 20.0, 60.0, 60.0), magnification=ZOOM_MAG)
    assert outside and all(tile["zoom"] == "digital" and tile["roi"] == "overview" for tile in outside)
    overview = client.zoom("synthetic", (20.0, 20.0, 60.0, 60.0), magnification=OVERVIEW_MAG)
    assert overview and all(tile["zoom"] == "optical" for tile in overview)


def test_stream_view_sends_coarse_tiles_first(built):
    _, client, _, _ = built
    levels = [
        int(tile.uri.split("/")[1])
        for tile in client.stream_view("synthetic", (240.0, 160.0, 360.0, 280.0), viewport_px=2048)
    ]
    assert levels[0] == 0 and levels == sorted(levels) and max(levels) >= 2


def test_repeated_request_id_returns_the_stored_specimen(built):
    """The same request again (same id, same content) gets the stored build, untouched; other
    content under that id is refused (tests/services/tiles/test_request_hardening.py)."""
    _, client, data, summary = built
    description = data / "specimens" / "synthetic" / "specimen.json"
    before = description.stat().st_mtime_ns
    specimen_id, rois = load_manifest(data.parent / "input" / "manifest.json")
    again = client.reconstruct_specimen(specimen_id, rois, request_id="first")
    assert again == summary
    assert description.stat().st_mtime_ns == before


def test_a_restarted_server_finds_the_specimen(built):
    _, _, data, summary = built
    server, port = create_server(ServerConfig(address="127.0.0.1:0", data_dir=data))
    server.start()
    try:
        with FractoscopeClient(f"127.0.0.1:{port}") as client:
            assert [s["id"] for s in client.list_specimens()] == ["synthetic"]
            assert client.get_specimen("synthetic") == summary
    finally:
        server.stop(grace=None)


def test_a_rebuilt_specimen_is_never_served_from_the_caches_of_the_old_build(built, tmp_path):
    """GetTile and the HTTP endpoint keep tiles in memory; a new build (a new specimen.json) must
    replace what they serve, on a running server."""
    import shutil

    _, _, data, _ = built
    copy = tmp_path / "data"
    shutil.copytree(data, copy)
    uri = content_uris(json.loads((copy / "specimens" / "synthetic" / "tileset.json").read_text()))[0]
    server, port = create_server(ServerConfig(address="127.0.0.1:0", data_dir=copy))
    server.start()
    http = start_http_server(SpecimenStore(copy))
    url = f"http://127.0.0.1:{http.server_port}/specimens/synthetic/{uri}"
    try:
        with FractoscopeClient(f"127.0.0.1:{port}") as client:
            old = client.get_tile("synthetic", uri)
            assert client.get_tile("synthetic", uri) == old and urllib.request.urlopen(url).read() == old
            directory = copy / "specimens" / "synthetic"
            (directory / uri).write_bytes(old + b"    ")  # what a rebuild writes, in place for the test
            description = directory / "specimen.json"
            stamp = description.stat().st_mtime_ns + 1_000_000
            os.utime(description, ns=(stamp, stamp))
            assert client.get_tile("synthetic", uri) == old + b"    "
            assert urllib.request.urlopen(url).read() == old + b"    "
    finally:
        http.shutdown()
        server.stop(grace=None)


@pytest.mark.parametrize(
    "call, code, field",
    [
        (lambda c: c.get_specimen("missing"), grpc.StatusCode.NOT_FOUND, None),
        (lambda c: c.get_specimen("../etc"), grpc.StatusCode.INVALID_ARGUMENT, "specimen_id"),
        (lambda c: c.get_tile("synthetic", "../../specimen.json"), grpc.StatusCode.INVALID_ARGUMENT, "uri"),
        (lambda c: c.get_tile("synthetic", "tiles/9/0/0.glb"), grpc.StatusCode.NOT_FOUND, None),
        (
            lambda c: c.get_tile("synthetic", "tiles/00/0/0.glb"),
            grpc.StatusCode.INVALID_ARGUMENT,
            "uri",
        ),  # one URI per tile
        (lambda c: c.profile("synthetic", [(0.0, 0.0)]), grpc.StatusCode.INVALID_ARGUMENT, "points"),
        (
            lambda c: c.zoom("synthetic", (10.0, 10.0, 5.0, 20.0), magnification=100),
            grpc.StatusCode.INVALID_ARGUMENT,
            "region",
        ),
        (
            lambda c: c.zoom("synthetic", (0.0, 0.0, 5.0, 5.0), magnification=-1),
            grpc.StatusCode.INVALID_ARGUMENT,
            "magnification",
        ),
        (lambda c: c.roughness("synthetic", roi="nope"), grpc.StatusCode.NOT_FOUND, None),
        # The message echoes the id, bounded: 20,000 characters of it overflowed gRPC's headers.
        (lambda c: c.roughness("synthetic", roi="r" * 20_000), grpc.StatusCode.NOT_FOUND, None),
        (
            lambda c: c.reconstruct_specimen("two-overviews", [_roi("a"), _roi("b")]),
            grpc.StatusCode.INVALID_ARGUMENT,
            "rois",
        ),
        (
            lambda c: c.reconstruct_specimen("orphan", [_roi("a"), _roi("b", parent="x")]),
            grpc.StatusCode.INVALID_ARGUMENT,
            "rois[1].parent",
        ),
        (
            lambda c: c.reconstruct_specimen("bad-window", [_roi_with_window("a", 4)]),
            grpc.StatusCode.INVALID_ARGUMENT,
            "rois[0].parameters.window_px",
        ),
    ],
)
def test_bad_requests_get_a_status_naming_the_problem(built, call, code, field):
    _, client, _, _ = built
    with pytest.raises(ClientError) as caught:
        call(client)
    assert caught.value.code == code
    assert caught.value.field == field


def _roi(roi_id: str, parent: str = ""):
    from fractoscope.v1 import common_pb2, matching_pb2, tiles_pb2

    image = matching_pb2.TiltImage(image=common_pb2.ImageFile(content=b"not an image"))
    return tiles_pb2.RoiSpec(id=roi_id, parent=parent, images=[image, image])


def _roi_with_window(roi_id: str, window_px: int):
    """A readable pair whose matching parameters the matching service must check."""
    from fractoscope.v1 import tiles_pb2

    pair = fracture_pair(size_px=128)
    spec = tiles_pb2.RoiSpec(id=roi_id, pixel_size_um=0.1)
    for image, tilt_deg in ((pair.first, -5.0), (pair.second, 5.0)):
        item = spec.images.add(tilt_deg=tilt_deg)
        item.image.content = tiff_bytes(image)
    spec.parameters.window_px = window_px
    return spec


def test_http_endpoint_serves_tiles_with_cors_etag_and_gzip(built):
    _, _, data, _ = built
    http = start_http_server(SpecimenStore(data))
    base = f"http://127.0.0.1:{http.server_port}/specimens/synthetic"
    try:
        request = urllib.request.Request(f"{base}/tileset.json", headers={"Accept-Encoding": "gzip"})
        with urllib.request.urlopen(request) as response:
            assert response.headers["Access-Control-Allow-Origin"] == "*"
            assert response.headers["Content-Encoding"] == "gzip"
            tileset = json.loads(gzip.decompress(response.read()))
            etag = response.headers["ETag"]
        uri = tileset["root"]["content"]["uri"]
        with urllib.request.urlopen(f"{base}/{uri}") as response:
            assert response.read(4) == b"glTF"
            assert response.headers["Content-Type"] == "model/gltf-binary"
        with pytest.raises(urllib.error.HTTPError) as unchanged:
            urllib.request.urlopen(
                urllib.request.Request(
                    f"{base}/tileset.json", headers={"If-None-Match": etag, "Accept-Encoding": "gzip"}
                )
            )
        assert unchanged.value.code == 304
        for bad in ("/tiles/../specimen.json", "/rois/zoom.npz", "/tiles/7/0/0.glb"):
            with pytest.raises(urllib.error.HTTPError) as missing:
                urllib.request.urlopen(f"{base}{bad}")
            assert missing.value.code == 404
    finally:
        http.shutdown()


def test_http_json_api_names_bad_parameters(built):
    _, _, data, _ = built
    http = start_http_server(SpecimenStore(data))
    base = f"http://127.0.0.1:{http.server_port}/api/specimens"
    try:
        with urllib.request.urlopen(f"{base}/synthetic/profile?from=100,200&to=300,200") as response:
            answer = json.loads(response.read())
        assert answer["parameters"]["Rq"] > 0 and len(answer["z_um"]) == len(answer["source"])
        with pytest.raises(urllib.error.HTTPError) as bad:
            urllib.request.urlopen(f"{base}/synthetic/profile?from=100&to=300,200")
        assert bad.value.code == 400 and json.loads(bad.value.read())["field"] == "from"
        with pytest.raises(urllib.error.HTTPError) as missing:
            urllib.request.urlopen(f"{base}/nothing/roughness")
        assert missing.value.code == 404
        for outside in ("/viewer/../../pyproject.toml", "/vendor/three/../../package.json", "/vendor/other/x.js"):
            with pytest.raises(urllib.error.HTTPError) as denied:
                urllib.request.urlopen(f"http://127.0.0.1:{http.server_port}{outside}")
            assert denied.value.code == 404
    finally:
        http.shutdown()

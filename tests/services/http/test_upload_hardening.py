"""Uploads over HTTP under a hostile probe, on a real server on loopback: what the build would
refuse is refused at upload (400 naming the manifest's entry, nothing stored), uploads expire and
can be deleted, and a ReconstructSpecimen over gRPC has the same bound on its ROIs."""

from __future__ import annotations

import json
import os
import shutil
import time
from pathlib import Path

import pytest
import requests

from fractoscope.client import ClientError, FractoscopeClient
from fractoscope.errors import InvalidInputError, NotFoundError
from fractoscope.http.server import start_http_server
from fractoscope.http.uploads import DEFAULT_MAX_UPLOAD_BYTES, Uploads
from fractoscope.rpc.limits import MAX_REQUEST_ID_CHARS, MAX_ROIS
from fractoscope.server.config import ServerConfig
from fractoscope.server.main import create_server
from fractoscope.store.folder import SpecimenStore
from fractoscope.synthetic.examples import write_multiscale_specimen
from fractoscope.v1 import common_pb2, matching_pb2, tiles_pb2

HUGE = "1" + "0" * 400  # a JSON integer beyond any double


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """(base URL, input folder with the example specimen's PNG pairs and manifest, uploads folder)."""
    root = tmp_path_factory.mktemp("uploads")
    write_multiscale_specimen(root / "input")
    endpoint = start_http_server(SpecimenStore(root / "data"))
    yield f"http://127.0.0.1:{endpoint.server_port}", root / "input", root / "data" / "uploads"
    endpoint.shutdown()


def _parts(input_directory: Path, manifest: dict | str | None = None, **replaced: bytes) -> list:
    """An upload of the example specimen: its manifest (or `manifest`: a dict or JSON text) and
    its images, the files named in `replaced` (with dots as underscores) replaced by those bytes."""
    if manifest is None:
        manifest = json.loads((input_directory / "manifest.json").read_text())
    text = manifest if isinstance(manifest, str) else json.dumps(manifest)
    images = [
        (path.name, replaced.get(path.name.replace(".", "_"), path.read_bytes()))
        for path in sorted(input_directory.glob("*.png"))
    ]
    return [("manifest", (None, text, "application/json"))] + [
        ("images", (name, content, "image/png")) for name, content in images
    ]


def _example(input_directory: Path) -> dict:
    return json.loads((input_directory / "manifest.json").read_text())


def _refused(base: str, parts: list, uploads: Path, field: str) -> dict:
    """The answer to an upload of `parts`, checked to be a 400 naming `field` that stored nothing."""
    before = sorted(path.name for path in uploads.iterdir())
    answer = requests.post(f"{base}/api/uploads", files=parts, timeout=120)
    assert answer.status_code == 400 and answer.json()["field"] == field, answer.text
    assert sorted(path.name for path in uploads.iterdir()) == before
    return answer.json()


def test_a_manifest_of_thousands_of_rois_naming_two_images_is_refused_naming_rois(server):
    """Once 201 after every ROI read both files (0.4 to 2.5 GB of server memory for an 818 kB
    manifest)."""
    base, input_directory, uploads = server
    roi = _example(input_directory)["rois"][0]
    children = [{**roi, "id": f"roi-{index}", "parent": "roi-0"} for index in range(1, 3000)]
    manifest = {"specimen": "amplified", "rois": [{**roi, "id": "roi-0"}, *children]}
    answer = _refused(base, _parts(input_directory, manifest), uploads, "manifest.rois")
    assert str(MAX_ROIS) in answer["error"]


def _with_overview(input_directory: Path, text: str) -> str:
    """The example manifest as JSON text with `text` (JSON of keys and values) in its overview."""
    manifest = json.dumps(_example(input_directory))
    return manifest.replace('"id": "overview",', '"id": "overview", ' + text + ",", 1)


@pytest.mark.parametrize(
    "keys, field",
    [
        ('"magnification": 1' + "0" * 5000, "manifest"),  # json.loads: ValueError, beyond 4,300 digits
        (f'"pixel_size_um": {HUGE}', "manifest.rois[0].pixel_size_um"),  # float(): OverflowError
        (f'"tilt_deg": [-5, {HUGE}]', "manifest.rois[0].tilt_deg"),
        (f'"center_um": [{HUGE}, 0]', "manifest.rois[0].center_um"),
        (f'"magnification": {HUGE}', "manifest.rois[0].magnification"),
        (f'"tilt_axis_deg": {HUGE}', "manifest.rois[0].tilt_axis_deg"),
        ('"left": "overview_right.png"', "manifest.rois[0].left"),  # a repeated key: the last one won unseen
    ],
)
def test_numbers_a_double_cannot_hold_and_repeated_keys_are_refused_naming_the_entry(server, keys, field):
    """Once a plain-text 500 (the numbers) or a 201 (the key)."""
    base, input_directory, uploads = server
    _refused(base, _parts(input_directory, _with_overview(input_directory, keys)), uploads, field)


@pytest.mark.parametrize(
    "roi, changes, field",
    [
        (0, {"tilt_deg": [float("nan"), 5]}, "manifest.rois[0].tilt_deg"),  # json.loads takes NaN
        (0, {"tilt_deg": [0, 0]}, "manifest.rois[0].tilt_deg"),
        (0, {"tilt_deg": [90, 90]}, "manifest.rois[0].tilt_deg"),
        (1, {"tilt_deg": [355, 365]}, "manifest.rois[1].tilt_deg"),
        (0, {"tilt_deg": [-1e308, 1e308]}, "manifest.rois[0].tilt_deg"),
        (1, {"center_um": [1e308, 100]}, "manifest.rois[1].center_um"),
        (1, {"center_um": [-300, 100]}, "manifest.rois[1].center_um"),  # wholly left of its 512 µm parent
        (0, {"tilt_deg": None}, "manifest.rois[0].tilt_deg"),  # PNG files state no tilt
        (0, {"pixel_size_um": None}, "manifest.rois[0].pixel_size_um"),  # nor a pixel size
    ],
)
def test_what_the_build_would_refuse_is_refused_at_upload(server, roi, changes, field):
    """Once 201, then a job that failed naming the gRPC field (rois[0].images[1].tilt_deg). A key
    changed to None is left out."""
    base, input_directory, uploads = server
    manifest = _example(input_directory)
    manifest["rois"][roi].update(changes)
    manifest["rois"][roi] = {key: value for key, value in manifest["rois"][roi].items() if value is not None}
    _refused(base, _parts(input_directory, manifest), uploads, field)


def test_a_truncated_image_is_refused_at_upload(server):
    """Its header, and so its size, intact: once 201, then a job that failed decoding it."""
    base, input_directory, uploads = server
    whole = (input_directory / "zoom_right.png").read_bytes()
    parts = _parts(input_directory, zoom_right_png=whole[: len(whole) // 2])
    _refused(base, parts, uploads, "manifest.rois[1].right")


def test_the_example_is_accepted_with_a_centre_inside_its_parent(server):
    base, input_directory, uploads = server
    manifest = _example(input_directory)
    manifest["rois"][1]["center_um"] = [300.0, 220.0]
    answer = requests.post(f"{base}/api/uploads", files=_parts(input_directory, manifest), timeout=120)
    assert answer.status_code == 201, answer.text
    assert (uploads / answer.json()["upload_id"]).is_dir()


def test_an_image_part_the_manifest_does_not_name_is_refused_and_nothing_is_stored(server):
    """Once kept with the upload: 5,000 extra parts were stored, for ever."""
    base, input_directory, uploads = server
    parts = _parts(input_directory) + [("images", ("x.tif", b"anything", "image/tiff"))]
    _refused(base, parts, uploads, "images['x.tif']")


@pytest.mark.parametrize(
    "request_id",
    [b"r" * 100_000, "é".encode() * (MAX_REQUEST_ID_CHARS + 1), b"lims-\xff\xfe"],
    ids=["100 kB", "one character too many", "not UTF-8"],
)
def test_a_request_id_gRPC_would_not_take_is_refused_naming_it(server, request_id):
    """Once cut to 128 characters, or its bad bytes replaced, silently."""
    base, input_directory, uploads = server
    parts = _parts(input_directory) + [("request_id", (None, request_id, "text/plain"))]
    _refused(base, parts, uploads, "request_id")


def test_a_request_id_is_kept_whole(server):
    base, input_directory, uploads = server
    request_id = "é" * MAX_REQUEST_ID_CHARS
    parts = _parts(input_directory) + [("request_id", (None, request_id.encode(), "text/plain"))]
    answer = requests.post(f"{base}/api/uploads", files=parts, timeout=120)
    assert answer.status_code == 201, answer.text
    assert Uploads(uploads, DEFAULT_MAX_UPLOAD_BYTES).field(answer.json()["upload_id"], "request_id") == request_id


def _stored_upload(base: str, input_directory: Path) -> str:
    answer = requests.post(f"{base}/api/uploads", files=_parts(input_directory), timeout=120)
    assert answer.status_code == 201, answer.text
    return answer.json()["upload_id"]


def _age(directory: Path, seconds: float) -> None:
    stamp = time.time() - seconds
    os.utime(directory, (stamp, stamp))


def test_uploads_expire_at_start_and_when_an_upload_is_received(server, tmp_path, monkeypatch):
    """Once kept for ever."""
    base, input_directory, uploads = server
    old, fresh = _stored_upload(base, input_directory), _stored_upload(base, input_directory)
    _age(uploads / old, 2 * 24 * 3600)  # beyond the default of a day
    _stored_upload(base, input_directory)
    assert not (uploads / old).exists() and (uploads / fresh).is_dir()
    copy = tmp_path / "uploads"
    shutil.copytree(uploads / fresh, copy / fresh)
    _age(copy / fresh, 120)
    monkeypatch.setenv("FRACTO_UPLOAD_MAX_AGE_S", "600")
    Uploads(copy, DEFAULT_MAX_UPLOAD_BYTES)
    assert (copy / fresh).is_dir()
    monkeypatch.setenv("FRACTO_UPLOAD_MAX_AGE_S", "60")
    Uploads(copy, DEFAULT_MAX_UPLOAD_BYTES)
    assert not (copy / fresh).exists()


def test_an_expired_upload_is_not_found_before_it_is_swept(server):
    base, input_directory, uploads = server
    kept = Uploads(uploads, DEFAULT_MAX_UPLOAD_BYTES, max_age_s=3600)
    upload_id = _stored_upload(base, input_directory)
    assert kept.load(upload_id)[0] == "synthetic"
    _age(uploads / upload_id, 7200)
    with pytest.raises(NotFoundError) as error:
        kept.load(upload_id)
    assert error.value.field == "upload_id"


def test_an_upload_can_be_deleted(server):
    base, input_directory, uploads = server
    upload_id = _stored_upload(base, input_directory)
    kept = Uploads(uploads, DEFAULT_MAX_UPLOAD_BYTES)
    kept.delete(upload_id)
    assert not (uploads / upload_id).exists() and not list(uploads.glob(".staging-*"))
    with pytest.raises(NotFoundError) as error:
        kept.delete(upload_id)
    assert error.value.field == "upload_id"
    with pytest.raises(InvalidInputError) as error:
        kept.delete("../data")
    assert error.value.field == "upload_id"


@pytest.mark.server
def test_a_reconstruction_over_grpc_with_more_than_max_rois_is_refused_naming_rois(tmp_path):
    image = matching_pb2.TiltImage(image=common_pb2.ImageFile(content=b"not an image"))
    rois = [tiles_pb2.RoiSpec(id="r0", images=[image, image])] + [
        tiles_pb2.RoiSpec(id=f"r{index}", parent="r0", images=[image, image]) for index in range(1, MAX_ROIS + 1)
    ]
    server, port = create_server(ServerConfig(address="127.0.0.1:0", data_dir=tmp_path / "data"))
    server.start()
    try:
        with FractoscopeClient(f"127.0.0.1:{port}", timeout_s=60) as client, pytest.raises(ClientError) as caught:
            client.reconstruct_specimen("many", rois)
    finally:
        server.stop(grace=None)
    assert caught.value.field == "rois" and str(MAX_ROIS) in str(caught.value)


def _series_parts(images: dict[str, bytes], roi: dict) -> list:
    manifest = {"specimen": "series", "rois": [{"id": "overview", **roi}]}
    return [("manifest", (None, json.dumps(manifest), "application/json"))] + [
        ("images", (name, content, "image/png")) for name, content in images.items()
    ]


def test_a_tilt_series_is_uploaded_and_what_its_calibration_cannot_take_is_refused(server):
    """A manifest ROI of three views with "calibrate": true is stored as an upload; a series
    missing a view, and a pair asked to calibrate its tilts (directly or through matching), are
    refused naming the manifest's entry."""
    import io

    from PIL import Image

    from fractoscope import synthetic

    base, _, uploads = server
    surface = synthetic.self_affine_surface((96, 96), hurst=0.8, rms_um=1.0, seed=3)
    views, _ = synthetic.render_tilt_series(
        surface, pixel_size_um=0.1, tilt_deg=(-5.0, 0.0, 5.0), output_shape=(64, 64), seed=3
    )
    images = {}
    for index, view in enumerate(views):
        encoded = io.BytesIO()
        Image.fromarray(view).save(encoded, format="PNG")
        images[f"view{index}.png"] = encoded.getvalue()
    series = {"images": list(images), "tilt_deg": [-4.5, 0, 4.5], "pixel_size_um": 0.1, "calibrate": True}
    answer = requests.post(f"{base}/api/uploads", files=_series_parts(images, series), timeout=60)
    assert answer.status_code == 201 and answer.json()["rois"] == ["overview"], answer.text
    missing = dict(list(images.items())[:2])
    _refused(base, _series_parts(missing, series), uploads, "manifest.rois[0].images[2]")
    pair = {"left": "view0.png", "right": "view2.png", "tilt_deg": [-5, 5], "pixel_size_um": 0.1}
    only_pair = {name: images[name] for name in ("view0.png", "view2.png")}
    _refused(base, _series_parts(only_pair, {**pair, "calibrate": True}), uploads, "manifest.rois[0].calibrate")
    asked = {**pair, "matching": {"calibrate_tilt": True}}
    _refused(base, _series_parts(only_pair, asked), uploads, "manifest.rois[0].matching.calibrate_tilt")


@pytest.mark.server
def test_a_reconstruction_over_grpc_of_one_image_or_a_calibrated_pair_is_refused_naming_the_roi(tmp_path):
    image = matching_pb2.TiltImage(image=common_pb2.ImageFile(content=b"not an image"))
    server, port = create_server(ServerConfig(address="127.0.0.1:0", data_dir=tmp_path / "data"))
    server.start()
    try:
        with FractoscopeClient(f"127.0.0.1:{port}", timeout_s=60) as client:
            with pytest.raises(ClientError) as one:
                client.reconstruct_specimen("one", [tiles_pb2.RoiSpec(id="o", images=[image])])
            calibrated = tiles_pb2.RoiSpec(
                id="o", images=[image, image], parameters=matching_pb2.MatchingParameters(calibrate_tilt=True)
            )
            with pytest.raises(ClientError) as pair:
                client.reconstruct_specimen("pair", [calibrated])
    finally:
        server.stop(grace=None)
    assert one.value.field == "rois[0].images" and "3 or more" in str(one.value)
    assert pair.value.field == "rois[0].parameters.calibrate_tilt"

"""Specimen manifests: ROIs read from JSON, bad entries named."""

import json

import pytest
from conftest import fracture_pair, tiff_bytes

from fractoscope.client.manifest import load_manifest
from fractoscope.errors import InvalidInputError


def _write(tmp_path, **roi):
    pair = fracture_pair(size_px=64)
    (tmp_path / "l.tif").write_bytes(tiff_bytes(pair.first))
    (tmp_path / "r.tif").write_bytes(tiff_bytes(pair.second))
    path = tmp_path / "manifest.json"
    path.write_text(
        json.dumps({"specimen": "s", "rois": [{"id": "overview", "left": "l.tif", "right": "r.tif", **roi}]})
    )
    return path


def test_an_roi_carries_its_images_tilts_and_matching_parameters(tmp_path):
    specimen_id, (roi,) = load_manifest(
        _write(
            tmp_path,
            tilt_deg=[-5, 5],
            pixel_size_um=0.1,
            matching={"normalize_local_contrast": False, "window_px": 21},
        )
    )
    assert specimen_id == "s" and roi.id == "overview"
    assert [image.tilt_deg for image in roi.images] == [-5.0, 5.0]
    assert roi.images[0].image.content == (tmp_path / "l.tif").read_bytes() and roi.images[1].image.filename == "r.tif"
    # An explicit false is kept apart from absent (which means the default, on).
    assert roi.parameters.HasField("normalize_local_contrast") and not roi.parameters.normalize_local_contrast
    assert roi.parameters.window_px == 21
    _, (plain,) = load_manifest(_write(tmp_path))
    assert not plain.HasField("parameters")


@pytest.mark.parametrize(
    "roi, field",
    [
        ({"matching": {"window": 21}}, "manifest.rois[0].matching"),
        ({"matching": {"window_px": "wide"}}, "manifest.rois[0].matching"),
        ({"matching": None}, "manifest.rois[0].matching"),
        ({"tilt_deg": [5]}, "manifest.rois[0].tilt_deg"),
        ({"colour": "red"}, "manifest.rois[0]"),
        ({"parent": 7}, "manifest.rois[0].parent"),  # once a TypeError from protobuf
    ],
)
def test_a_bad_entry_is_named(tmp_path, roi, field):
    with pytest.raises(InvalidInputError) as error:
        load_manifest(_write(tmp_path, **roi))
    assert error.value.field == field and "\n" not in str(error.value)


@pytest.mark.parametrize(
    "content",
    [
        pytest.param(b"\xff\xfe{", id="not UTF-8"),
        pytest.param(b"[" * 30_000 + b"]" * 30_000, id="nested too deeply"),  # once a RecursionError
        pytest.param(json.dumps({"specimen": "s", "rois": [], "comment": 1}).encode(), id="unknown key"),
    ],
)
def test_a_manifest_that_is_not_one_is_named(tmp_path, content):
    path = tmp_path / "manifest.json"
    path.write_bytes(content)
    with pytest.raises(InvalidInputError) as error:
        load_manifest(path)
    assert error.value.field == "manifest" and "\n" not in str(error.value)

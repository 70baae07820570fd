"""Specimen manifests: ROIs read from JSON, bad entries named."""

import json

import pytest
from conftest import fracture_pair, tiff_bytes

from fractoscope.client.manifest import load_manifest
from fractoscope.errors import InvalidInputError
from fractoscope.rpc.limits import MAX_ROIS
from fractoscope.rpc.manifest import parse_manifest
from fractoscope.v1 import matching_pb2


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
    _, (fast,) = load_manifest(_write(tmp_path, matching={"method": "MATCHING_METHOD_FAST"}))
    assert fast.parameters.method == matching_pb2.MATCHING_METHOD_FAST


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


def _manifest(rois: list[dict]) -> str:
    return json.dumps({"specimen": "s", "rois": rois})


def _pair_roi(index: int, **keys) -> dict:
    return {"id": f"r{index}", "left": "l.tif", "right": "r.tif", **keys}


def test_each_file_is_read_once_and_only_after_the_whole_manifest_is_checked():
    """Once every ROI read both its images before the next entry was looked at: 3,000 ROIs naming
    two files took a server from 0.4 to 2.5 GB before a bad entry or the ROI count was seen."""
    reads = []

    def read_image(name: str, field: str) -> bytes:
        reads.append(name)
        return name.encode()

    rois = [_pair_roi(index) for index in range(3)]
    with pytest.raises(InvalidInputError) as error:
        parse_manifest(_manifest([*rois, _pair_roi(3, tilt_deg=[5])]), read_image)
    assert error.value.field == "manifest.rois[3].tilt_deg" and reads == []
    with pytest.raises(InvalidInputError) as error:
        parse_manifest(_manifest([_pair_roi(index) for index in range(MAX_ROIS + 1)]), read_image)
    assert error.value.field == "manifest.rois" and str(MAX_ROIS) in error.value.message and reads == []
    _, specs = parse_manifest(_manifest(rois), read_image)
    assert sorted(reads) == ["l.tif", "r.tif"]
    assert [image.image.content for spec in specs for image in spec.images] == [b"l.tif", b"r.tif"] * 3


def test_images_counted_per_roi_are_bounded():
    """Each ROI's message carries its own copy of its images: the bound counts them so."""
    with pytest.raises(InvalidInputError) as error:
        parse_manifest(_manifest([_pair_roi(0), _pair_roi(1)]), lambda name, field: b"x" * 100, max_image_bytes=399)
    assert error.value.field == "manifest.rois"
    _, specs = parse_manifest(_manifest([_pair_roi(0), _pair_roi(1)]), lambda n, f: b"x" * 100, max_image_bytes=400)
    assert len(specs) == 2


HUGE = "1" + "0" * 400  # a valid JSON integer beyond any double


@pytest.mark.parametrize(
    "roi_json, field",
    [
        (f'"pixel_size_um": {HUGE}', "manifest.rois[0].pixel_size_um"),
        (f'"magnification": {HUGE}', "manifest.rois[0].magnification"),
        (f'"tilt_axis_deg": -{HUGE}', "manifest.rois[0].tilt_axis_deg"),
        (f'"tilt_deg": [-5, {HUGE}]', "manifest.rois[0].tilt_deg"),
        (f'"center_um": [{HUGE}, 0]', "manifest.rois[0].center_um"),
        (f'"matching": {{"min_confidence": {HUGE}}}', "manifest.rois[0].matching"),
        ('"tilt_deg": [-5, 5], "tilt_deg": [5, -5]', "manifest.rois[0].tilt_deg"),
        ('"matching": {"window_px": 21, "window_px": 31}', "manifest.rois[0].matching.window_px"),
    ],
)
def test_numbers_beyond_a_double_and_repeated_keys_are_named(roi_json, field):
    """Once an OverflowError (float() of a 400-digit integer: HTTP 500), or the last of two values
    kept unseen."""
    text = '{"specimen": "s", "rois": [{"id": "o", "left": "l.tif", "right": "r.tif", ' + roi_json + "}]}"
    with pytest.raises(InvalidInputError) as error:
        parse_manifest(text, lambda name, field: b"")
    assert error.value.field == field and "\n" not in str(error.value)


@pytest.mark.parametrize(
    "text, field",
    [
        (
            '{"specimen": "s", "rois": [{"id": "o", "left": "l", "right": "r", "magnification": 1' + "0" * 5000 + "}]}",
            "manifest",
        ),
        ('{"specimen": "s", "specimen": "t", "rois": []}', "manifest.specimen"),
    ],
    ids=["an integer of 5,001 digits", "a repeated specimen"],
)
def test_a_manifest_json_cannot_hold_is_named(text, field):
    """Integers of more than 4,300 digits: json.loads raises ValueError (once HTTP 500)."""
    with pytest.raises(InvalidInputError) as error:
        parse_manifest(text, lambda name, field: b"")
    assert error.value.field == field and "\n" not in str(error.value)


def _series_roi(**keys) -> dict:
    return {"id": "o", "images": ["a.tif", "b.tif", "c.tif"], **keys}


def test_a_tilt_series_roi_carries_its_images_tilts_and_calibration():
    """A series lists its images, reference first, one tilt each; "calibrate": true asks for the
    tilt calibration (calibrate_tilt); a pair's entry is read as before."""
    reads = []

    def read_image(name: str, field: str) -> bytes:
        reads.append((name, field))
        return name.encode()

    _, (series,) = parse_manifest(_manifest([_series_roi(tilt_deg=[-4.5, 0, 4.5], calibrate=True)]), read_image)
    assert [image.image.filename for image in series.images] == ["a.tif", "b.tif", "c.tif"]
    assert [image.image.content for image in series.images] == [b"a.tif", b"b.tif", b"c.tif"]
    assert [image.tilt_deg for image in series.images] == [-4.5, 0.0, 4.5] and series.parameters.calibrate_tilt
    assert reads[2] == ("c.tif", "manifest.rois[0].images[2]")
    _, (nominal,) = parse_manifest(_manifest([_series_roi(calibrate=False)]), read_image)
    assert not nominal.parameters.calibrate_tilt and not any(image.HasField("tilt_deg") for image in nominal.images)
    _, (pair,) = parse_manifest(_manifest([_pair_roi(0, tilt_deg=[-5, 5])]), read_image)
    assert [image.image.filename for image in pair.images] == ["l.tif", "r.tif"] and not pair.parameters.calibrate_tilt


@pytest.mark.parametrize(
    "roi, field",
    [
        (_series_roi(images=["a.tif", "b.tif"]), "manifest.rois[0].images"),  # a pair is left and right
        (_series_roi(images=["a.tif", "b.tif", 3]), "manifest.rois[0].images"),
        (_series_roi(left="a.tif", right="b.tif"), "manifest.rois[0].images"),
        (_series_roi(tilt_deg=[-5, 5]), "manifest.rois[0].tilt_deg"),
        (_series_roi(calibrate="yes"), "manifest.rois[0].calibrate"),
        (_pair_roi(0, calibrate=True), "manifest.rois[0].calibrate"),  # two views cannot be calibrated
        ({"id": "o", "left": "l.tif"}, "manifest.rois[0].right"),
    ],
)
def test_a_bad_series_entry_is_named(roi, field):
    with pytest.raises(InvalidInputError) as error:
        parse_manifest(_manifest([roi]), lambda name, field: b"")
    assert error.value.field == field and "\n" not in str(error.value)


@pytest.mark.parametrize(
    "field, images, entry",
    [
        ("rois[0].images[1].image", 2, "manifest.rois[0].right"),
        ("rois[0].images[1].image", 3, "manifest.rois[0].images[1]"),
        ("rois[0].images[2]", 3, "manifest.rois[0].images[2]"),
        ("rois[0].images[2].tilt_deg", 3, "manifest.rois[0].tilt_deg"),
        ("rois[0].parameters.calibrate_tilt", 2, "manifest.rois[0].matching.calibrate_tilt"),
    ],
)
def test_request_fields_are_named_as_the_manifest_entries_they_come_from(field, images, entry):
    from fractoscope.rpc.manifest import manifest_field
    from fractoscope.v1 import tiles_pb2

    roi = tiles_pb2.RoiSpec(id="o", images=[matching_pb2.TiltImage() for _ in range(images)])
    assert manifest_field(field, [roi]) == entry

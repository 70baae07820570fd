"""X3P (ISO 25178-72) files: written here, read back by surfalize, an independent reader."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import zipfile
from xml.etree import ElementTree

import numpy as np
import pytest
from surfalize import Surface

from fractoscope.errors import InvalidInputError
from fractoscope.formats.calibration import Calibration
from fractoscope.formats.x3p import read_x3p, write_x3p

PIXEL_SIZE_UM = 0.125
AMPLITUDE_UM = 1.5
PERIOD_PX = 64
SINE_SA_UM = AMPLITUDE_UM * 2 / PERIOD_PX / math.tan(math.pi / PERIOD_PX)  # sum of |sin| over a period: 2 cot(π/N)

CALIBRATION = Calibration(
    tilt_deg=(-4.93, 5.12),
    tilt_source=("metadata", "tilt_calibration"),
    tilt_sigma_deg=(0.5, 0.031),
    pixel_size_um=0.0625,
    pixel_size_source="argument",
)


def sine_surface(rows: int = 96, cols: int = 4 * PERIOD_PX) -> np.ndarray:
    """z = A sin(2π col / period) + 7 µm, float32, whole periods along each row: Sa is the mean of
    A |sin| over a period's samples, SINE_SA_UM."""
    col = np.arange(cols)
    return np.broadcast_to(AMPLITUDE_UM * np.sin(2 * np.pi * col / PERIOD_PX) + 7.0, (rows, cols)).astype(np.float32)


def test_surfalize_reads_heights_sa_and_pixel_size(tmp_path):
    z_um = sine_surface()
    path = tmp_path / "sine.x3p"
    write_x3p(path, z_um, pixel_size_um=PIXEL_SIZE_UM, calibration=CALIBRATION)

    surface = Surface.load(path)

    assert surface.data.shape == z_um.shape
    np.testing.assert_allclose(surface.data, z_um, rtol=0, atol=1e-9)
    assert surface.step_x == pytest.approx(PIXEL_SIZE_UM, rel=1e-12)
    assert surface.step_y == pytest.approx(PIXEL_SIZE_UM, rel=1e-12)
    assert surface.Sa() == pytest.approx(SINE_SA_UM, rel=1e-5)
    assert surface.Sa() == pytest.approx(np.mean(np.abs(z_um - z_um.mean(dtype=np.float64))), rel=1e-9)


def test_heights_are_metres_of_type_d_in_the_file(tmp_path):
    z_um = sine_surface(rows=3, cols=5)
    path = tmp_path / "small.x3p"
    write_x3p(path, z_um, pixel_size_um=PIXEL_SIZE_UM)

    with zipfile.ZipFile(path) as archive:
        main_xml = archive.read("main.xml").decode()
        stored = np.frombuffer(archive.read("bindata/data.bin"), "<f8").reshape(3, 5)
        checksum = archive.read("md5checksum.hex").decode().split()[0]

    np.testing.assert_allclose(stored, z_um.astype(np.float64) * 1e-6, rtol=1e-15)
    assert "<DataType>D</DataType>" in main_xml
    assert f"<Increment>{PIXEL_SIZE_UM * 1e-6!r}</Increment>" in main_xml
    assert checksum == hashlib.md5(main_xml.encode()).hexdigest()


def test_unknown_points_are_nan_for_surfalize_and_our_reader(tmp_path):
    z_um = sine_surface()
    z_um[10:14, 30:41] = np.nan
    z_um[50, 3] = np.inf
    path = tmp_path / "holes.x3p"
    write_x3p(path, z_um, pixel_size_um=PIXEL_SIZE_UM)

    expected_unknown = ~np.isfinite(z_um)
    for heights in (Surface.load(path).data, read_x3p(path).z_um):
        np.testing.assert_array_equal(np.isnan(heights), expected_unknown)
        np.testing.assert_allclose(heights[~expected_unknown], z_um[~expected_unknown], atol=1e-9)


def test_comment_holds_the_calibration_with_sources_and_sigma(tmp_path):
    calibration = Calibration(
        tilt_deg=(0.0, 6.0, 12.0),
        tilt_source=("argument", "tilt_calibration", "tilt_calibration"),
        tilt_sigma_deg=(0.5, 0.02, math.nan),  # the last one's sigma unknown
        pixel_size_um=0.1,
        pixel_size_source="metadata",
    )
    path = tmp_path / "calibrated.x3p"
    write_x3p(path, sine_surface(), pixel_size_um=PIXEL_SIZE_UM, calibration=calibration)

    comment = json.loads(Surface.load(path).metadata["Comment"])

    assert comment["calibration"]["tilt_calibrated"] is True
    assert comment["calibration"]["tilt_sigma_deg"] == [0.5, 0.02, None]
    assert comment["grid_step_um"] == PIXEL_SIZE_UM
    assert comment["z_unit"] == "m"  # the point data; the grid step is given in µm
    back = Calibration.from_dict(comment["calibration"])
    assert back.tilt_deg == calibration.tilt_deg
    assert back.tilt_source == calibration.tilt_source
    assert back.tilt_sigma_deg[:2] == calibration.tilt_sigma_deg[:2] and math.isnan(back.tilt_sigma_deg[2])
    assert (back.pixel_size_um, back.pixel_size_source) == (0.1, "metadata")


def test_uncalibrated_export_says_so(tmp_path):
    path = tmp_path / "nominal.x3p"
    nominal = Calibration((-5.0, 5.0), ("metadata", "metadata"), (0.5, 0.5), 0.1, "metadata")
    write_x3p(path, sine_surface(), pixel_size_um=PIXEL_SIZE_UM, calibration=nominal)
    assert json.loads(read_x3p(path).comment)["calibration"]["tilt_calibrated"] is False

    write_x3p(path, sine_surface(), pixel_size_um=PIXEL_SIZE_UM)
    assert json.loads(read_x3p(path).comment)["calibration"] is None


def test_record2_names_the_microscope_and_dates_the_calibration_by_the_images(tmp_path):
    """Issue 48: CalibrationDate was the export's own time. The images' acquisition is the day their
    tilts and pixel size are true of; the microscope is the one their metadata names."""
    import zipfile
    from xml.etree import ElementTree

    dated = dataclasses.replace(CALIBRATION, acquired_at="2016-03-08T10:39:14", instrument=("Zeiss", "Auriga 60"))
    path = tmp_path / "dated.x3p"
    write_x3p(path, sine_surface(), pixel_size_um=PIXEL_SIZE_UM, calibration=dated)
    record2 = ElementTree.fromstring(zipfile.ZipFile(path).read("main.xml")).find("Record2")
    assert record2.findtext("CalibrationDate") == "2016-03-08T10:39:14"
    assert record2.findtext("Instrument/Manufacturer") == "Zeiss"
    assert record2.findtext("Instrument/Model") == "Auriga 60 scanning electron microscope"
    assert Surface.load(path).data.shape == (96, 4 * PERIOD_PX)  # still an X3P surfalize reads
    assert Calibration.from_dict(json.loads(read_x3p(path).comment)["calibration"]) == dated


def test_origin_is_the_offset_of_the_x_and_y_axes(tmp_path):
    path = tmp_path / "region.x3p"
    write_x3p(path, sine_surface(), pixel_size_um=PIXEL_SIZE_UM, origin_um=(120.5, -3.25))

    with zipfile.ZipFile(path) as archive:
        axes = ElementTree.fromstring(archive.read("main.xml")).find("Record1/Axes")
    assert float(axes.find("CX/Offset").text) == pytest.approx(120.5e-6, rel=1e-12)
    assert float(axes.find("CY/Offset").text) == pytest.approx(-3.25e-6, rel=1e-12)
    assert read_x3p(path).origin_um == (pytest.approx(120.5), pytest.approx(-3.25))
    assert Surface.load(path).data.shape == sine_surface().shape


def test_block_size_does_not_change_the_file_content(tmp_path):
    z_um = np.random.default_rng(3).normal(size=(37, 23)).astype(np.float32)
    one, many = tmp_path / "one.x3p", tmp_path / "many.x3p"
    write_x3p(one, z_um, pixel_size_um=0.2, block_rows=1000)
    write_x3p(many, z_um, pixel_size_um=0.2, block_rows=5)
    with zipfile.ZipFile(one) as a, zipfile.ZipFile(many) as b:
        assert a.read("bindata/data.bin") == b.read("bindata/data.bin")
    np.testing.assert_array_equal(read_x3p(many).z_um.astype(np.float32), z_um)  # float32 survives µm -> m -> µm


def test_compressed_file_reads_the_same(tmp_path):
    z_um = sine_surface()
    path = tmp_path / "deflated.x3p"
    write_x3p(path, z_um, pixel_size_um=PIXEL_SIZE_UM, compress=True)
    with zipfile.ZipFile(path) as archive:
        assert archive.getinfo("bindata/data.bin").compress_type == zipfile.ZIP_DEFLATED
    np.testing.assert_allclose(Surface.load(path).data, z_um, atol=1e-9)


@pytest.mark.filterwarnings("ignore:The surface has different pixel size")  # on purpose: x and y must not swap
def test_our_reader_reads_what_surfalize_writes(tmp_path):
    z_um = np.random.default_rng(5).normal(size=(20, 30))
    z_um[4, 5] = np.nan
    path = tmp_path / "by_surfalize.x3p"
    Surface(z_um, 0.25, 0.5).save(path)

    surface = read_x3p(path)

    np.testing.assert_allclose(surface.z_um, z_um, atol=1e-12)
    assert np.isnan(surface.z_um[4, 5])
    assert (surface.step_x_um, surface.step_y_um) == (pytest.approx(0.25), pytest.approx(0.5))


def _integer_x3p(path, counts: np.ndarray, valid: np.ndarray, *, increment_m: float, offset_m: float) -> None:
    """An X3P file of int16 heights and a valid.bin mask, laid out as ISO 25178-72 describes."""
    data = counts.astype("<i2").tobytes()
    bits = np.packbits(valid.reshape(-1), bitorder="little").tobytes()
    rows, cols = counts.shape
    xml = f"""<?xml version="1.0" encoding="UTF-8"?>
<p:ISO5436_2 xmlns:p="http://www.opengps.eu/2008/ISO5436_2">
<Record1><Revision>ISO5436 - 2000</Revision><FeatureType>SUR</FeatureType><Axes>
<CX><AxisType>I</AxisType><DataType>D</DataType><Increment>2e-07</Increment><Offset>0</Offset></CX>
<CY><AxisType>I</AxisType><DataType>D</DataType><Increment>2e-07</Increment><Offset>0</Offset></CY>
<CZ><AxisType>A</AxisType><DataType>I</DataType><Increment>{increment_m!r}</Increment><Offset>{offset_m!r}</Offset></CZ>
</Axes></Record1>
<Record3><MatrixDimension><SizeX>{cols}</SizeX><SizeY>{rows}</SizeY><SizeZ>1</SizeZ></MatrixDimension>
<DataLink><PointDataLink>bindata/data.bin</PointDataLink><MD5ChecksumPointData>{hashlib.md5(data).hexdigest()}</MD5ChecksumPointData>
<ValidPointsLink>bindata/valid.bin</ValidPointsLink><MD5ChecksumValidPoints>{hashlib.md5(bits).hexdigest()}</MD5ChecksumValidPoints></DataLink>
</Record3><Record4><ChecksumFile>md5checksum.hex</ChecksumFile></Record4></p:ISO5436_2>""".encode()
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("main.xml", xml)
        archive.writestr("bindata/data.bin", data)
        archive.writestr("bindata/valid.bin", bits)
        archive.writestr("md5checksum.hex", f"{hashlib.md5(xml).hexdigest()} *main.xml\n")


def test_reader_scales_integer_heights_and_applies_valid_bin(tmp_path):
    counts = np.arange(-6, 9).reshape(3, 5)
    valid = np.ones((3, 5), dtype=bool)
    valid[1, 2] = valid[2, 4] = False
    path = tmp_path / "integers.x3p"
    _integer_x3p(path, counts, valid, increment_m=1e-8, offset_m=2e-6)

    surface = read_x3p(path)

    expected = counts * 0.01 + 2.0
    np.testing.assert_array_equal(np.isnan(surface.z_um), ~valid)
    np.testing.assert_allclose(surface.z_um[valid], expected[valid], rtol=1e-12)
    assert surface.step_x_um == pytest.approx(0.2)
    np.testing.assert_array_equal(np.isnan(Surface.load(path).data), ~valid)  # surfalize agrees


def test_reader_rejects_point_data_whose_checksum_differs(tmp_path):
    good, bad = tmp_path / "good.x3p", tmp_path / "bad.x3p"
    write_x3p(good, sine_surface(rows=4, cols=4), pixel_size_um=PIXEL_SIZE_UM)
    with zipfile.ZipFile(good) as source, zipfile.ZipFile(bad, "w") as target:
        for item in source.infolist():
            content = source.read(item)
            target.writestr(item, content[:-1] + b"\x01" if item.filename == "bindata/data.bin" else content)
    with pytest.raises(InvalidInputError, match="bindata/data.bin: MD5") as raised:
        read_x3p(bad)
    assert raised.value.field == str(bad)


def _rewritten(good, path, member: str, edit) -> None:
    """A copy of the X3P file `good` at `path` with `member`'s content passed through `edit`."""
    with zipfile.ZipFile(good) as source, zipfile.ZipFile(path, "w") as target:
        for item in source.infolist():
            content = source.read(item)
            target.writestr(item, edit(content) if item.filename == member else content)


@pytest.mark.parametrize(
    ("damage", "message"),
    [
        ("empty", "is not a readable X3P file (a zip archive)"),
        ("text", "is not a readable X3P file (a zip archive)"),
        ("truncated", "is not a readable X3P file (a zip archive)"),
        ("malformed_xml", "main.xml: malformed XML"),
        ("zero_step", "Record1/Axes/CX/Increment: the grid step must be positive and finite, got 0.0 m"),
        ("negative_step", "Record1/Axes/CY/Increment: the grid step must be positive and finite, got -1e-07 m"),
        ("size_not_a_number", "Record3/MatrixDimension/SizeX: expected an integer, got 'many'"),
    ],
)
def test_unreadable_files_are_named_with_what_is_wrong(tmp_path, damage, message):
    good, bad = tmp_path / "good.x3p", tmp_path / f"{damage}.x3p"
    write_x3p(good, sine_surface(rows=4, cols=4), pixel_size_um=PIXEL_SIZE_UM)
    xml = zipfile.ZipFile(good).read("main.xml")
    rewritten = {
        "malformed_xml": lambda content: content[:40],
        "zero_step": lambda content: content.replace(
            b"<Increment>1.25e-07</Increment>", b"<Increment>0</Increment>", 1
        ),
        "negative_step": lambda content: content.replace(
            b"<Increment>1.25e-07</Increment>", b"<Increment>-1e-07</Increment>"
        ).replace(b"<Increment>-1e-07</Increment>", b"<Increment>1.25e-07</Increment>", 1),
        "size_not_a_number": lambda content: content.replace(b"<SizeX>4</SizeX>", b"<SizeX>many</SizeX>"),
    }
    if damage in rewritten:
        assert rewritten[damage](xml) != xml
        _rewritten(good, bad, "main.xml", rewritten[damage])
    else:
        bad.write_bytes(
            {"empty": b"", "text": b"heights, one per line\n", "truncated": good.read_bytes()[:300]}[damage]
        )
    with pytest.raises(InvalidInputError) as raised:
        read_x3p(bad)
    assert raised.value.field == str(bad) and message in raised.value.message


@pytest.mark.parametrize(
    ("z_um", "pixel_size_um", "named"),
    [
        (np.zeros(5), 0.1, "z_um"),
        (np.zeros((0, 3)), 0.1, "z_um"),
        (np.zeros((2, 2), dtype=complex), 0.1, "z_um"),
        (np.zeros((2, 2)), 0.0, "pixel_size_um"),
        (np.zeros((2, 2)), math.nan, "pixel_size_um"),
    ],
)
def test_bad_arguments_are_named(tmp_path, z_um, pixel_size_um, named):
    with pytest.raises(ValueError, match=f"^{named}:"):
        write_x3p(tmp_path / "x.x3p", z_um, pixel_size_um=pixel_size_um)


@pytest.mark.parametrize("origin_um", [(1.0,), (0.0, math.inf), "here"])
def test_bad_origin_is_named(tmp_path, origin_um):
    with pytest.raises(ValueError, match="^origin_um:"):
        write_x3p(tmp_path / "x.x3p", np.zeros((2, 2)), pixel_size_um=0.1, origin_um=origin_um)


def test_calibration_rejects_an_unknown_source():
    with pytest.raises(ValueError, match="^tilt_source:"):
        Calibration((0.0, 5.0), ("metadata", "guess"), (0.5, 0.5), 0.1, "metadata")
    with pytest.raises(ValueError, match="^pixel_size_source:"):
        Calibration((0.0, 5.0), ("metadata", "metadata"), (0.5, 0.5), 0.1, "tilt_calibration")
    with pytest.raises(ValueError, match="^tilt_sigma_deg:"):
        Calibration((0.0, 5.0), ("metadata", "metadata"), (0.5,), 0.1, "metadata")

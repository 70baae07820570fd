"""Float32 TIFF and CSV exports of a height map, read back with tifffile and the csv module."""

from __future__ import annotations

import csv
import io
import json
import math

import numpy as np
import pytest
import tifffile

from fractoscope.formats.calibration import Calibration
from fractoscope.formats.surface_export import write_height_csv, write_height_tiff

CALIBRATION = Calibration(
    tilt_deg=(-5.0, 5.0),
    tilt_source=("argument", "metadata"),
    tilt_sigma_deg=(0.5, 0.5),
    pixel_size_um=0.0875,
    pixel_size_source="metadata",
)


def heights(rows: int = 23, cols: int = 31) -> np.ndarray:
    z_um = np.random.default_rng(11).normal(scale=3.0, size=(rows, cols)).astype(np.float32)
    z_um[4:7, 9:12] = np.nan
    return z_um


def test_tiff_keeps_float32_heights_with_nan(tmp_path):
    z_um = heights()
    path = tmp_path / "z.tif"
    write_height_tiff(path, z_um, pixel_size_um=0.1234, calibration=CALIBRATION)

    with tifffile.TiffFile(path) as tiff:
        page = tiff.pages[0]
        assert page.dtype == np.float32
        np.testing.assert_array_equal(page.asarray(), z_um)  # NaN where NaN: equal_nan is the default


def test_tiff_resolution_tags_give_the_pixel_size_in_centimetres(tmp_path):
    path = tmp_path / "z.tif"
    write_height_tiff(path, heights(), pixel_size_um=0.1234)

    with tifffile.TiffFile(path) as tiff:
        page = tiff.pages[0]
        assert page.resolutionunit == tifffile.RESUNIT.CENTIMETER
        per_cm_x, per_cm_y = page.resolution
    assert 1e4 / per_cm_x == pytest.approx(0.1234, rel=1e-7)
    assert 1e4 / per_cm_y == pytest.approx(0.1234, rel=1e-7)


def test_tiff_description_holds_the_calibration(tmp_path):
    path = tmp_path / "z.tif"
    write_height_tiff(path, heights(), pixel_size_um=0.1234, origin_um=(50.0, 7.5), calibration=CALIBRATION)

    with tifffile.TiffFile(path) as tiff:
        description = json.loads(tiff.pages[0].description)
    assert description["z_unit"] == "um"
    assert description["origin_um"] == [50.0, 7.5]
    assert description["grid_step_um"] == 0.1234
    assert Calibration.from_dict(description["calibration"]) == CALIBRATION


def read_csv(text: str) -> list[dict[str, str]]:
    return list(csv.DictReader(io.StringIO(text)))


def test_csv_lists_measured_points_with_their_positions_and_sigma(tmp_path):
    z_um = heights()
    sigma_um = np.abs(z_um) * 0.01 + 0.02
    path = tmp_path / "z.csv"
    count = write_height_csv(path, z_um, pixel_size_um=0.25, sigma_um=sigma_um, origin_um=(100.0, -3.5), block_rows=4)

    rows = read_csv(path.read_text())

    measured = np.isfinite(z_um)
    assert count == len(rows) == measured.sum()
    assert list(rows[0]) == ["x_um", "y_um", "z_um", "sigma_um"]
    row, col = np.nonzero(measured)  # row-major, as written
    np.testing.assert_allclose([float(r["x_um"]) for r in rows], 100.0 + col * 0.25, rtol=1e-9)
    np.testing.assert_allclose([float(r["y_um"]) for r in rows], -3.5 + row * 0.25, rtol=1e-9)
    np.testing.assert_array_equal(np.array([r["z_um"] for r in rows], dtype=np.float32), z_um[measured])
    np.testing.assert_array_equal(np.array([r["sigma_um"] for r in rows], dtype=np.float32), sigma_um[measured])


def test_csv_sigma_is_empty_where_unknown():
    z_um = np.array([[1.0, 2.0], [3.0, math.nan]], dtype=np.float32)
    out = io.StringIO()
    write_height_csv(out, z_um, pixel_size_um=1.0, sigma_um=np.array([[0.5, math.nan], [0.25, math.nan]]))
    assert out.getvalue() == "x_um,y_um,z_um,sigma_um\n0,0,1,0.5\n1,0,2,\n0,1,3,0.25\n"

    out = io.StringIO()
    write_height_csv(out, z_um, pixel_size_um=1.0)
    assert [r["sigma_um"] for r in read_csv(out.getvalue())] == ["", "", ""]


def test_csv_block_size_does_not_change_the_text():
    z_um = heights()
    texts = []
    for block_rows in (1, 5, 1000):
        out = io.StringIO()
        write_height_csv(out, z_um, pixel_size_um=0.3, block_rows=block_rows)
        texts.append(out.getvalue())
    assert texts[0] == texts[1] == texts[2]


@pytest.mark.parametrize(
    ("call", "named"),
    [
        (lambda path: write_height_tiff(path, np.zeros((2, 2, 2)), pixel_size_um=0.1), "z_um"),
        (lambda path: write_height_tiff(path, np.zeros((2, 2)), pixel_size_um=-1.0), "pixel_size_um"),
        (
            lambda path: write_height_csv(path, np.zeros((2, 2)), pixel_size_um=0.1, sigma_um=np.zeros((2, 3))),
            "sigma_um",
        ),
        (lambda path: write_height_csv(path, np.zeros((2, 2)), pixel_size_um=0.1, block_rows=0), "block_rows"),
    ],
)
def test_bad_arguments_are_named(tmp_path, call, named):
    with pytest.raises(ValueError, match=f"^{named}:"):
        call(tmp_path / "out")

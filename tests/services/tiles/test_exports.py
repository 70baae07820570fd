"""Export over gRPC from the example specimen and from a height map sent along, read back by
independent readers: surfalize (X3P), tifffile, the csv module, trimesh (meshes)."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
import tifffile
import trimesh
from surfalize import Surface

from fractoscope.client import ClientError
from fractoscope.formats.x3p import read_x3p
from fractoscope.store.folder import SpecimenStore


@pytest.fixture(scope="module")
def zoom_arrays(built):
    """The zoom ROI's stored heights and sigma, as the specimen keeps them."""
    _, _, data, _ = built
    placed = SpecimenStore(data).load("synthetic").heights("zoom")
    return placed.z_um, placed.sigma_um, placed.pixel_size_um, placed.origin_um


def test_x3p_of_an_roi_reads_back_in_surfalize_with_the_api_sa_and_its_calibration(built, zoom_arrays, tmp_path):
    _, client, _, _ = built
    z_um, _, pixel_size_um, origin_um = zoom_arrays
    grid = client.export_area("synthetic", tmp_path / "zoom.x3p", roi="zoom")
    assert (grid["rows"], grid["cols"]) == z_um.shape and grid["pixel_size_um"] == pixel_size_um
    surface = Surface.load(tmp_path / "zoom.x3p")
    assert surface.step_x == pytest.approx(pixel_size_um) and surface.data.shape == z_um.shape
    np.testing.assert_allclose(surface.data, z_um, rtol=1e-6, atol=1e-6, equal_nan=True)
    ours = read_x3p(tmp_path / "zoom.x3p")
    assert ours.origin_um == pytest.approx(origin_um)
    calibration = json.loads(ours.comment)["calibration"]
    assert calibration["tilt_source"] == ["argument", "argument"] and calibration["pixel_size_source"] == "argument"
    assert calibration["tilt_sigma_deg"] == [0.5, 0.5] and calibration["tilt_calibrated"] is False


def test_x3p_of_a_region_has_the_api_sa_in_surfalize(built, tmp_path):
    """surfalize levels by its own least-squares plane: it finds the API's Sa, computed after the
    same plane on the same samples (an inner region of the zoom ROI, fully measured)."""
    _, client, _, summary = built
    region = summary["rois"][1]["region"]
    box = (
        region["min"]["x_um"] + 16,
        region["min"]["y_um"] + 16,
        region["max"]["x_um"] - 16,
        region["max"]["y_um"] - 16,
    )
    client.export_area("synthetic", tmp_path / "region.x3p", region_um=box, pixel_size_um=0.25)
    surface = Surface.load(tmp_path / "region.x3p")
    side = round((box[2] - box[0]) / 0.25) + 1
    assert not surface.has_missing_points and surface.data.shape == (side, side)
    assert surface.level().Sa() == pytest.approx(client.roughness("synthetic", region_um=box)["Sa"], rel=1e-6)


def test_tiff_and_csv_of_an_roi_hold_its_heights_and_sigma(built, zoom_arrays, tmp_path):
    _, client, _, _ = built
    z_um, sigma_um, pixel_size_um, origin_um = zoom_arrays
    client.export_area("synthetic", tmp_path / "zoom.tif", roi="zoom")
    with tifffile.TiffFile(tmp_path / "zoom.tif") as tiff:
        np.testing.assert_array_equal(tiff.pages[0].asarray(), z_um)
        description = json.loads(tiff.pages[0].description)
    assert (
        description["origin_um"] == pytest.approx(list(origin_um))
        and description["calibration"]["pixel_size_um"] == pixel_size_um
    )
    client.export_area("synthetic", tmp_path / "zoom.csv", roi="zoom")
    with open(tmp_path / "zoom.csv", newline="") as file:
        rows = list(csv.DictReader(file))
    known = np.isfinite(z_um)
    assert len(rows) == known.sum()
    first = np.argwhere(known)[0]
    assert float(rows[0]["z_um"]) == pytest.approx(float(z_um[tuple(first)]), rel=1e-6)
    # The whole sigma, as fracto height's npz has it: the matching noise the specimen keeps and the
    # tilt part, epsilon_z of the height about the median (the demo is levelled on no datum).
    _, _, data, _ = built
    epsilon = SpecimenStore(data).load("synthetic").roi("zoom").tilt_rel_uncertainty
    tilt_part = epsilon * abs(float(z_um[tuple(first)]) - float(np.median(z_um[known])))
    whole = float(np.hypot(sigma_um[tuple(first)], tilt_part))
    assert epsilon > 0.05 and float(rows[0]["sigma_um"]) == pytest.approx(whole, rel=1e-5)
    assert all(float(row["sigma_um"]) > 0 for row in rows)
    assert float(rows[0]["x_um"]) == pytest.approx(origin_um[0] + first[1] * pixel_size_um)


@pytest.mark.parametrize("file_type", ["stl", "ply", "obj"])
def test_solid_mesh_of_a_region_at_a_chosen_pixel_size_is_watertight_with_the_right_extent(built, tmp_path, file_type):
    _, client, _, summary = built
    region = summary["rois"][1]["region"]
    box = (
        region["min"]["x_um"] + 10,
        region["min"]["y_um"] + 10,
        region["min"]["x_um"] + 60,
        region["min"]["y_um"] + 40,
    )
    grid = client.export_area(
        "synthetic", tmp_path / f"region.{file_type}", region_um=box, pixel_size_um=0.5, solid=True, units="mm"
    )
    assert (grid["rows"], grid["cols"]) == (61, 101) and grid["origin_um"] == {"x_um": box[0], "y_um": box[1]}
    mesh = trimesh.load(tmp_path / f"region.{file_type}", force="mesh")
    assert mesh.is_watertight and mesh.is_volume
    extent_mm = mesh.bounds[1] - mesh.bounds[0]
    assert extent_mm[:2] == pytest.approx([0.05, 0.03], rel=1e-4)  # 100 and 60 steps of 0.5 µm, in mm
    roughness = client.roughness("synthetic", region_um=box)
    assert extent_mm[2] * 1000 > roughness["Sz"]  # the block holds the relief and a base below it


def test_height_map_sent_along_is_area_averaged_onto_the_chosen_pixel_size(client, tmp_path):
    rows, cols = np.mgrid[0:64, 0:96]
    z_um = (0.05 * cols + np.sin(rows / 5.0)).astype(np.float32)
    z_um[10:14, 20:30] = np.nan
    report = {
        "tilt_deg": [-5.0, 5.0],
        "tilt_source": ["metadata", "metadata"],
        "pixel_size_um": 0.2,
        "pixel_size_source": "metadata",
        "parameters": {"tilt_uncertainty_deg": 0.5},
    }
    grid = client.export_height_map(
        z_um, tmp_path / "map.x3p", pixel_size_um=0.2, report=report, export_pixel_size_um=0.4
    )
    assert (grid["rows"], grid["cols"]) == (32, 48) and grid["pixel_size_um"] == pytest.approx(0.4)
    surface = read_x3p(tmp_path / "map.x3p")
    assert surface.step_x_um == pytest.approx(0.4)
    assert surface.z_um[0, 0] == pytest.approx(np.mean(z_um[:2, :2]), rel=1e-6)
    assert json.loads(surface.comment)["calibration"]["tilt_source"] == ["metadata", "metadata"]
    client.export_height_map(z_um, tmp_path / "map.stl", pixel_size_um=0.2)
    mesh = trimesh.load(tmp_path / "map.stl", force="mesh")
    assert mesh.bounds[1][:2] - mesh.bounds[0][:2] == pytest.approx([95 * 0.2, 63 * 0.2], rel=1e-5)


@pytest.mark.parametrize(
    ("arguments", "field"),
    [
        ({"roi": "nope"}, None),
        ({"pixel_size_um": 0.1, "roi": "zoom"}, "pixel_size_um"),
        ({"region_um": (-500.0, -500.0, -400.0, -400.0)}, "region"),
        ({"roi": "zoom", "solid": True, "name": "zoom.tif"}, "solid"),
        ({"roi": "zoom", "units": "mm", "name": "zoom.csv"}, "units"),
    ],
)
def test_a_failed_export_names_the_field_and_leaves_no_file(built, tmp_path, arguments, field):
    _, client, _, _ = built
    path = tmp_path / arguments.pop("name", "out.x3p")
    with pytest.raises(ClientError) as raised:
        client.export_area("synthetic", path, **arguments)
    assert raised.value.field == field
    assert list(tmp_path.iterdir()) == []

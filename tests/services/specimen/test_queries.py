"""Queries on a stored specimen with known heights: the statistics of an area and of a point."""

import numpy as np
import pytest

from fractoscope.errors import InvalidInputError
from fractoscope.specimen.fusion import PlacedRoi
from fractoscope.specimen.model import RoiEntry, write_description, write_roi_arrays
from fractoscope.specimen.quadtree import OPTICAL, QuadtreeLayout, TileKey, TileRecord
from fractoscope.specimen.queries import height_statistics, roughness_of
from fractoscope.store.folder import SpecimenStore


@pytest.fixture()
def step_specimen(tmp_path):
    """A 0.5 µm/px map at the specimen origin: 2 µm left of x = 20 µm, 7 µm right of it, a
    quarter of the right half unknown."""
    z = np.full((60, 80), 2.0, np.float32)
    z[:, 40:] = 7.0
    z[:15, 60:] = np.nan
    roi = PlacedRoi("overview", 100.0, 0.5, (0.0, 0.0), z, np.zeros(z.shape, np.uint8))
    entry = RoiEntry(roi.id, "", 100.0, 0.5, (0.0, 0.0), z.shape)
    root = TileKey(0, 0, 0)
    store = SpecimenStore(tmp_path)
    with store.writing("step") as staging:
        write_roi_arrays(staging, roi)
        write_description(
            staging,
            specimen_id="step",
            request_id="",
            rois=[entry],
            layout=QuadtreeLayout((0.0, 0.0), 40.0),
            tiles={root: TileRecord(root, roi.id, 100.0, OPTICAL, 0.0, 2.0, 7.0)},
        )
    return store.load("step")


def test_area_statistics_tell_a_step_height(step_specimen):
    left = height_statistics(step_specimen, (2.0, 2.0, 15.0, 25.0))
    right = height_statistics(step_specimen, (25.0, 2.0, 38.0, 25.0))
    assert (
        left["mean_um"] == pytest.approx(2.0)
        and left["std_um"] == pytest.approx(0.0, abs=1e-6)
        and left["measured_fraction"] == 1.0
    )
    assert right["mean_um"] - left["mean_um"] == pytest.approx(5.0)
    assert right["measured_fraction"] < 1.0 and right["count"] > 100 and right["pixel_size_um"] == 0.5


def test_a_point_and_an_unmeasured_area(step_specimen):
    point = height_statistics(step_specimen, (30.0, 20.0, 30.0, 20.0))  # a point is a region of no extent
    assert point["count"] == 1 and point["median_um"] == pytest.approx(7.0)
    nothing = height_statistics(step_specimen, (32.0, 1.0, 38.0, 6.0))
    assert nothing["count"] == 0 and nothing["mean_um"] is None and nothing["measured_fraction"] == 0.0
    with pytest.raises(InvalidInputError):
        height_statistics(step_specimen, (30.0, 20.0, 29.0, 21.0))


def test_a_region_far_beyond_the_specimen_is_clipped_to_it(step_specimen):
    """What the fuzzed API sent (a region 1e31 µm wide) is measured where the specimen is: the same
    statistics and roughness as the specimen's own extent, not an allocation of petabytes."""
    huge = (-2.7e31, -4.6e6, 8.8e6, 3.8e8)
    whole = (0.0, 0.0, 39.5, 29.5)
    assert height_statistics(step_specimen, huge) == height_statistics(step_specimen, whole)
    assert roughness_of(step_specimen, region_um=huge).parameters["Sq"] == pytest.approx(
        roughness_of(step_specimen, region_um=whole).parameters["Sq"]
    )
    with pytest.raises(InvalidInputError, match="does not meet the specimen"):
        roughness_of(step_specimen, region_um=(1e6, 1e6, 2e6, 2e6))

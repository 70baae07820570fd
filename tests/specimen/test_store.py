"""The specimen store on disk: atomic replacement, loading, caching by version, and its errors."""

import os

import numpy as np
import pytest

from fractoscope.errors import InvalidInputError, NotFoundError
from fractoscope.specimen.fusion import PlacedRoi
from fractoscope.specimen.quadtree import OPTICAL, QuadtreeLayout, TileKey, TileRecord
from fractoscope.specimen.store import RoiEntry, SpecimenStore, write_description, write_roi_arrays

ROOT_TILE = TileKey(0, 0, 0)


def _write(store: SpecimenStore, specimen_id: str, *, height_um: float = 1.0, request_id: str = "job") -> None:
    """A one-ROI specimen (a 16 x 24 map of `height_um` at 0.5 µm/px) with its root tile."""
    roi = PlacedRoi("overview", 100.0, 0.5, (2.0, 3.0), np.full((16, 24), height_um, np.float32), np.full((16, 24), 7, np.uint8))
    entry = RoiEntry(roi.id, "", roi.magnification, roi.pixel_size_um, roi.origin_um, roi.z_um.shape, matching={"valid_fraction": 1.0})
    record = TileRecord(ROOT_TILE, roi.id, roi.magnification, OPTICAL, 0.0, height_um, height_um)
    with store.writing(specimen_id) as staging:
        (staging / ROOT_TILE.uri).parent.mkdir(parents=True)
        (staging / ROOT_TILE.uri).write_bytes(b"glTF" + bytes([int(height_um)]))
        (staging / "tileset.json").write_text("{}")
        write_roi_arrays(staging, roi)
        write_description(staging, specimen_id=specimen_id, request_id=request_id, rois=[entry],
                          layout=QuadtreeLayout((2.0, 3.0), 12.0), tiles={ROOT_TILE: record})


def test_a_written_specimen_loads_with_everything_it_was_given(tmp_path):
    store = SpecimenStore(tmp_path)
    _write(store, "steel-1", height_um=3.0)
    assert store.ids() == ["steel-1"]
    specimen = store.load("steel-1")
    assert specimen.id == "steel-1" and specimen.request_id == "job"
    (roi,) = specimen.rois
    assert roi.origin_um == (2.0, 3.0) and roi.shape == (16, 24) and roi.matching == {"valid_fraction": 1.0}
    assert roi.region_um == (2.0, 3.0, 2.0 + 23 * 0.5, 3.0 + 15 * 0.5)
    assert specimen.layout == QuadtreeLayout((2.0, 3.0), 12.0) and specimen.tiles[ROOT_TILE].zoom == OPTICAL
    np.testing.assert_array_equal(specimen.heights("overview").z_um, np.full((16, 24), 3.0, np.float32))
    assert specimen.tile_bytes(ROOT_TILE.uri) == b"glTF\x03" and specimen.tileset_bytes == b"{}"
    assert specimen.pixel_size_at_magnification(400.0) == pytest.approx(0.125)


def test_loading_is_cached_until_the_specimen_is_rebuilt(tmp_path):
    store = SpecimenStore(tmp_path)
    _write(store, "steel-1")
    first = store.load("steel-1")
    assert store.load("steel-1") is first
    _write(store, "steel-1", height_um=2.0)
    description = tmp_path / "specimens" / "steel-1" / "specimen.json"
    stamp = first.version + 1_000_000  # a rebuild within the file system's time resolution still counts
    os.utime(description, ns=(stamp, stamp))
    rebuilt = store.load("steel-1")
    assert rebuilt is not first and rebuilt.version != first.version
    assert rebuilt.tile_bytes(ROOT_TILE.uri) == b"glTF\x02"


def test_a_failed_build_leaves_the_stored_specimen_as_it_was(tmp_path):
    store = SpecimenStore(tmp_path)
    _write(store, "steel-1", height_um=1.0)
    with pytest.raises(RuntimeError), store.writing("steel-1") as staging:
        (staging / "specimen.json").write_text("half")
        raise RuntimeError("mesher gone")
    assert store.load("steel-1").tile_bytes(ROOT_TILE.uri) == b"glTF\x01"
    assert sorted(p.name for p in (tmp_path / "specimens").iterdir()) == ["steel-1"]


def test_leftovers_of_a_killed_writer_are_discarded(tmp_path):
    store = SpecimenStore(tmp_path)
    _write(store, "steel-1")
    for leftover in (".staging-steel-2-abc", ".retired-steel-1-def"):
        (tmp_path / "specimens" / leftover).mkdir()
    assert store.ids() == ["steel-1"]
    assert store.discard_unfinished() == 2
    assert sorted(p.name for p in (tmp_path / "specimens").iterdir()) == ["steel-1"]


def test_unknown_and_malformed_names_are_told_apart(tmp_path):
    store = SpecimenStore(tmp_path)
    _write(store, "steel-1")
    with pytest.raises(NotFoundError):
        store.load("steel-2")
    with pytest.raises(InvalidInputError) as bad_id:
        store.load("../etc")
    assert bad_id.value.field == "specimen_id"
    specimen = store.load("steel-1")
    with pytest.raises(InvalidInputError) as bad_uri:
        specimen.tile_bytes("../specimen.json")
    assert bad_uri.value.field == "uri"
    with pytest.raises(NotFoundError):
        specimen.tile_bytes("tiles/3/0/0.glb")
    with pytest.raises(NotFoundError):
        specimen.roi("zoom")

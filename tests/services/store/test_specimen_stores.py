"""The specimen stores: the same contract on the folder and on a real S3 server (loading,
rebuilding, failed builds, deletion, errors), then each one's own crash safety: the folder's
renames that survive a kill at any step, the object store's pointer, sweep and build lease."""

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import write_small_specimen

from fractoscope.errors import InvalidInputError, NotFoundError
from fractoscope.specimen.quadtree import OPTICAL, QuadtreeLayout, TileKey
from fractoscope.store.folder import SpecimenStore
from fractoscope.store.s3 import ObjectSpecimenStore

ROOT_TILE = TileKey(0, 0, 0)


@pytest.fixture(params=["folder", pytest.param("s3", marks=pytest.mark.server)])
def store(request, tmp_path):
    """Each backend, empty; the object store looks at its pointers on every load."""
    if request.param == "folder":
        return SpecimenStore(tmp_path)
    return ObjectSpecimenStore(request.getfixturevalue("s3_objects"), tmp_path / "tmp", pointer_ttl_s=0.0)


def test_a_written_specimen_loads_with_everything_it_was_given(store):
    write_small_specimen(store, "steel-1", height_um=3.0)
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
    write_small_specimen(store, "steel-1")
    first = store.load("steel-1")
    assert store.load("steel-1") is first
    write_small_specimen(store, "steel-1", height_um=2.0)
    description = tmp_path / "specimens" / "steel-1" / "specimen.json"
    stamp = first.version + 1_000_000  # a rebuild within the file system's time resolution still counts
    os.utime(description, ns=(stamp, stamp))
    rebuilt = store.load("steel-1")
    assert rebuilt is not first and rebuilt.version != first.version
    assert rebuilt.tile_bytes(ROOT_TILE.uri) == b"glTF\x02"


def test_a_rebuild_replaces_the_whole_specimen_and_a_deletion_removes_it(store):
    write_small_specimen(store, "steel-1", height_um=1.0, request_id="build-1")
    first = store.load("steel-1")
    write_small_specimen(store, "steel-1", height_um=2.0, request_id="build-2")
    rebuilt = store.load("steel-1")
    assert rebuilt.version != first.version and rebuilt.request_id == "build-2"
    assert rebuilt.tile_bytes(ROOT_TILE.uri) == b"glTF\x02"
    np.testing.assert_array_equal(rebuilt.heights("overview").z_um, np.full((16, 24), 2.0, np.float32))
    store.delete("steel-1")
    assert store.ids() == []
    with pytest.raises(NotFoundError):
        store.load("steel-1")
    with pytest.raises(NotFoundError) as again:
        store.delete("steel-1")
    assert again.value.field == "specimen_id"


def test_a_failed_build_leaves_the_stored_specimen_as_it_was(store):
    write_small_specimen(store, "steel-1", height_um=1.0)
    with pytest.raises(RuntimeError), store.writing("steel-1") as staging:
        (staging / "specimen.json").write_text("half")
        raise RuntimeError("mesher gone")
    with pytest.raises(RuntimeError), store.writing("steel-2") as staging:
        raise RuntimeError("matcher gone")
    assert store.load("steel-1").tile_bytes(ROOT_TILE.uri) == b"glTF\x01"
    assert store.ids() == ["steel-1"]


def test_a_failed_folder_build_leaves_no_files(tmp_path):
    store = SpecimenStore(tmp_path)
    write_small_specimen(store, "steel-1", height_um=1.0)
    with pytest.raises(RuntimeError), store.writing("steel-1") as staging:
        (staging / "specimen.json").write_text("half")
        raise RuntimeError("mesher gone")
    assert sorted(p.name for p in (tmp_path / "specimens").iterdir()) == ["steel-1"]


def test_leftovers_of_a_killed_writer_are_discarded(tmp_path):
    store = SpecimenStore(tmp_path)
    write_small_specimen(store, "steel-1")
    for leftover in (".staging-steel-2-abc", ".retired-steel-1-def"):
        (tmp_path / "specimens" / leftover).mkdir()
    assert store.ids() == ["steel-1"]
    assert store.recover() == ([], 2)
    assert sorted(p.name for p in (tmp_path / "specimens").iterdir()) == ["steel-1"]


def test_recovery_restores_a_retired_specimen_whose_replacement_never_came(tmp_path):
    """Killed between the two renames: the stored build is the retired copy, its staging twin
    may be anything; the next start restores the retired one instead of deleting both."""
    store = SpecimenStore(tmp_path)
    write_small_specimen(store, "steel-1", height_um=1.0)
    specimens = tmp_path / "specimens"
    (specimens / "steel-1").rename(specimens / ".retired-steel-1-0123abcd")
    (specimens / ".staging-steel-1-0123abcd").mkdir()
    (specimens / ".staging-steel-1-0123abcd" / "specimen.json").write_text("half")
    recovered = SpecimenStore(tmp_path)
    assert recovered.recover() == (["steel-1"], 1)
    assert recovered.load("steel-1").tile_bytes(ROOT_TILE.uri) == b"glTF\x01"
    assert sorted(p.name for p in specimens.iterdir()) == ["steel-1"]


# Writes build 2 over build 1 in a copy of the store for each step k, in a forked child that
# counts the write's steps (fsyncs, renames, removals) and is killed just before the k-th.
_KILLING_WRITER = """
import os, shutil, signal, sys
sys.path.insert(0, sys.argv[1])
from conftest import write_small_specimen
from fractoscope.store.folder import SpecimenStore

def counted(original, state):
    def step(*args, **kwargs):
        state["steps"] += 1
        if state["steps"] == state["kill_at"]:
            os.kill(os.getpid(), signal.SIGKILL)
        return original(*args, **kwargs)
    return step

for kill_at in range(1, 100):
    root = os.path.join(sys.argv[2], str(kill_at))
    write_small_specimen(SpecimenStore(root), "steel-1", height_um=1.0, request_id="build-1")
    child = os.fork()
    if child == 0:
        state = {"steps": 0, "kill_at": kill_at}
        os.fsync, os.rename, shutil.rmtree = (counted(f, state) for f in (os.fsync, os.rename, shutil.rmtree))
        write_small_specimen(SpecimenStore(root), "steel-1", height_um=2.0, request_id="build-2")
        os._exit(0)
    _, status = os.waitpid(child, 0)
    print(kill_at, os.waitstatus_to_exitcode(status), flush=True)
    if status == 0:
        break
"""


@pytest.mark.slow
def test_a_writer_killed_at_any_step_leaves_the_old_or_the_new_build_intact(tmp_path):
    done = subprocess.run(
        [sys.executable, "-c", _KILLING_WRITER, str(Path(__file__).parents[2]), str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=300,
        check=True,
    )
    runs = [tuple(map(int, line.split())) for line in done.stdout.splitlines()]
    assert [code for _, code in runs[:-1]] == [-signal.SIGKILL] * (len(runs) - 1) and runs[-1][1] == 0
    assert len(runs) > 10  # every file and folder fsynced, two renames and their folder fsynced, removals
    served = []
    for kill_at, _ in runs:
        store = SpecimenStore(tmp_path / str(kill_at))
        store.recover()
        specimen = store.load("steel-1")
        build = {"build-1": 1, "build-2": 2}[specimen.request_id]
        assert specimen.tile_bytes(ROOT_TILE.uri) == b"glTF" + bytes([build])
        np.testing.assert_array_equal(specimen.heights("overview").z_um, np.full((16, 24), float(build), np.float32))
        assert json.loads(specimen.tileset_bytes) == {}
        assert sorted(p.name for p in store.root.iterdir()) == ["steel-1"]
        served.append(build)
    assert (
        served[0] == 1 and served[-1] == 2 and served == sorted(served)
    )  # the old build until the new one is in place


def test_every_file_and_folder_is_fsynced_before_its_rename_and_the_renames_after(tmp_path, monkeypatch):
    """The write's journal of fsyncs (by path) and renames: every file and folder of the staging
    copy is flushed before it is renamed into place, and the specimens folder after each rename."""
    store = SpecimenStore(tmp_path)
    write_small_specimen(store, "steel-1", height_um=1.0)
    journal, fsync, rename = [], os.fsync, os.rename
    monkeypatch.setattr(
        os, "fsync", lambda fd: (journal.append(("fsync", os.readlink(f"/proc/self/fd/{fd}"))), fsync(fd))[1]
    )
    monkeypatch.setattr(os, "rename", lambda a, b: (journal.append(("rename", str(a), str(b))), rename(a, b))[1])
    write_small_specimen(store, "steel-1", height_um=2.0)
    renames = [index for index, entry in enumerate(journal) if entry[0] == "rename"]
    assert len(renames) == 2  # stored -> retired, staging -> stored
    specimens = os.path.realpath(tmp_path / "specimens")
    staging, stored = journal[renames[1]][1:]
    flushed = {path.replace(staging, stored) for kind, path, *_ in journal[: renames[0]] if kind == "fsync"}
    assert flushed >= {stored, *(str(path) for path in Path(stored).rglob("*"))}  # every file and folder, itself too
    for index in renames:
        assert journal[index + 1] == ("fsync", specimens)


def test_a_request_id_finds_the_specimen_it_built(store):
    write_small_specimen(store, "steel-1", request_id="lims-7")
    assert store.built_by("steel-1", "lims-7", "digest").request_id == "lims-7"
    assert store.built_by("steel-1", "lims-8", "digest") is None and store.built_by("steel-2", "lims-7", "") is None
    assert store.built_by("steel-1", "", "") is None  # a request without an id built nothing


def test_unknown_and_malformed_names_are_told_apart(store):
    write_small_specimen(store, "steel-1")
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

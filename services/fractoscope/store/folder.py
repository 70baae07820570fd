"""Specimens on disk: `DATA/specimens/{id}/` holds specimen.json, tileset.json, tiles/ and rois/.

A specimen is written in a staging folder, fsynced, and renamed into place (the stored one first
renamed aside as its retired twin, then removed), so readers see the old one or the new one
complete, never half of one. A process killed between the two renames leaves the retired copy
and no specimen; `recover`, at the next start, renames it back. A deleted specimen is renamed
aside as a deleted copy, then removed; `recover` removes what a killed process left of that.

Exports and reports are written in scratch folders under `DATA/tmp` (store.scratch), not the
system's temporary folder: on the data volume, sized for them, and cleared of the folders of
killed processes when a store of that data is made.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import threading
import uuid
from collections.abc import Iterator
from pathlib import Path

from fractoscope.errors import NotFoundError
from fractoscope.specimen.model import ID_PATTERN, Specimen, validate_id
from fractoscope.store.base import StoredSpecimens
from fractoscope.store.scratch import remove_abandoned_scratch

# Folders of unfinished writes: `{prefix}{id}-{token}`, the token shared by a write's two.
_STAGING, _RETIRED = ".staging-", ".retired-"
# Folders of a deletion under way: `{prefix}{id}-{token}`, never restored.
_DELETED = ".deleted-"


class SpecimenStore(StoredSpecimens):
    """The specimens under `root/specimens`, cached in memory once read. A process makes one store
    per directory and hands it to everything that serves it (the tile service and the HTTP
    endpoint), so a specimen's surface is read and held once."""

    def __init__(self, root: Path):
        self.root = Path(root) / "specimens"
        self.root.mkdir(parents=True, exist_ok=True)
        self.scratch_root = Path(root) / "tmp"  # exports' and reports' scratch folders (scratch_folder)
        self._cache: dict[str, tuple[int, Specimen]] = {}
        self._lock = threading.Lock()
        self._commit_lock = threading.Lock()
        remove_abandoned_scratch(self.scratch_root)

    def recover(self) -> tuple[list[str], int]:
        """Undoes what writes of a killed process left; only the one writer may call this, when it
        starts. A retired specimen whose replacement never came into place (the process died
        between the two renames) is restored; every other leftover (staging folders, retired
        copies already replaced) is removed. Returns the restored ids and the number removed."""
        restored, removed = [], 0
        for retired in sorted(self.root.glob(f"{_RETIRED}*")):
            specimen_id = retired.name[len(_RETIRED) :].rpartition("-")[0]
            if ID_PATTERN.fullmatch(specimen_id) and not (self.root / specimen_id).exists():
                retired.rename(self.root / specimen_id)
                restored.append(specimen_id)
            else:
                shutil.rmtree(retired, ignore_errors=True)
                removed += 1
        for leftover in [*self.root.glob(f"{_STAGING}*"), *self.root.glob(f"{_DELETED}*")]:
            shutil.rmtree(leftover, ignore_errors=True)
            removed += 1
        _sync_folder(self.root)
        return restored, removed

    def ids(self) -> list[str]:
        return sorted(
            p.name
            for p in self.root.iterdir()
            if p.is_dir() and ID_PATTERN.fullmatch(p.name) and (p / "specimen.json").is_file()
        )

    def load(self, specimen_id: str, *, fresh: bool = False) -> Specimen:
        """The stored specimen, always as it is on disk now (`fresh` or not: one stat tells)."""
        validate_id(specimen_id, field="specimen_id")
        description_path = self.root / specimen_id / "specimen.json"
        try:
            stamp = description_path.stat().st_mtime_ns
        except FileNotFoundError:
            raise NotFoundError(f"no specimen {specimen_id!r}", field="specimen_id") from None
        with self._lock:
            cached = self._cache.get(specimen_id)
            if cached and cached[0] == stamp:
                return cached[1]
        folder = self.root / specimen_id
        specimen = Specimen(
            lambda relative: (folder / relative).read_bytes(), json.loads(description_path.read_text()), version=stamp
        )
        with self._lock:
            self._cache[specimen_id] = (stamp, specimen)
        return specimen

    @contextlib.contextmanager
    def writing(self, specimen_id: str) -> Iterator[Path]:
        """A staging folder to write a specimen into; on success it is fsynced and replaces the
        stored one at once, on failure it is removed and the stored one stays as it was."""
        token = uuid.uuid4().hex
        staging = self.root / f"{_STAGING}{specimen_id}-{token}"
        staging.mkdir()
        try:
            yield staging
            _sync_tree(staging)
            target, retired = self.root / specimen_id, self.root / f"{_RETIRED}{specimen_id}-{token}"
            with self._commit_lock:  # two builds of one id must not interleave their renames
                if target.exists():
                    target.rename(retired)
                    _sync_folder(self.root)
                staging.rename(target)
                _sync_folder(self.root)
            shutil.rmtree(retired, ignore_errors=True)
        finally:
            shutil.rmtree(staging, ignore_errors=True)

    def delete(self, specimen_id: str) -> None:
        """Removes a stored specimen: renamed aside at once, so readers see it whole or not at all
        (one that still holds it gets NotFoundError for files it had not read), then its files;
        NotFoundError naming `specimen_id` when there is none."""
        validate_id(specimen_id, field="specimen_id")
        target, deleted = self.root / specimen_id, self.root / f"{_DELETED}{specimen_id}-{uuid.uuid4().hex}"
        with self._commit_lock:  # not between the two renames of a build of that id
            if not (target / "specimen.json").is_file():
                raise NotFoundError(f"no specimen {specimen_id!r}", field="specimen_id")
            target.rename(deleted)
            _sync_folder(self.root)
        with self._lock:
            self._cache.pop(specimen_id, None)
        shutil.rmtree(deleted, ignore_errors=True)


def _sync_tree(folder: Path) -> None:
    """Flushes every file and folder under `folder` (and itself) to disk, deepest first."""
    for directory, _, files in os.walk(folder, topdown=False):
        for name in files:
            descriptor = os.open(os.path.join(directory, name), os.O_RDONLY)
            try:
                os.fsync(descriptor)
            finally:
                os.close(descriptor)
        _sync_folder(Path(directory))


def _sync_folder(folder: Path) -> None:
    """Flushes a folder's entries (the renames within it) to disk."""
    descriptor = os.open(folder, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(descriptor)
    finally:
        os.close(descriptor)

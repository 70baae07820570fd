"""Specimens on disk: `DATA/specimens/{id}/` holds specimen.json, tileset.json, tiles/ and rois/.

A specimen is written in a staging folder, fsynced, and renamed into place (the stored one first
renamed aside as its retired twin, then removed), so readers see the old one or the new one
complete, never half of one. A process killed between the two renames leaves the retired copy
and no specimen; `recover`, at the next start, renames it back. A deleted specimen is renamed
aside as a deleted copy, then removed; `recover` removes what a killed process left of that.

Exports and reports are written in scratch folders under `DATA/tmp` (`scratch_folder`), not the
system's temporary folder: on the data volume, sized for them, and cleared of the folders of
killed processes when a store of that data is made.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import os
import re
import shutil
import tempfile
import threading
import uuid
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from fractoscope.errors import AlreadyExistsError, InvalidInputError, NotFoundError
from fractoscope.specimen.fusion import FusedSurface, PlacedRoi, contains, footprint_um, overlaps
from fractoscope.specimen.quadtree import QuadtreeLayout, TileKey, TileRecord

_ID = re.compile(r"[A-Za-z0-9_-]{1,64}")
# Folders of unfinished writes: `{prefix}{id}-{token}`, the token shared by a write's two.
_STAGING, _RETIRED = ".staging-", ".retired-"
# Folders of a deletion under way: `{prefix}{id}-{token}`, never restored.
_DELETED = ".deleted-"
# Scratch folders: `{purpose}-{pid}.{start}-{random}`, named after the process that made them.
_SCRATCH_NAME = re.compile(r"[a-z-]+-(?P<pid>[0-9]+)\.(?P<start>[0-9]+)-[a-z0-9_]+")


def validate_id(value: str, *, field: str) -> str:
    """Specimen and ROI ids: 1 to 64 of A-Z a-z 0-9 _ -, which keeps them safe in paths and URLs."""
    if not _ID.fullmatch(value or ""):
        raise InvalidInputError(field, f"{value!r} is not an id of 1 to 64 letters, digits, '_' or '-'")
    return value


@dataclass
class RoiEntry:
    """An ROI as stored: placement (origin of pixel (0, 0), µm), shape (rows, cols), fit figures,
    the matching report, the datum its heights were levelled on (surface.datum.Datum.to_dict;
    None: as measured), their coverage (surface.measurement.Coverage.to_dict; None: stored before
    it was kept) and its image files (`views`: {"file": path in the specimen folder,
    "name": the name it was given}, reference first; empty for specimens built before they
    were kept)."""

    id: str
    parent: str
    magnification: float
    pixel_size_um: float
    origin_um: tuple[float, float]
    shape: tuple[int, int]
    alignment_residual_um: float = 0.0
    registration_score: float = 0.0
    matching: dict = field(default_factory=dict)
    datum: dict | None = None
    tilt_rel_uncertainty: float | None = None  # relative height error a tilt error makes (None: not known)
    views: list[dict] = field(default_factory=list)
    coverage: dict | None = None

    @property
    def region_um(self) -> tuple[float, float, float, float]:
        return footprint_um(self.origin_um, self.shape, self.pixel_size_um)


# A stored specimen's file by its path in the specimen (e.g. "tiles/0/0/0.glb"); FileNotFoundError when gone.
ReadFile = Callable[[str], bytes]


class Specimen:
    """A stored specimen: ROIs (overview first), tile layout and records, lazily loaded surface,
    its files read by `read` (from a folder or from object storage). `version` tells builds of
    one id apart (the description's modification time, ns, or the build id in object storage),
    so caches key on (id, version) without holding the specimen, and its surface, alive."""

    def __init__(self, read: ReadFile, description: dict, version: int | str = 0):
        self.read = read
        self.version = version
        self.id: str = description["id"]
        self.request_id: str = description.get("request_id", "")
        # What identifies the content of the request that built it ("" for specimens built before it was kept).
        self.request_digest: str = description.get("request_digest", "")
        self.rois = [
            RoiEntry(**{**roi, "origin_um": tuple(roi["origin_um"]), "shape": tuple(roi["shape"])})
            for roi in description["rois"]
        ]
        self.layout = QuadtreeLayout(tuple(description["layout"]["origin_um"]), description["layout"]["size_um"])
        self.tiles = {record.key: record for record in map(TileRecord.from_json, description["tiles"])}

    def roi(self, roi_id: str) -> RoiEntry:
        for roi in self.rois:
            if roi.id == roi_id:
                return roi
        raise NotFoundError(f"specimen {self.id!r} has no ROI {roi_id!r}", field="roi")

    def pixel_size_at_magnification(self, magnification: float) -> float:
        """Pixel size, µm, that a magnification means here (inversely proportional, from the overview)."""
        overview = self.rois[0]
        if overview.magnification <= 0:
            raise InvalidInputError(
                "magnification", f"specimen {self.id!r} was built without magnifications; give them in its manifest"
            )
        pixel_size_um = overview.pixel_size_um * overview.magnification / magnification
        if not (math.isfinite(pixel_size_um) and pixel_size_um > 0):
            raise InvalidInputError("magnification", f"{magnification} gives no usable pixel size")
        return pixel_size_um

    def finest_pixel_size_um(self, region_um: tuple[float, float, float, float], *, holding: bool = False) -> float:
        """The smallest pixel size among the ROIs that meet a region, or with `holding` that hold
        all of it (the overview's if none)."""
        meets = contains if holding else overlaps
        sizes = [roi.pixel_size_um for roi in self.rois if meets(roi.region_um, region_um)]
        return min(sizes) if sizes else self.rois[0].pixel_size_um

    def heights(self, roi_id: str) -> PlacedRoi:
        return next(placed for placed in self.surface.rois if placed.id == roi_id)

    @cached_property
    def surface(self) -> FusedSurface:
        placed = []
        for roi in self.rois:
            with self._stored_file(), np.load(io.BytesIO(self.read(f"rois/{roi.id}.npz"))) as arrays:
                # Specimens built before they were kept have none.
                sigma_um = arrays["sigma_um"] if "sigma_um" in arrays else None
                filled = arrays["filled"] if "filled" in arrays else None
                placed.append(
                    PlacedRoi(
                        roi.id,
                        roi.magnification,
                        roi.pixel_size_um,
                        roi.origin_um,
                        arrays["z_um"],
                        arrays["texture"],
                        sigma_um,
                        filled=filled,
                    )
                )
        return FusedSurface(placed)

    @cached_property
    def tileset_bytes(self) -> bytes:
        with self._stored_file():
            return self.read("tileset.json")

    def tile_record(self, uri: str) -> TileRecord:
        try:
            key = TileKey.from_uri(uri)
        except ValueError:
            raise InvalidInputError("uri", f"{uri!r} is not a tile URI of the form tiles/LEVEL/COL/ROW.glb") from None
        if key not in self.tiles:
            raise NotFoundError(f"specimen {self.id!r} has no tile {uri!r}", field="uri")
        return self.tiles[key]

    def view_bytes(self, roi_id: str, index: int) -> bytes:
        """The image file of view `index` (0: the reference) of an ROI, as it was given."""
        views = self.roi(roi_id).views
        if not 0 <= index < len(views):
            raise NotFoundError(f"ROI {roi_id!r} of specimen {self.id!r} keeps no view {index}")
        with self._stored_file():
            return self.read(views[index]["file"])

    def tile_bytes(self, uri: str) -> bytes:
        """The GLB of a tile named as in tileset.json."""
        record = self.tile_record(uri)
        with self._stored_file():
            return self.read(record.key.uri)

    @contextlib.contextmanager
    def _stored_file(self) -> Iterator[None]:
        """A file of this specimen gone since it was loaded: the specimen was deleted or rebuilt
        meanwhile, which is NotFoundError as for an unknown one (loading it again finds a rebuild)."""
        try:
            yield
        except FileNotFoundError:
            raise NotFoundError(
                f"specimen {self.id!r} was deleted or rebuilt while it was read; load it again", field="specimen_id"
            ) from None


class StoredSpecimens:
    """What every specimen store does alike, over its `load`: this folder store and the object
    store's (fractoscope.store.specimens). `objects` is the object storage that replicas share
    (None: this process alone owns the store)."""

    objects = None

    def load(self, specimen_id: str) -> Specimen:
        raise NotImplementedError

    def building(self, specimen_id: str) -> contextlib.AbstractContextManager[None]:
        """Held for the whole of one build of `specimen_id`: a process that owns its store builds
        alone, its job runner keeping builds of one request apart."""
        return contextlib.nullcontext()

    def built_by(self, specimen_id: str, request_id: str, digest: str) -> Specimen | None:
        """The stored specimen that a request with `request_id` and content `digest` (a digest of
        the request without its id) built, if any; AlreadyExistsError naming request_id when that
        id built it from other content. A request without an id built nothing."""
        if not request_id:
            return None
        try:
            existing = self.load(specimen_id)
        except NotFoundError:
            return None
        if existing.request_id != request_id:
            return None
        # A specimen built before digests were kept has none: its content cannot be compared.
        if existing.request_digest and existing.request_digest != digest:
            raise AlreadyExistsError(
                f"request_id {request_id!r} built specimen {specimen_id!r} from other content; give this request a "
                "new request_id",
                field="request_id",
            )
        return existing


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
            if _ID.fullmatch(specimen_id) and not (self.root / specimen_id).exists():
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
            if p.is_dir() and _ID.fullmatch(p.name) and (p / "specimen.json").is_file()
        )

    def load(self, specimen_id: str) -> Specimen:
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


@contextlib.contextmanager
def scratch_folder(root: Path, purpose: str) -> Iterator[Path]:
    """A new folder under `root` (SpecimenStore.scratch_root) for one export's or report's files,
    removed on exit. Its name carries `purpose` (lower-case letters and '-') and this process's
    identity, so that a store made by another process removes it only once this one has gone."""
    root.mkdir(parents=True, exist_ok=True)
    folder = Path(tempfile.mkdtemp(prefix=f"{purpose}-{process_identity(os.getpid())}-", dir=root))
    try:
        yield folder
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def remove_abandoned_scratch(root: Path) -> None:
    """Removes the scratch folders under `root` of processes that no longer run (killed mid-export);
    those of running processes stay, this one's included: several servers of one process, or
    processes of one host, may share a data directory. (Processes of separate PID namespaces, e.g.
    containers, must not share one: each would take the other's processes for gone.)"""
    if not root.is_dir():
        return
    for folder in root.iterdir():
        named = _SCRATCH_NAME.fullmatch(folder.name)
        if named and process_identity(int(named["pid"])) != f"{named['pid']}.{named['start']}":
            shutil.rmtree(folder, ignore_errors=True)


def process_identity(pid: int) -> str | None:
    """`{pid}.{start}` of a running process, its start time (clock ticks after boot, field 22 of
    /proc/PID/stat) telling it apart from a later process given the same pid, as a restarted
    container's server is; None when no process has that pid."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return f"{pid}.{stat.rpartition(')')[2].split()[19]}"


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


def write_description(
    directory: Path,
    *,
    specimen_id: str,
    request_id: str,
    rois: list[RoiEntry],
    layout: QuadtreeLayout,
    tiles: dict[TileKey, TileRecord],
    request_digest: str = "",
) -> None:
    """specimen.json: everything about a specimen except arrays and tiles' bytes; `request_digest`
    identifies the content of the request that built it (see Specimen.request_digest)."""
    description = {
        "id": specimen_id,
        "request_id": request_id,
        "request_digest": request_digest,
        "rois": [asdict(roi) for roi in rois],
        "layout": {"origin_um": list(layout.origin_um), "size_um": layout.size_um},
        "tiles": [record.to_json() for _, record in sorted(tiles.items())],
    }
    (directory / "specimen.json").write_text(json.dumps(description, indent=1))


def write_roi_arrays(directory: Path, roi: PlacedRoi) -> None:
    """rois/{id}.npz: z_um, texture and, when known, sigma_um and filled."""
    (directory / "rois").mkdir(exist_ok=True)
    arrays = {"z_um": roi.z_um, "texture": roi.texture}
    arrays |= {name: value for name in ("sigma_um", "filled") if (value := getattr(roi, name)) is not None}
    np.savez_compressed(directory / "rois" / f"{roi.id}.npz", **arrays)


def write_roi_views(directory: Path, roi_id: str, images) -> list[dict]:
    """rois/{id}.view{N}: the ROI's image files ((name, bytes), reference first) as given; returns
    the RoiEntry's `views`."""
    (directory / "rois").mkdir(exist_ok=True)
    views = []
    for index, (name, content) in enumerate(images):
        relative = f"rois/{roi_id}.view{index}"
        (directory / relative).write_bytes(content)
        views.append({"file": relative, "name": name})
    return views

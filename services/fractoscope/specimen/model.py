"""A specimen as stored: its description (specimen.json: ROIs, tile layout and records), its ROIs'
arrays (rois/{id}.npz) and image files, read lazily through a function that reads its files, from
a folder or from object storage (fractoscope.store). The writers here lay out a specimen's files
in the folder a store hands out (`writing`)."""

from __future__ import annotations

import contextlib
import io
import json
import math
import re
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from fractoscope.errors import InvalidInputError, NotFoundError
from fractoscope.specimen.fusion import FusedSurface, PlacedRoi, contains, footprint_um, overlaps
from fractoscope.specimen.quadtree import QuadtreeLayout, TileKey, TileRecord

# Specimen and ROI ids (validate_id); stores tell their specimens' folders and objects by them.
ID_PATTERN = re.compile(r"[A-Za-z0-9_-]{1,64}")


def validate_id(value: str, *, field: str) -> str:
    """Specimen and ROI ids: 1 to 64 of A-Z a-z 0-9 _ -, which keeps them safe in paths and URLs."""
    if not ID_PATTERN.fullmatch(value or ""):
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

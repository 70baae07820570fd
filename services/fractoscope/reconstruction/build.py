"""Building a specimen: measure every ROI, place children in their parents, fuse, tile, store.

Matching and meshing are passed in as functions, so the tile service can run them on the other
services and tests can run them in-process.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from fractoscope.errors import InvalidInputError
from fractoscope.mesh.outline import Unmeasured
from fractoscope.progress import ProgressCallback, silent
from fractoscope.specimen import registration
from fractoscope.specimen.fusion import FusedSurface, PlacedRoi
from fractoscope.specimen.model import (
    RoiEntry,
    Specimen,
    validate_id,
    write_description,
    write_roi_arrays,
    write_roi_views,
)
from fractoscope.specimen.quadtree import QuadtreeLayout, TileKey, TileRecord, TileSamples, build_tiles
from fractoscope.specimen.tileset import tileset_json
from fractoscope.stereo import geometry
from fractoscope.store.base import StoredSpecimens
from fractoscope.surface import measurement


@dataclass(frozen=True)
class RoiRequest:
    """One ROI to build: its parent ('' for the overview), magnification, centre in the parent's
    frame (x, y) µm or None to register it automatically, for the overview the datum its heights
    are levelled on ('' none, else one of surface.datum.LEVELS), and its image files as given
    ((file name, bytes), reference first), which the specimen keeps with its heights."""

    id: str
    parent: str = ""
    magnification: float = 0.0
    center_um: tuple[float, float] | None = None
    level: str = ""
    images: tuple[tuple[str, bytes], ...] = ()


@dataclass(frozen=True)
class MeasuredHeights:
    """What matching returns for an ROI: heights (rows, cols) µm, grey texture, pixel size µm, the
    matching report (see MatchingReport) and the heights' one-sigma uncertainty (µm, None: not
    known), tilt part included."""

    z_um: np.ndarray
    texture: np.ndarray
    pixel_size_um: float
    report: dict
    sigma_um: np.ndarray | None = None


# An ROI's heights, reporting the matching's progress (fraction 0 to 1) to the callback.
Measure = Callable[[RoiRequest, ProgressCallback], MeasuredHeights]
TileMesher = Callable[[TileSamples], bytes]


def ordered_rois(rois: Sequence[RoiRequest]) -> list[RoiRequest]:
    """The ROIs with every parent before its children; checks ids, the single overview and parents."""
    if not rois:
        raise InvalidInputError("rois", "a specimen needs at least one ROI")
    by_id: dict[str, RoiRequest] = {}
    for index, roi in enumerate(rois):
        validate_id(roi.id, field=f"rois[{index}].id")
        if roi.id in by_id:
            raise InvalidInputError(f"rois[{index}].id", f"ROI id {roi.id!r} is used twice")
        by_id[roi.id] = roi
    overviews = [roi.id for roi in rois if not roi.parent]
    if len(overviews) != 1:
        raise InvalidInputError("rois", f"exactly one ROI must have no parent (the overview); found {len(overviews)}")
    for index, roi in enumerate(rois):
        if roi.parent and roi.parent not in by_id:
            raise InvalidInputError(f"rois[{index}].parent", f"no ROI {roi.parent!r} in this specimen")
    ordered, placed = [], set()
    while len(ordered) < len(rois):
        ready = [roi for roi in rois if roi.id not in placed and (not roi.parent or roi.parent in placed)]
        if not ready:
            raise InvalidInputError("rois", "the ROIs' parents form a cycle")
        for roi in ready:
            ordered.append(roi)
            placed.add(roi.id)
    return ordered


def reconstruct_specimen(
    specimen_id: str,
    rois: Sequence[RoiRequest],
    *,
    measure: Measure,
    mesh_tile: TileMesher,
    store: StoredSpecimens,
    request_id: str = "",
    request_digest: str = "",
    progress: ProgressCallback | None = None,
    unmeasured: Unmeasured = Unmeasured.ABSENT,
) -> Specimen:
    """Builds and stores a specimen, with the id and the content digest of the request it builds
    (see Specimen.request_digest); returns it as stored. Errors name the ROI by its index in
    `rois` (`rois[1].center_um`). `unmeasured`: how the tiles show what nothing measured."""
    report = progress or silent
    validate_id(specimen_id, field="specimen_id")
    ordered = ordered_rois(rois)
    measured: dict[str, MeasuredHeights] = {}
    for index, roi in enumerate(ordered):
        start, share = 0.6 * index / len(ordered), 0.6 / len(ordered)
        report(start, f"matching ROI {roi.id}")

        def roi_progress(fraction: float, message: str, roi=roi, start=start, share=share) -> None:
            report(start + share * fraction, f"matching ROI {roi.id}: {message}")

        measured[roi.id] = measure(roi, roi_progress)
    report(0.6, "placing ROIs")
    placed, entries = _place(ordered, measured, {roi.id: index for index, roi in enumerate(rois)})
    surface = FusedSurface(list(placed.values()))
    layout = QuadtreeLayout.covering(surface)
    with store.writing(specimen_id) as staging:
        records = _write_tiles(staging, surface, layout, mesh_tile, report, unmeasured=unmeasured)
        for roi in placed.values():
            write_roi_arrays(staging, roi)
        for roi, entry in zip(ordered, entries):
            entry.views = write_roi_views(staging, roi.id, roi.images)
        (staging / "tileset.json").write_text(json.dumps(tileset_json(layout, records)))
        write_description(
            staging,
            specimen_id=specimen_id,
            request_id=request_id,
            request_digest=request_digest,
            rois=entries,
            layout=layout,
            tiles=records,
        )
    report(1.0, "stored")
    return store.load(specimen_id)


def store_height_map(
    store: StoredSpecimens,
    specimen_id: str,
    z_um: np.ndarray,
    *,
    pixel_size_um: float,
    report: dict,
    sigma_um: np.ndarray | None = None,
    filled: np.ndarray | None = None,
    tilt_rel_uncertainty: float | None = None,
    datum: dict | None = None,
) -> Specimen:
    """Stores one height map as it is (no filtering, placement, tiles or image files) as a specimen
    of one ROI, "overview": what a measurement report of a height map file reads. z_um (rows, cols)
    µm, NaN unknown; sigma_um its matching noise, µm (the tilt part left out, see PlacedRoi);
    `filled` the points interpolated rather than matched; the matching `report` (MatchingReport's
    fields), the relative height error a tilt error makes and the datum as RoiEntry keeps them."""
    validate_id(specimen_id, field="specimen_id")
    z_um = np.asarray(z_um, np.float32)
    entry = RoiEntry(
        "overview",
        "",
        0.0,
        pixel_size_um,
        (0.0, 0.0),
        z_um.shape,
        matching=report,
        datum=datum,
        tilt_rel_uncertainty=tilt_rel_uncertainty,
        coverage=measurement.coverage(z_um, filled).to_dict(),
    )
    placed = PlacedRoi(
        entry.id,
        0.0,
        pixel_size_um,
        entry.origin_um,
        z_um,
        np.zeros(z_um.shape, np.uint8),
        sigma_um=sigma_um,
        filled=filled,
    )
    with store.writing(specimen_id) as staging:
        write_roi_arrays(staging, placed)
        write_description(
            staging,
            specimen_id=specimen_id,
            request_id="",
            rois=[entry],
            layout=QuadtreeLayout.covering(FusedSurface([placed])),
            tiles={},
        )
    return store.load(specimen_id)


def _place(
    ordered: list[RoiRequest], measured: dict[str, MeasuredHeights], indices: dict[str, int]
) -> tuple[dict[str, PlacedRoi], list[RoiEntry]]:
    """Every ROI's filtered heights and texture placed in the specimen frame, parents first: the
    overview levelled on its datum if it names one, a child registered in its parent (unless its
    centre is given), its heights brought onto the parent's by a fitted plane and its texture
    onto the parent's brightness and contrast. A placement that fails names the ROI as `rois[i]`
    (its index in the request, `indices`)."""
    placed: dict[str, PlacedRoi] = {}
    entries: list[RoiEntry] = []
    for roi in ordered:
        heights = measured[roi.id]
        texture = _grey8(heights.texture)
        try:
            kept = _measurement(heights, roi.level or None)
        except ValueError as error:
            raise InvalidInputError(f"rois[{indices[roi.id]}].level", str(error)) from None
        z_um, sigma_um = kept.z_um, kept.local_sigma_um
        entry = RoiEntry(
            roi.id,
            roi.parent,
            roi.magnification,
            heights.pixel_size_um,
            (0.0, 0.0),
            z_um.shape,
            matching=heights.report,
            datum=kept.datum.to_dict() if kept.datum else None,
            tilt_rel_uncertainty=kept.tilt_rel_uncertainty if sigma_um is not None else None,
            coverage=measurement.coverage(z_um, kept.filled).to_dict(),
        )
        walls = _wall_settings(heights, sigma_um)
        if roi.parent:
            parent = placed[roi.parent]
            try:
                entry.origin_um, entry.registration_score = _child_origin(roi, parent, texture, heights)
                unaligned = PlacedRoi(
                    roi.id, roi.magnification, heights.pixel_size_um, entry.origin_um, z_um, texture, **walls
                )
                alignment = registration.align_heights(parent, unaligned)
            except InvalidInputError as error:  # registration names fields as rois.*
                raise InvalidInputError(
                    error.field.replace("rois", f"rois[{indices[roi.id]}]", 1), error.message
                ) from None
            z_um = registration.apply_height_alignment(z_um, alignment, pixel_size_um=heights.pixel_size_um)
            texture = registration.match_texture(parent, unaligned)
            entry.alignment_residual_um = alignment.residual_um
            entry.matching["warnings"] = [*entry.matching.get("warnings", ()), *_sign_warnings(roi, alignment)]
        placed[roi.id] = PlacedRoi(
            roi.id,
            roi.magnification,
            heights.pixel_size_um,
            entry.origin_um,
            z_um,
            texture,
            sigma_um=sigma_um,
            filled=kept.filled,
            **walls,
        )
        entries.append(entry)
    return placed, entries


# Heights of one area that correlate below this on the overlap run against each other: one of the
# two ROIs has its relief upside down (its tilts typed reversed, its images swapped).
_OPPOSED_CORRELATION = -0.5


def _sign_warnings(roi: RoiRequest, alignment: registration.HeightAlignment) -> list[str]:
    """A warning where a child's heights run against its parent's on their overlap."""
    if not alignment.height_correlation < _OPPOSED_CORRELATION:
        return []
    return [
        f"ROI {roi.id!r}'s heights run against its parent {roi.parent!r}'s on their overlap (correlation "
        f"{alignment.height_correlation:.2f}): one of the two is upside down; check both's tilts and image order, "
        "or give relief_sign in their matching"
    ]


def _measurement(heights: MeasuredHeights, level: str | None) -> measurement.Measurement:
    """An ROI's heights as kept (surface.measurement, as `fracto height` keeps them): cleaned, its
    matching noise apart from the tilt's part (whose ε_z the entry keeps), levelled on `level`.
    The tilt uncertainty is the one the pipeline's sigma used (the report's tilt_uncertainty_deg)."""
    report = heights.report
    return measurement.measurement(
        heights.z_um,
        heights.sigma_um,
        pixel_size_um=heights.pixel_size_um,
        tilt_deg=report.get("tilt_deg") or [],
        tilt_uncertainty_deg=report.get("tilt_uncertainty_deg"),
        level=level,
    )


def _write_tiles(
    staging, surface: FusedSurface, layout: QuadtreeLayout, mesh_tile: TileMesher, report, *, unmeasured: Unmeasured
) -> dict[TileKey, TileRecord]:
    """Walks the quadtree, meshes its tiles two at a time and writes their GLBs under `staging`;
    the first failed tile stops the walk."""
    meshers = ThreadPoolExecutor(max_workers=2)
    pending, failures = [], []

    def _record_failure(done) -> None:
        if not done.cancelled() and done.exception() is not None:  # cancelled: the build is stopping anyway
            failures.append(done.exception())

    def emit(key: TileKey, samples: TileSamples) -> None:
        if failures:  # fail fast: a mesher that cannot be reached will not come back mid-build
            raise failures[0]
        job = meshers.submit(mesh_tile, samples)
        job.add_done_callback(_record_failure)
        pending.append((key, job))
        report(0.65 + 0.3 * (1 - 0.5 ** (len(pending) / 16)), f"tile {key.uri}")

    try:
        records = build_tiles(surface, layout, emit, unmeasured=unmeasured)
        for key, glb in pending:
            path = staging / key.uri
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(glb.result())
    finally:
        meshers.shutdown(wait=True, cancel_futures=True)
    return records


def _wall_settings(heights: MeasuredHeights, sigma_um: np.ndarray | None) -> dict:
    """PlacedRoi's max_slope from the pair's tilts and noise_um, the median of its heights'
    matching sigma (`_matching_sigma`)."""
    tilts = heights.report.get("tilt_deg") or []
    if len(tilts) < 2:
        return {}
    settings = {"max_slope": geometry.max_measurable_slope(tilts)}
    if sigma_um is not None and np.isfinite(sigma_um).any():
        settings["noise_um"] = float(np.nanmedian(sigma_um))
    return settings


def given_child_origin_um(
    center_um: tuple[float, float],
    shape: tuple[int, int],
    pixel_size_um: float,
    parent_origin_um: tuple[float, float] = (0.0, 0.0),
) -> tuple[float, float]:
    """Where a child ROI of (rows, cols) `shape` whose centre is given at `center_um` (x, y in its
    parent's frame: the parent's pixel (0, 0) at the origin) has its pixel (0, 0), µm, in the
    frame where the parent's pixel (0, 0) is at `parent_origin_um`."""
    rows, cols = shape
    half_x_um, half_y_um = (cols - 1) / 2 * pixel_size_um, (rows - 1) / 2 * pixel_size_um
    return parent_origin_um[0] + center_um[0] - half_x_um, parent_origin_um[1] + center_um[1] - half_y_um


def _child_origin(
    roi: RoiRequest, parent: PlacedRoi, texture: np.ndarray, heights: MeasuredHeights
) -> tuple[tuple[float, float], float]:
    """Where the child's pixel (0, 0) lies in the specimen frame, µm, and the registration score."""
    rows, cols = heights.z_um.shape
    if roi.center_um is not None:
        return given_child_origin_um(roi.center_um, (rows, cols), heights.pixel_size_um, parent.origin_um), 0.0
    image_rows = rows - int(heights.report.get("data_bar_rows", 0))
    found = registration.register_child(
        parent.texture,
        texture[:image_rows],
        parent_pixel_size_um=parent.pixel_size_um,
        child_pixel_size_um=heights.pixel_size_um,
    )
    if found.score < registration.MIN_REGISTRATION_SCORE:
        raise InvalidInputError(
            "rois.center_um",
            f"automatic placement found no convincing match for ROI {roi.id!r} in {roi.parent!r} (registration score "
            f"{found.score:.3f}, below {registration.MIN_REGISTRATION_SCORE}); give its center_um",
        )
    col_px, row_px = found.origin_px
    origin = (parent.origin_um[0] + col_px * parent.pixel_size_um, parent.origin_um[1] + row_px * parent.pixel_size_um)
    return origin, found.score


def _grey8(texture: np.ndarray) -> np.ndarray:
    """8-bit grey of a uint8 or uint16 texture (16-bit spread over its 0.1 to 99.9 percentiles)."""
    if texture.dtype == np.uint8:
        return texture
    low, high = np.percentile(texture, (0.1, 99.9))
    return np.clip((texture.astype(np.float32) - low) * 255.0 / max(high - low, 1.0), 0, 255).astype(np.uint8)

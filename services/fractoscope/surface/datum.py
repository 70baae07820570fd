"""Where height zero is: a datum plane fitted to the whole surface, to its substrate, or to a region.

Stereo heights are relative (their offset is arbitrary, and an uneven stage leaves a tilt). A
datum gives them a meaning: with the "substrate" datum, the heights of a grain lying on a flat
substrate are its heights above that substrate. Each datum is a plane fitted by robust least
squares (surface.form_removal) and subtracted; heights are (rows, cols) µm, NaN unknown, and a
region is (x_min, y_min, x_max, y_max) µm with x = col * pixel size, y = row * pixel size.

A datum checks itself (`datum_doubt`): the substrate search always finds some "lowest level",
even on a surface that has none (a rough surface, or a grain on a background the matcher barely
measured), so the level it finds must be measured over an extensive area and be flat: its
heights scatter about its plane by little more than their own sigma, or by little against the
relief standing on it. A substrate that fails is never replaced by a plane through all heights,
which goes through whatever stands on the substrate (a particle filling most of a barely
measured field tilts it by tens of degrees). It is replaced by the background plane
(`_background`): the plane under the lowest heights of blocks spread over the map, taken only
when it lies under the whole surface; else the heights stay as measured ("none"). Either comes
with a warning that says which and why (or is refused, when asked to be strict): a long matching
is not thrown away for a datum, and zero never claims to be a substrate that was not found.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import numpy as np

from fractoscope.surface.form_removal import remove_form

LEVELS = ("plane", "substrate")
# The substrate search starts from the lowest fifth of the heights and grows by points within
# this many robust sigmas of its plane.
_SUBSTRATE_START_QUANTILE = 0.2
_SUBSTRATE_SIGMAS = 3.0
_SUBSTRATE_ROUNDS = 4
# A level is measured over at least this share of the map, and at least this share of its points
# were measured rather than filled.
MIN_LEVEL_AREA = 0.1
MIN_MEASURED_SHARE = 0.5
# A level is flat: its residual RMS is at most this many times its heights' median sigma (on the
# real pollen pairs 1.7 at ±3°, 2.4 at ±6° and 3.0 at ±9°: the substrate's own unevenness, about
# 0.4 µm, counts more as the sigma falls), or at most this share of the relief (1st to 99th
# percentile of the levelled heights; 0.015 on the pollen pairs, about 0.2 on a rough surface).
MAX_RESIDUAL_SIGMAS = 3.0
MAX_RELIEF_SHARE = 0.05
# The background plane: the map is cut into BACKGROUND_BLOCKS x BACKGROUND_BLOCKS blocks, each with
# at least BACKGROUND_MIN_POINTS measured points giving its low level (the median of its lowest
# fifth); the plane rests on at least BACKGROUND_MIN_BLOCKS of them, spread over half the map's
# width and height, each measured on the plane over BACKGROUND_LEVEL_SHARE of its area, and at
# most BACKGROUND_MAX_BELOW of the measured points lie below it by more than the flatness
# tolerance (a plane through a feature leaves much of it below).
BACKGROUND_BLOCKS = 8
BACKGROUND_MIN_POINTS = 16
BACKGROUND_MIN_BLOCKS = 4
BACKGROUND_LEVEL_SHARE = 0.5
BACKGROUND_MAX_BELOW = 0.01


@dataclass(frozen=True)
class Datum:
    """How heights were levelled: `level` ("plane", "substrate", "region", or where no substrate was
    found "background" (the background plane) or "none" (heights as measured, nothing subtracted)),
    the region (µm) for "region", and the plane that was subtracted: z = offset_um + slope_x x +
    slope_y y (x, y µm), with the figures that tell whether it is a measured level (NaN, None in
    to_dict, where none was fitted):

    fraction: share of the known (measured or filled) points that carry the fit;
    area_fraction: share of the whole map's area that carries it;
    measured_fraction: share of those points that were measured rather than filled (only they
        enter the fit);
    residual_rms_um: RMS of the measured points' residuals from the plane, µm;
    sigma_um: their heights' median sigma, µm (NaN: not known; None in to_dict);
    relief_um: 1st to 99th percentile of all levelled heights, µm;
    tilt_deg: the plane's angle to the map's x-y plane, degrees;
    requested: the level asked for ("substrate" where the substrate failed and `level` says what
        stands in for it);
    warning: why the datum is not the level asked for, or why a region is no level ("" none)."""

    level: str
    offset_um: float
    slope_x: float
    slope_y: float
    region_um: tuple[float, float, float, float] | None = None
    fraction: float = 1.0
    area_fraction: float = 1.0
    measured_fraction: float = 1.0
    residual_rms_um: float = float("nan")
    sigma_um: float = float("nan")
    relief_um: float = float("nan")
    tilt_deg: float = 0.0
    requested: str = ""
    warning: str = ""

    def to_dict(self) -> dict:
        values = asdict(self)
        values["region_um"] = list(self.region_um) if self.region_um else None
        # strict JSON: null unknown
        return {k: None if isinstance(v, float) and not np.isfinite(v) else v for k, v in values.items()}


def level_heights(
    z_um: np.ndarray,
    *,
    pixel_size_um: float,
    level: str | tuple[float, float, float, float],
    sigma_um: np.ndarray | None = None,
    filled: np.ndarray | None = None,
    strict: bool = False,
) -> tuple[np.ndarray, Datum]:
    """Heights with the datum plane subtracted (float32) and the datum. `level`: "plane" (a plane
    through all measured heights), "substrate" (through the lowest extensive level: the points
    near a plane grown from the lowest fifth of the heights) or a region (x_min, y_min, x_max,
    y_max) µm. `sigma_um` (rows, cols) µm: the heights' matching noise (the tilt part, shared by
    neighbours, left out), for the flatness check; `filled` (rows, cols) bool: points interpolated
    rather than measured, which stay out of the fit. A substrate that fails `datum_doubt` gives the
    background plane or no levelling ("none"), with a warning that says which and why, or
    ValueError when `strict`; ValueError too when the region or datum holds too few measured
    points."""
    z = np.asarray(z_um, np.float64)
    known = np.isfinite(z)
    measured = known & ~np.asarray(filled, bool) if filled is not None else known
    if isinstance(level, str):
        if level not in LEVELS:
            raise ValueError(f"level must be one of {', '.join(LEVELS)} or a region, not {level!r}")
        # The substrate grows over measured points only: a fill across a hole is no level.
        region = known if level == "plane" else _substrate(z, measured, pixel_size_um)
        name, region_um = level, None
    else:
        region_um, region = _region(level, known, pixel_size_um)
        name = "region"
    levelled, datum = _fitted(z, region, measured, pixel_size_um, name, region_um, sigma_um)
    doubt = datum_doubt(datum) if name != "plane" else ""
    if doubt and name == "substrate":
        if strict:
            raise ValueError(f"no measured substrate: {doubt}")
        return _instead_of_substrate(z, measured, pixel_size_um, sigma_um, doubt)
    return levelled, replace(datum, warning=f"the region is no measured level: {doubt}" if doubt else "")


def _instead_of_substrate(z, measured, pixel_size_um, sigma_um, doubt) -> tuple[np.ndarray, Datum]:
    """The background plane's levelling where the substrate failed (`doubt` says why), else the
    heights as measured; the datum's warning says which it is."""
    background, blocks = _background(z, measured, sigma_um)
    if background is not None:
        levelled, plane = _fitted(z, background, measured, pixel_size_um, "background", None, sigma_um)
        warning = (
            f"no measured substrate ({doubt}): zero is on the background plane under the lowest heights of {blocks} "
            f"blocks across the map, under all but {100 * BACKGROUND_MAX_BELOW:g} % of the measured heights at most"
        )
        return levelled, replace(plane, requested="substrate", warning=warning)
    nan = float("nan")
    warning = (
        f"no measured substrate ({doubt}), and no plane lies under the whole surface: the heights are left as "
        "measured (no plane subtracted; a plane through all heights would go through what stands on the substrate)"
    )
    none = Datum("none", 0.0, 0.0, 0.0, fraction=0.0, area_fraction=0.0, measured_fraction=nan, requested="substrate")
    return z.astype(np.float32), replace(none, residual_rms_um=nan, relief_um=_relief(z, measured), warning=warning)


def datum_doubt(datum: Datum) -> str:
    """Why `datum`'s fit is no measured, extensive, flat level ("" when it is one): measured over
    less than MIN_LEVEL_AREA of the map, mostly filled, or scattering by more than
    MAX_RESIDUAL_SIGMAS sigmas and by more than MAX_RELIEF_SHARE of the relief."""
    doubts = []
    measured_area = datum.area_fraction * datum.measured_fraction
    if measured_area < MIN_LEVEL_AREA:
        doubts.append(
            f"only {100 * measured_area:.1f} % of the map is measured on it, {100 * MIN_LEVEL_AREA:g} % needed"
        )
    if datum.measured_fraction < MIN_MEASURED_SHARE:
        doubts.append(f"{100 * (1 - datum.measured_fraction):.0f} % of its points are filled, not measured")
    too_rough = not datum.residual_rms_um <= MAX_RELIEF_SHARE * datum.relief_um
    if too_rough and not datum.residual_rms_um <= MAX_RESIDUAL_SIGMAS * datum.sigma_um:
        against = (
            f"{datum.residual_rms_um / datum.sigma_um:.1f} times their sigma of {datum.sigma_um:.3g} µm"
            if datum.sigma_um > 0
            else "their sigma unknown"
        )
        doubts.append(
            f"its heights scatter by {datum.residual_rms_um:.3g} µm RMS about its plane ({against}), "
            f"{100 * datum.residual_rms_um / datum.relief_um:.0f} % of the {datum.relief_um:.3g} µm relief"
        )
    return "; ".join(doubts)


def _region(
    level: tuple[float, float, float, float], known: np.ndarray, pixel_size_um: float
) -> tuple[tuple[float, float, float, float], np.ndarray]:
    """The region (x_min, y_min, x_max, y_max) µm as floats and its known points."""
    region_um = tuple(float(v) for v in level)
    x0, y0, x1, y1 = region_um
    if not (x0 < x1 and y0 < y1):
        raise ValueError("the region's minimum must be smaller than its maximum in x and y")
    rows, cols = np.indices(known.shape)
    x_um, y_um = cols * pixel_size_um, rows * pixel_size_um
    return region_um, known & (x_um >= x0) & (x_um <= x1) & (y_um >= y0) & (y_um <= y1)


def _fitted(z, region, measured, pixel_size_um, name, region_um, sigma_um) -> tuple[np.ndarray, Datum]:
    """The heights levelled on the plane through `region`'s measured points, and its Datum."""
    carrying = region & measured
    if carrying.sum() < 3:
        raise ValueError(f"the {name} datum needs at least 3 measured points, found {int(carrying.sum())}")
    offset, slope_x, slope_y = _plane(z, carrying, pixel_size_um)
    rows, cols = np.indices(z.shape)
    levelled = z - (offset + slope_x * cols * pixel_size_um + slope_y * rows * pixel_size_um)
    sigma = np.asarray(sigma_um, np.float64)[carrying] if sigma_um is not None else np.empty(0)
    sigma = sigma[np.isfinite(sigma)]
    datum = Datum(
        name,
        offset,
        slope_x,
        slope_y,
        region_um,
        fraction=float(region.sum() / max(np.isfinite(z).sum(), 1)),
        area_fraction=float(region.mean()),
        measured_fraction=float(carrying.sum() / region.sum()),
        residual_rms_um=float(np.sqrt(np.mean(levelled[carrying] ** 2))),
        sigma_um=float(np.median(sigma)) if sigma.size else float("nan"),
        relief_um=_relief(levelled, measured),
        tilt_deg=float(np.degrees(np.arctan(np.hypot(slope_x, slope_y)))),
        requested=name,
    )
    return levelled.astype(np.float32), datum


def _plane(z: np.ndarray, region: np.ndarray, pixel_size_um: float) -> tuple[float, float, float]:
    """(offset, slope along x, slope along y) of the robust plane through `region`."""
    fit = remove_form(z, pixel_size_um=pixel_size_um, form="plane", region=region)
    form = fit.form_um
    rows, cols = z.shape
    offset = float(form[0, 0])
    slope_x = float((form[0, -1] - form[0, 0]) / ((cols - 1) * pixel_size_um)) if cols > 1 else 0.0
    slope_y = float((form[-1, 0] - form[0, 0]) / ((rows - 1) * pixel_size_um)) if rows > 1 else 0.0
    return offset, slope_x, slope_y


def _substrate(z: np.ndarray, measured: np.ndarray, pixel_size_um: float) -> np.ndarray:
    """The measured points of the lowest extensive level: start from the lowest fifth, fit a
    plane, keep every point within _SUBSTRATE_SIGMAS robust sigmas of it (the substrate's own
    roughness and tilt), and refit."""
    if measured.sum() < 3:
        return measured
    region = measured & (z <= np.quantile(z[measured], _SUBSTRATE_START_QUANTILE))
    rows, cols = np.indices(z.shape)
    for _ in range(_SUBSTRATE_ROUNDS):
        offset, slope_x, slope_y = _plane(z, region, pixel_size_um)
        residual = z - (offset + slope_x * cols * pixel_size_um + slope_y * rows * pixel_size_um)
        inside = residual[region]
        scale = 1.4826 * np.median(np.abs(inside - np.median(inside)))
        grown = measured & (np.abs(residual) <= _SUBSTRATE_SIGMAS * max(scale, 1e-6))
        if grown.sum() < 3 or np.array_equal(grown, region):
            break
        region = grown
    return region


def _relief(z: np.ndarray, measured: np.ndarray) -> float:
    """1st to 99th percentile of the measured heights, µm."""
    low, high = np.percentile(z[measured], [1, 99])
    return float(high - low)


def _background(z, measured, sigma_um) -> tuple[np.ndarray | None, int]:
    """The measured points the background plane rests on (None where there is none) and the number
    of blocks they lie in: the plane through the blocks' low levels (see BACKGROUND_BLOCKS),
    dropping the highest block above it by more than the tolerance until none is; then only the
    blocks mostly measured on it (a flank's lowest points are no level, nor are the few heights of
    a barely measured background) carry it, and it must lie under the whole surface."""
    rows, cols = np.indices(z.shape)
    block = (rows * BACKGROUND_BLOCKS // z.shape[0]) * BACKGROUND_BLOCKS + cols * BACKGROUND_BLOCKS // z.shape[1]
    lows = _block_lows(z, measured, block)
    if len(lows) < BACKGROUND_MIN_BLOCKS:
        return None, 0
    tolerance = _background_tolerance_um(z, measured, sigma_um)
    kept = np.ones(len(lows), bool)
    while kept.sum() >= BACKGROUND_MIN_BLOCKS:
        plane = _plane_through(lows[kept])
        residual = lows[:, 3] - (plane[0] + plane[1] * lows[:, 1] + plane[2] * lows[:, 2])
        above = kept & (residual > tolerance)
        if not above.any():
            break
        kept[np.argmax(np.where(above, residual, -np.inf))] = False  # the highest first: features stand above
    if kept.sum() < BACKGROUND_MIN_BLOCKS:
        return None, 0
    distance = np.abs(np.where(measured, z, np.inf) - (plane[0] + plane[1] * cols + plane[2] * rows))
    on_plane = measured & (distance <= tolerance)
    # A block is level where most of its area is measured on the plane: the few heights a barely
    # measured background gives (a ring biased by a grain's edge) carry no plane.
    share = np.bincount(block[on_plane], minlength=BACKGROUND_BLOCKS**2) / np.bincount(block.ravel())
    level = kept & (share[lows[:, 0].astype(int)] >= BACKGROUND_LEVEL_SHARE)
    spread = np.ptp(lows[level, 1:3], axis=0) if level.any() else np.zeros(2)
    if level.sum() < BACKGROUND_MIN_BLOCKS or np.any(spread < 0.5 * np.array([z.shape[1], z.shape[0]])):
        return None, 0
    below = (z - (plane[0] + plane[1] * cols + plane[2] * rows))[measured] < -tolerance
    if below.mean() > BACKGROUND_MAX_BELOW:
        return None, 0
    return on_plane & np.isin(block, lows[level, 0].astype(int)), int(level.sum())


def _background_tolerance_um(z: np.ndarray, measured: np.ndarray, sigma_um) -> float:
    """How far a point may lie from the background plane and be on it, µm: MAX_RESIDUAL_SIGMAS
    times the measured heights' median sigma (a background is flat within its noise; the
    relief's share, which a substrate may also meet, would let a ring of heights biased by a
    grain's edge pass for one), or that share where the sigma is not known."""
    sigma = np.asarray(sigma_um, np.float64)[measured] if sigma_um is not None else np.full(1, np.nan)
    if np.isfinite(sigma).any():
        return MAX_RESIDUAL_SIGMAS * float(np.nanmedian(sigma))
    return MAX_RELIEF_SHARE * _relief(z, measured)


def _plane_through(lows: np.ndarray) -> np.ndarray:
    """(offset, slope per column, slope per row) of the least-squares plane through the blocks'
    low levels (K, 4) (block, col, row, height)."""
    design = np.column_stack([np.ones(len(lows)), lows[:, 1], lows[:, 2]])
    return np.linalg.lstsq(design, lows[:, 3], rcond=None)[0]


def _block_lows(z: np.ndarray, measured: np.ndarray, block: np.ndarray) -> np.ndarray:
    """(K, 4) (block, col, row, low height) of the blocks (`block`: each point's block number) with
    enough measured points: the centroid and median height of each block's lowest fifth (pixels,
    µm)."""
    lows = []
    rows, cols = np.nonzero(measured)
    labels, heights = block[rows, cols], z[rows, cols]
    for label in np.unique(labels):
        inside = labels == label
        if inside.sum() < BACKGROUND_MIN_POINTS:
            continue
        lowest = inside & (heights <= np.quantile(heights[inside], _SUBSTRATE_START_QUANTILE))
        lows.append((label, cols[lowest].mean(), rows[lowest].mean(), np.median(heights[lowest])))
    return np.array(lows, np.float64).reshape(-1, 4)

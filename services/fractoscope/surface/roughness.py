"""Roughness of a height map as the product measures it: the surface texture chain of ISO 25178-3
run end to end, and reported with the settings it ran with.

1. Form removal (`form_removal`, robust least squares; optionally levelled on a region).
2. S- and L-filters (`iso_filters`, ISO 16610-61 Gaussians): the S-F surface, and the S-L surface
   when an L-filter is given.
3. Every ISO 25178-2 areal parameter of that surface (`areal_parameters`).
4. The Hurst exponent by the height-height correlation and by the profile PSD, along and across a
   direction (`scaling`), of the S-F surface (an L-filter would remove exactly the scales it is
   fitted over), over lags from `min_windows` matching windows to a tenth of the field; and the
   radially averaged areal PSD.
5. Each parameter's uncertainty from the matching noise (a per-pixel sigma map, correlated over
   the matching window) and the relative tilt uncertainty, and the bias noise adds to Sa and Sq
   (`uncertainty`).

The API, the command line, the HTTP endpoint and the viewer all call `analyse`. Heights are
(rows, cols) float arrays in µm on a square grid, NaN unknown.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import math
import threading
import time
from dataclasses import dataclass, field

import numba
import numpy as np

from fractoscope.errors import InvalidInputError
from fractoscope.progress import carried, checkpoint
from fractoscope.surface import areal_parameters, form_removal, iso_filters, measurement, scaling, uncertainty

FORMS = ("none", *form_removal.FORMS)
HURST_METHODS = ("hhc", "psd")
HURST_SIDES = ("along", "across")
FALLBACK_MIN_WINDOWS = 2.0  # the "about two matching windows", when the field is too small for more
STEP_THREADS = 2  # the independent steps after the filters run on this many threads


@dataclass(frozen=True)
class SurfaceChain:
    """The chain's operators and settings.

    form: one of FORMS ("none": heights as they are, about their mean).
    lambda_s_um, lambda_c_um: S- and L-filter cut-offs, µm; 0 = that filter is not applied.
    direction_deg: direction of the "along" Hurst exponents, degrees counter-clockwise from the
        column axis (+x) with y up the map; "across" is 90° more.
    window_px: the smoothing width of the matcher that made the map, in its pixels (1: none, as from
        a profilometer); it also correlates the matching noise.
    min_windows: the Hurst fit range starts this many windows up (scaling.TRUSTWORTHY_WINDOWS).
    levelled_on_region: whether the form was fitted on a region only.
    robust_form: whether the form was fitted robustly (form_removal's IRLS) instead of by least
        squares, ISO 25178-3's F-operator.
    """

    form: str = "plane"
    lambda_s_um: float = 0.0
    lambda_c_um: float = 0.0
    direction_deg: float = 0.0
    window_px: float = 1.0
    min_windows: float = scaling.TRUSTWORTHY_WINDOWS
    levelled_on_region: bool = False
    robust_form: bool = False


def surface_chain(
    *,
    form: str = "plane",
    lambda_s_um: float = 0.0,
    lambda_c_um: float = 0.0,
    direction_deg: float = 0.0,
    window_px: float = 1.0,
    min_windows: float = scaling.TRUSTWORTHY_WINDOWS,
    levelled_on_region: bool = False,
    robust_form: bool = False,
) -> SurfaceChain:
    """A SurfaceChain, checked: InvalidInputError names the API's field (form, s_filter_um,
    l_filter_um, direction_deg, window_px, min_windows)."""
    if form not in FORMS:
        raise InvalidInputError("form", f"must be one of {', '.join(FORMS)}, not {form!r}")
    for name, value in (("s_filter_um", lambda_s_um), ("l_filter_um", lambda_c_um)):
        if not (math.isfinite(value) and value >= 0):
            raise InvalidInputError(name, f"must be a cut-off in µm >= 0 (0: no filter), got {value}")
    if lambda_s_um and lambda_c_um and not lambda_s_um < lambda_c_um:
        raise InvalidInputError("s_filter_um", f"must be below l_filter_um ({lambda_c_um} µm), got {lambda_s_um}")
    if not math.isfinite(direction_deg):
        raise InvalidInputError("direction_deg", f"must be finite, got {direction_deg}")
    if not (math.isfinite(window_px) and 1 <= window_px <= 1000):
        raise InvalidInputError("window_px", f"must be 1 to 1000 pixels, got {window_px}")
    if not (math.isfinite(min_windows) and 0.5 <= min_windows <= 100):
        raise InvalidInputError("min_windows", f"must be 0.5 to 100, got {min_windows}")
    return SurfaceChain(
        form=form,
        lambda_s_um=float(lambda_s_um),
        lambda_c_um=float(lambda_c_um),
        direction_deg=float(direction_deg) % 360.0,
        window_px=float(window_px),
        min_windows=float(min_windows),
        levelled_on_region=levelled_on_region,
        robust_form=bool(robust_form),
    )


@dataclass(frozen=True)
class HurstResult:
    """The Hurst fits: ``fits[method][side]`` (methods "hhc", "psd"; sides "along", "across"; each
    fit says itself why it does not determine H), and the windows the fit range started at
    (``min_windows`` of the chain, or FALLBACK_MIN_WINDOWS on a field too small for it, which the
    ``note`` says). Empty fits with a ``note`` when even that does not fit."""

    fits: dict[str, dict[str, scaling.ScalingFit]]
    min_windows: float
    note: str = ""


@dataclass(frozen=True)
class SurfaceAnalysis:
    """What `analyse` found, and how.

    chain: the settings used; pixel_size_um: of the analysed map, µm.
    parameters: areal_parameters' values by ISO name (units in areal_parameters.UNITS).
    uncertainty: their standard uncertainties, noise bias of Sa and Sq (None without a sigma map).
    tilt_rel_uncertainty: the relative tilt uncertainty propagated (None: not known).
    hurst: the Hurst fits.
    psd_q_per_um, psd_um4: the radially averaged areal PSD of the S-F surface (cycles/µm, µm⁴).
    form_parameters: the fitted form's geometry (form_removal.FormFit.parameters).
    coverage: what share of the map was measured, filled (and left out) or unknown (None: not
        told, a map analysed as it is).
    """

    chain: SurfaceChain
    pixel_size_um: float
    parameters: dict[str, float]
    uncertainty: uncertainty.ArealUncertainty | None
    tilt_rel_uncertainty: float | None
    hurst: HurstResult
    psd_q_per_um: np.ndarray
    psd_um4: np.ndarray
    form_parameters: dict = field(default_factory=dict)
    coverage: measurement.Coverage | None = None

    @property
    def caveats(self) -> list[str]:
        """One line per parameter family that does not suit this surface (`parameter_caveats`)."""
        return parameter_caveats(self.parameters, self.coverage)

    def legacy(self) -> dict:
        """The keys Fractoscope reported before the chain: Sa ... Sdr, and the Hurst exponent by
        h(r) along the direction with its fit range (µm), fractal dimension 3 - H and curve (NaN
        and empty without a fit; H and 3 - H NaN where the fit does not determine H, the note says
        why)."""
        values = {name: self.parameters[name] for name in ("Sa", "Sq", "Ssk", "Sku", "Sp", "Sv", "Sz", "Sdq", "Sdr")}
        fit = self.hurst.fits.get("hhc", {}).get("along")
        if fit is None:
            nan = float("nan")
            return values | {
                "hurst_exponent": nan,
                "hurst_fit_min_um": nan,
                "hurst_fit_max_um": nan,
                "fractal_dimension": nan,
                "hhc_lag_um": [],
                "hhc_rms_um": [],
            }
        hurst = float("nan") if fit.not_determinable else fit.hurst
        return values | {
            "hurst_exponent": hurst,
            "hurst_fit_min_um": fit.fit_min_um,
            "hurst_fit_max_um": fit.fit_max_um,
            "fractal_dimension": 3.0 - hurst,
            "hhc_lag_um": fit.scale_um.tolist(),
            "hhc_rms_um": fit.value.tolist(),
        }


# Unknown points beyond this share leave Spd and Spc counting a fraction of the hills.
_FEATURE_UNKNOWN_SHARE = 0.05


def parameter_caveats(parameters: dict[str, float], coverage: measurement.Coverage | None) -> list[str]:
    """Why some parameters do not describe a surface, one line each: the Sk family where the areal
    material ratio curve has no straight core (Spk beyond Sp, Svk beyond Sv, or Sk + Spk + Svk
    beyond Sz: heights of two levels, a grain on a substrate), Spd and Spc where unknown points leave hills
    uncounted (ISO 25178-2 counts only complete hills)."""
    lines = []
    sz, sp, sv, sk, spk, svk = (parameters.get(name, math.nan) for name in ("Sz", "Sp", "Sv", "Sk", "Spk", "Svk"))
    beyond = [
        f"{name} = {value:.3g} µm exceeds {limit_name} = {limit:.3g} µm"
        for name, value, limit_name, limit in (
            ("Spk", spk, "Sp", sp),
            ("Svk", svk, "Sv", sv),
            ("Sk + Spk + Svk", sk + spk + svk, "Sz", sz),
        )
        if value > limit > 0
    ]
    if beyond:
        lines.append(
            f"Sk, Spk, Svk, Smr1, Smr2 do not describe this surface: {'; '.join(beyond)}, so the material ratio "
            "curve has no straight core (heights of two levels, such as a grain on a substrate)"
        )
    unknown = coverage.unknown + coverage.filled if coverage is not None else 0.0
    if unknown > _FEATURE_UNKNOWN_SHARE:
        lines.append(
            f"Spd and Spc count only the hills that touch no unmeasured point ({100 * unknown:.0f} % of the area is "
            "unmeasured or filled): they describe the measured part"
        )
    return lines


def analyse(
    z_um: np.ndarray,
    *,
    pixel_size_um: float,
    chain: SurfaceChain = SurfaceChain(),
    levelling_region: np.ndarray | None = None,
    sigma_um: np.ndarray | float | None = None,
    tilt_rel_uncertainty: float | None = None,
    features: bool = True,
    timings: dict[str, float] | None = None,
) -> SurfaceAnalysis:
    """Run the chain on a (rows, cols) µm height map. ``levelling_region``: (rows, cols) bool, where
    the form is fitted; ``sigma_um``: the matching noise's one-sigma per pixel (µm, a map or one
    value; without it no uncertainty is computed); ``tilt_rel_uncertainty``: the relative
    uncertainty of the tilt difference (0.01 for 1 %; None: unknown, propagated as 0);
    ``features=False`` leaves out Spd and Spc (NaN); ``timings``, if given, receives each step's
    wall-clock seconds (STEPS; the steps after the filters run two at a time, so theirs overlap).
    Raises InvalidInputError naming what is wrong."""
    z = _checked_heights(z_um)
    if chain.levelled_on_region != (levelling_region is not None):
        chain = SurfaceChain(**{**chain.__dict__, "levelled_on_region": levelling_region is not None})
    step = _Stopwatch(timings)
    surface, form_parameters = _scale_limited(z, pixel_size_um, chain, levelling_region, step)
    # The steps below are independent but for the uncertainty, which needs the parameters: two
    # threads run them, each its compiled loops on one thread. The parameters are submitted first
    # (the longest first) and the areal PSD after the uncertainty, so that the two threads finish
    # about together.
    with _step_threads() as pool:
        futures = _submit_parameters(pool, step, surface, pixel_size_um, chain, features)
        parameters = {}
        for name in ("height and hybrid parameters", "spatial parameters", "functional parameters"):
            parameters |= futures[name].result()
        parameters |= futures["feature parameters"].result()
        parameters = {name: parameters[name] for name in areal_parameters.UNITS}
        uncertain = pool.submit(
            carried(step.timed),
            "uncertainty",
            lambda: _uncertainty(surface.z_um, sigma_um, pixel_size_um, parameters, tilt_rel_uncertainty, chain),
        )
        psd = pool.submit(
            carried(step.timed), "areal PSD", lambda: scaling.radial_psd(surface.sf_um, pixel_size_um=pixel_size_um)
        )
        hurst = futures["Hurst exponents"].result()
        q, c = psd.result()
        try:
            u = uncertain.result()
        except ValueError as error:
            raise InvalidInputError("sigma_um", str(error)) from None
    return SurfaceAnalysis(
        chain=chain,
        pixel_size_um=float(pixel_size_um),
        parameters=parameters,
        uncertainty=u,
        tilt_rel_uncertainty=tilt_rel_uncertainty,
        hurst=hurst,
        psd_q_per_um=q,
        psd_um4=c,
        form_parameters=form_parameters,
    )


def _uncertainty(sl_um, sigma_um, pixel_size_um: float, parameters: dict, tilt_rel_uncertainty, chain: SurfaceChain):
    """The parameters' uncertainty (uncertainty.areal_uncertainty) on the S-L surface, None
    without a matching sigma."""
    if sigma_um is None:
        return None
    return uncertainty.areal_uncertainty(
        sl_um,
        sigma_um,
        pixel_size_um=pixel_size_um,
        parameters={k: v for k, v in parameters.items() if np.isfinite(v)},
        tilt_rel_uncertainty=tilt_rel_uncertainty or 0.0,
        correlation_px=chain.window_px,
    )


def _checked_heights(z_um: np.ndarray) -> np.ndarray:
    """The heights as float64, or InvalidInputError naming `region` when too few or too scattered
    to analyse: slopes, spectra and correlations need neighbours, which scattered points lack."""
    z = np.asarray(z_um, dtype=np.float64)
    if z.ndim != 2 or min(z.shape) < 16:
        raise InvalidInputError("region", f"needs at least 16 x 16 points, got {z.shape[-1]} x {z.shape[0]}")
    known = np.isfinite(z)
    if np.count_nonzero(known) < 64:
        raise InvalidInputError("region", "holds fewer than 64 measured points")
    neighbours = (np.count_nonzero(known[:, 1:] & known[:, :-1]), np.count_nonzero(known[1:] & known[:-1]))
    if min(neighbours) < 64:
        raise InvalidInputError(
            "region",
            f"its measured points are scattered: {neighbours[0]} pairs of neighbours along x, {neighbours[1]} along "
            "y, fewer than 64",
        )
    return z


def _scale_limited(z: np.ndarray, pixel_size_um: float, chain: SurfaceChain, levelling_region, step):
    """The form removed and the S- and L-filters applied: (iso_filters' surface, the form's
    parameters); InvalidInputError names the chain's setting at fault."""
    with step("form removal"):
        if chain.form == "none":
            residual, form_parameters = z, {}
        else:
            try:
                fit = form_removal.remove_form(
                    z, pixel_size_um=pixel_size_um, form=chain.form, region=levelling_region, robust=chain.robust_form
                )
            except ValueError as error:
                raise InvalidInputError(
                    "levelling_region" if levelling_region is not None else "form", str(error)
                ) from None
            residual, form_parameters = fit.residual_um, fit.parameters
    with step("S- and L-filters"):
        try:
            surface = iso_filters.scale_limited_surface(
                residual,
                pixel_size_um=pixel_size_um,
                lambda_s_um=chain.lambda_s_um or None,
                lambda_c_um=chain.lambda_c_um or None,
            )
        except ValueError as error:
            raise InvalidInputError(
                "s_filter_um" if str(error).startswith("lambda_s") else "l_filter_um", str(error)
            ) from None
    return surface, form_parameters


def _submit_parameters(pool, step, surface, pixel_size_um: float, chain: SurfaceChain, features: bool) -> dict:
    """The parameter families and the Hurst fits submitted to `pool`, the longest first: their
    futures by step name."""
    sl = surface.z_um
    max_lag_px = None
    if chain.lambda_c_um:  # past lambda_c the S-L surface holds no correlation to resolve
        max_lag_px = max(1, min(min(sl.shape) // 2, int(np.ceil(chain.lambda_c_um / pixel_size_um))))
    nan = float("nan")
    pending = {
        "feature parameters": (lambda: areal_parameters.feature_parameters(sl, pixel_size_um=pixel_size_um))
        if features
        else (lambda: {"Spd": nan, "Spc": nan}),
        "spatial parameters": lambda: areal_parameters.spatial_parameters(
            sl, pixel_size_um=pixel_size_um, max_lag_px=max_lag_px
        ),
        "height and hybrid parameters": lambda: (
            areal_parameters.height_parameters(sl) | areal_parameters.hybrid_parameters(sl, pixel_size_um=pixel_size_um)
        ),
        "functional parameters": lambda: areal_parameters.functional_parameters(sl),
        "Hurst exponents": lambda: _hurst(surface.sf_um, pixel_size_um, chain),
    }
    return {name: pool.submit(carried(step.timed), name, task) for name, task in pending.items()}


STEPS = (
    "form removal",
    "S- and L-filters",
    "height and hybrid parameters",
    "spatial parameters",
    "functional parameters",
    "feature parameters",
    "Hurst exponents",
    "areal PSD",
    "uncertainty",
)


class _Stopwatch:
    """``with step(name):`` adds the block's wall-clock seconds to timings[name] (nothing without);
    ``step.timed(name, task)`` does so for ``task()`` and returns its value."""

    def __init__(self, timings: dict[str, float] | None):
        self.timings = timings
        self._lock = threading.Lock()

    @contextlib.contextmanager
    def __call__(self, name: str):
        checkpoint()  # between steps: a caller gone stops the chain
        started = time.perf_counter()
        try:
            yield
        finally:
            if self.timings is not None:
                with self._lock:
                    self.timings[name] = self.timings.get(name, 0.0) + time.perf_counter() - started

    def timed(self, name: str, task):
        with self(name):
            return task()


@contextlib.contextmanager
def _step_threads():
    """Two threads whose compiled loops (numba) run on one thread each: two steps at a time use
    the two cores without oversubscribing them."""
    pool = concurrent.futures.ThreadPoolExecutor(STEP_THREADS, initializer=numba.set_num_threads, initargs=(1,))
    try:
        yield pool
    finally:
        pool.shutdown(cancel_futures=True)  # after an error, the steps not yet started are not run


def _hurst(sf_um: np.ndarray, pixel_size_um: float, chain: SurfaceChain) -> HurstResult:
    """Both methods along and across the direction, from min_windows windows up, or from two on a
    field too small for that (said in the note), or none."""
    tried = [chain.min_windows] + ([FALLBACK_MIN_WINDOWS] if chain.min_windows > FALLBACK_MIN_WINDOWS else [])
    for min_windows in tried:
        try:
            fit_range = scaling.trustworthy_range_um(
                sf_um.shape, pixel_size_um=pixel_size_um, window_px=chain.window_px, min_windows=min_windows
            )
            sides = {
                side: scaling.hurst_exponents(
                    sf_um,
                    pixel_size_um=pixel_size_um,
                    window_px=chain.window_px,
                    methods=HURST_METHODS,
                    direction_deg=chain.direction_deg + (90.0 if side == "across" else 0.0),
                    fit_range_um=fit_range,
                )
                for side in HURST_SIDES
            }
            fits = {method: {side: sides[side][method] for side in HURST_SIDES} for method in HURST_METHODS}
        except ValueError as error:
            note = f"no Hurst exponent: {error}"
            continue
        if min_windows != chain.min_windows:
            note = (
                f"the field ({min(sf_um.shape)} px) is too small for a fit from {chain.min_windows:g} windows of "
                f"{chain.window_px:g} px: fitted from {min_windows:g}, where a matcher's smoothing can raise H by up "
                "to 0.07"
            )
        else:
            note = ""
        return HurstResult(fits, min_windows, note)
    return HurstResult({}, chain.min_windows, note)


def height_parameters_after_plane(z_um: np.ndarray) -> dict[str, float]:
    """Sa, Sq, Ssk, Sku, Sp, Sv, Sz (µm where dimensional) after removing the least-squares plane
    (by plain least squares over every known point: what comparisons of a measured map with its
    truth use)."""
    z = np.asarray(z_um)
    residual = form_removal.remove_form(
        z, pixel_size_um=1.0, form="plane", robust=False, max_fit_points=max(z.size, 16)
    ).residual_um
    return areal_parameters.height_parameters(residual)

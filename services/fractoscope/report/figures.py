"""The report's matplotlib figures (no display needed): the SEM images, the height map with a
colour bar and a scale bar, the coverage and uncertainty maps, the height-height correlation with
its fit, the PSDs with theirs, and the profiles. Axes are micrometres in the specimen frame (x right, y down)."""

from __future__ import annotations

import math

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.colors import BoundaryNorm, LightSource, ListedColormap, Normalize
from matplotlib.figure import Figure
from matplotlib.ticker import LogFormatter
from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

from fractoscope.report.content import ReportContent, ReportProfile, View
from fractoscope.specimen.queries import SurfaceArea

WIDTH_IN = 7.2  # fits an A4 page's margins and an HTML column
_UNKNOWN_GREY = (0.55, 0.55, 0.55, 1.0)
_FILLED = (0.88, 0.84, 0.72, 1.0)  # interpolated heights: a pale sand, apart from every ROI's colour


def views_figure(views: list[View]) -> Figure:
    """The SEM images side by side, two a row, each titled with its ROI, file and tilt."""
    columns = 2 if len(views) > 1 else 1
    rows = math.ceil(len(views) / columns)
    figure, axes = plt.subplots(rows, columns, figsize=(WIDTH_IN, 3.4 * rows), layout="constrained", squeeze=False)
    for ax in axes.ravel():
        ax.set_axis_off()
    for ax, view in zip(axes.ravel(), views):
        ax.imshow(view.pixels, cmap="gray", vmin=0, vmax=255, interpolation="antialiased")
        tilt = f", tilt {view.tilt_deg:+.3g}°" if math.isfinite(view.tilt_deg) else ""
        # The file's name is the user's text, never mathtext: `$\frac{1}{$` would fail every report.
        ax.set_title(f"ROI {view.roi}, view {view.index} ({view.name}){tilt}", fontsize=8, parse_math=False)
    return figure


def height_map_axes(figure: Figure, ax, z_um: np.ndarray, *, pixel_size_um: float, origin_um=(0.0, 0.0)) -> None:
    """Heights as a colour map shaded by a hillshade, unknown points grey, with a colour bar in µm,
    a scale bar, and axes in µm."""
    z = np.ma.masked_invalid(z_um)
    low, high = np.nanpercentile(z_um, [0.5, 99.5]) if z.count() else (0.0, 1.0)
    norm = Normalize(low, high if high > low else low + 1e-6)
    shaded = LightSource(azdeg=315, altdeg=45).shade(
        z.filled(np.nanmedian(z_um) if z.count() else 0.0),
        cmap=plt.get_cmap("viridis"),
        norm=norm,
        blend_mode="soft",
        vert_exag=1.0 / pixel_size_um,
        dx=1,
        dy=1,
    )
    shaded[np.ma.getmaskarray(z)] = _UNKNOWN_GREY
    ax.imshow(shaded, extent=_extent(z_um.shape, pixel_size_um, origin_um), interpolation="antialiased")
    _micrometre_axes(ax)
    _scale_bar(ax, z_um.shape[1] * pixel_size_um)
    bar = figure.colorbar(plt.cm.ScalarMappable(norm=norm, cmap="viridis"), ax=ax, shrink=0.85)
    bar.set_label("height (µm)")


def height_figure(area: SurfaceArea) -> Figure:
    figure, ax = plt.subplots(figsize=(WIDTH_IN, 5.6), layout="constrained")
    height_map_axes(figure, ax, area.z_um, pixel_size_um=area.pixel_size_um, origin_um=area.origin_um)
    ax.set_title("Height map (plane not removed; grey: unknown)", fontsize=9)
    return figure


def maps_figure(area: SurfaceArea) -> Figure:
    """Coverage (which ROI each matched point comes from, the filled points apart, grey where
    unknown) and the one-sigma matching noise of the heights."""
    figure, (coverage_ax, sigma_ax) = plt.subplots(1, 2, figsize=(WIDTH_IN, 3.4), layout="constrained")
    extent = _extent(area.z_um.shape, area.pixel_size_um, area.origin_um)
    shown = sorted(set(np.unique(area.source[~area.filled]).tolist()) - {-1})
    palette = [_UNKNOWN_GREY, _FILLED] + [plt.get_cmap("tab10")(i % 10) for i in range(len(shown))]
    codes = np.zeros(area.source.shape, np.int16)
    codes[area.filled & np.isfinite(area.z_um)] = 1
    for position, index in enumerate(shown, start=2):
        codes[(area.source == index) & ~area.filled] = position
    norm = BoundaryNorm(np.arange(len(palette) + 1) - 0.5, len(palette))
    coverage_ax.imshow(codes, cmap=ListedColormap(palette), norm=norm, extent=extent, interpolation="nearest")
    covered = area.coverage
    coverage_ax.set_title(
        f"Coverage: {100 * covered.measured:.1f} % matched, {100 * covered.filled:.1f} % filled", fontsize=9
    )
    bar = figure.colorbar(
        plt.cm.ScalarMappable(norm=norm, cmap=ListedColormap(palette)),
        ax=coverage_ax,
        shrink=0.85,
        ticks=range(len(palette)),
    )
    bar.ax.set_yticklabels(["unknown", "filled"] + [f"ROI {area.sources[index]}" for index in shown], fontsize=7)
    sigma = np.ma.masked_invalid(area.sigma_um)
    if sigma.count():
        image = sigma_ax.imshow(
            sigma,
            cmap="magma",
            extent=extent,
            interpolation="antialiased",
            vmin=float(np.nanpercentile(area.sigma_um, 0.5)),
            vmax=float(np.nanpercentile(area.sigma_um, 99.5)),
        )
        figure.colorbar(image, ax=sigma_ax, shrink=0.85).set_label("σ, matching part (µm)")
        sigma_ax.set_title("Height uncertainty: matching part (one sigma)", fontsize=9)
    else:
        sigma_ax.set_title("Height uncertainty: not stored", fontsize=9)
    for ax in (coverage_ax, sigma_ax):
        _micrometre_axes(ax)
        _scale_bar(ax, area.z_um.shape[1] * area.pixel_size_um)
    return figure


def hurst_figure(content: ReportContent) -> Figure:
    """The height-height correlation h(r), its power-law fit over the fit range, and the range
    the scaling analysis trusts."""
    values = content.roughness.legacy()
    lags, rms = np.asarray(values["hhc_lag_um"]), np.asarray(values["hhc_rms_um"])
    figure, ax = plt.subplots(figsize=(WIDTH_IN, 3.6), layout="constrained")
    ax.loglog(lags, rms, "o", markersize=3, color="0.3", label="h(r)")
    low, high, hurst = values["hurst_fit_min_um"], values["hurst_fit_max_um"], values["hurst_exponent"]
    fitted = (lags >= low) & (lags <= high) & (rms > 0)
    if fitted.sum() >= 2 and math.isfinite(hurst):
        prefactor = np.exp(np.mean(np.log(rms[fitted]) - hurst * np.log(lags[fitted])))
        span = np.array([low, high])
        ax.loglog(
            span,
            prefactor * span**hurst,
            "-",
            color="C3",
            label=f"fit: H = {hurst:.3f} over {low:.3g} to {high:.3g} µm",
        )
    if content.trustworthy_range_um is not None:
        ax.axvspan(*content.trustworthy_range_um, color="C2", alpha=0.15, label="trustworthy lags (scaling)")
    along = content.roughness.hurst.fits.get("hhc", {}).get("along")
    if along is not None and along.not_determinable:
        ax.set_title(f"fit: H = {along.hurst:.3f} ± {along.hurst_stderr:.3f}, not determinable (see below)", fontsize=8)
    ax.set_xlabel("lag r (µm)")
    ax.set_ylabel("h(r) (µm)")
    for axis in (ax.xaxis, ax.yaxis):  # plain numbers ("8", not "8 × 10⁰"): a fit range often spans less than a decade
        axis.set_major_formatter(LogFormatter())
        axis.set_minor_formatter(LogFormatter(labelOnlyBase=False))
    ax.legend(fontsize=7)
    ax.grid(True, which="both", alpha=0.3)
    return figure


def psd_figure(content: ReportContent) -> Figure:
    """Left: the radially averaged areal PSD C(q) of the S-F surface. Right: the profile PSDs along
    and across the direction, the PSD Hurst fits drawn over the wavelengths they were fitted on."""
    analysis = content.roughness
    figure, (areal_ax, profile_ax) = plt.subplots(1, 2, figsize=(WIDTH_IN, 3.4), layout="constrained")
    shown = np.isfinite(analysis.psd_um4) & (analysis.psd_um4 > 0)
    areal_ax.loglog(
        analysis.psd_q_per_um[shown], analysis.psd_um4[shown], "-", color="0.3", linewidth=1.0, label="C(q)"
    )
    areal_ax.set_xlabel("spatial frequency q (1/µm)")
    areal_ax.set_ylabel("C(q) (µm⁴)")
    areal_ax.set_title("Areal PSD (radially averaged)", fontsize=9)
    for side, fit in analysis.hurst.fits.get("psd", {}).items():
        k = 1.0 / fit.scale_um
        (line,) = profile_ax.loglog(k, fit.value, ".", markersize=2, label=f"{side} ({fit.direction_deg:g}°)")
        band = np.array([1.0 / fit.fit_max_um, 1.0 / fit.fit_min_um])
        profile_ax.loglog(
            band,
            fit.prefactor * band ** -(1.0 + 2.0 * fit.hurst),
            "-",
            color=line.get_color(),
            linewidth=1.5,
            label=f"fit: H = {fit.hurst:.3f} ± {fit.hurst_stderr:.2g}"
            + (" (not determinable)" if fit.not_determinable else ""),
        )
        if side == "along":
            areal_ax.axvspan(*band, color="C2", alpha=0.15, label="fitted frequencies")
    profile_ax.set_xlabel("spatial frequency k (1/µm)")
    profile_ax.set_ylabel("P(k) (µm³)")
    profile_ax.set_title("Profile PSD and its fits", fontsize=9)
    if not analysis.hurst.fits:
        profile_ax.text(
            0.5,
            0.5,
            "no PSD fit: the field is too small",
            ha="center",
            va="center",
            transform=profile_ax.transAxes,
            fontsize=8,
        )
    for ax in (areal_ax, profile_ax):
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=6)
        ax.grid(True, which="both", alpha=0.3)
        ax.tick_params(labelsize=7)
    return figure


def profile_figure(profile: ReportProfile) -> Figure:
    """A profile's primary heights (as the API samples them, by source ROI) and its roughness
    profile after the ISO 21920-3 chain."""
    found = profile.found
    figure, ax = plt.subplots(figsize=(WIDTH_IN, 2.8), layout="constrained")
    sources = np.asarray(found.source_index)
    for index in sorted(set(sources.tolist()) - {-1}):  # -1: no ROI, no data: no series and no legend entry
        shown = np.where(sources == index, found.z_um, np.nan)
        if np.isfinite(shown).any():
            label = f"primary, ROI {found.sources[index]}"
            ax.plot(found.distance_um, shown - np.nanmean(found.z_um), linewidth=0.9, label=label)
    if profile.roughness_um is not None and np.isfinite(profile.roughness_um).any():
        ax.plot(
            found.distance_um,
            profile.roughness_um,
            linewidth=0.7,
            color="C3",
            label=f"roughness (λs {profile.lambda_s_um:.3g} µm, λc {profile.lambda_c_um:.3g} µm)",
        )
    ax.set_xlabel("distance (µm)")
    ax.set_ylabel("height (µm)")
    ax.set_title(f"{profile.name.capitalize()} profile", fontsize=9)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=7)
    ax.grid(True, alpha=0.3)
    return figure


def _extent(shape, pixel_size_um: float, origin_um) -> tuple[float, float, float, float]:
    """imshow extent of a (rows, cols) grid whose pixel centres start at `origin_um`, y down."""
    rows, cols = shape
    x0, y0 = origin_um[0] - pixel_size_um / 2, origin_um[1] - pixel_size_um / 2
    return x0, x0 + cols * pixel_size_um, y0 + rows * pixel_size_um, y0


def _micrometre_axes(ax) -> None:
    ax.set_xlabel("x (µm)")
    ax.set_ylabel("y (µm)")
    ax.tick_params(labelsize=7)


def _scale_bar(ax, width_um: float) -> None:
    """A bar of a round length (1, 2 or 5 times a power of ten) about a fifth of the width."""
    target = width_um / 5
    power = 10 ** math.floor(math.log10(target))
    length = max(step * power for step in (1, 2, 5) if step * power <= target)
    label = f"{length:g} µm" if length >= 1 else f"{length * 1000:g} nm"
    ax.add_artist(
        AnchoredSizeBar(
            ax.transData,
            length,
            label,
            "lower right",
            pad=0.4,
            color="white",
            frameon=False,
            size_vertical=width_um / 150,
            fontproperties={"size": 8},
        )
    )

"""ISO 25178-2 areal parameters on surfaces whose parameters are known analytically."""

from __future__ import annotations

import numpy as np
import pytest
from surface_truth import self_affine

from fractoscope.surface import areal_parameters

PIXEL_UM = 0.25


def _egg_crate(amplitude_um: float, wavelength_x_px: float, wavelength_y_px: float, shape=(512, 512)) -> np.ndarray:
    rows, cols = np.indices(shape)
    return amplitude_um * (np.sin(2 * np.pi * cols / wavelength_x_px) + np.sin(2 * np.pi * rows / wavelength_y_px))


def _egg_crate_decay_lengths_px(wavelength_x_px: float, wavelength_y_px: float, threshold: float) -> np.ndarray:
    """First lag at which the analytic f_ACF = (cos(2 pi tx / lx) + cos(2 pi ty / ly)) / 2 falls to
    the threshold, along every direction 0.05° apart (0.01 px steps, then linear interpolation)."""
    angles = np.radians(np.arange(0.0, 180.0, 0.05))[:, None]
    radius = np.arange(0.0, 48.0, 0.01)
    acf = 0.5 * (
        np.cos(2 * np.pi * radius * np.cos(angles) / wavelength_x_px)
        + np.cos(2 * np.pi * radius * np.sin(angles) / wavelength_y_px)
    )
    first = np.argmax(acf <= threshold, axis=1)
    rows = np.arange(len(first))
    before, after = acf[rows, first - 1], acf[rows, first]
    return radius[first - 1] + (before - threshold) / (before - after) * 0.01


def test_sine_grid_gives_its_sq_sal_and_str():
    z = _egg_crate(0.8, 32.0, 64.0)
    values = areal_parameters.areal_parameters(z, pixel_size_um=PIXEL_UM, features=False)
    assert values["Sq"] == pytest.approx(0.8, rel=1e-9)  # two independent unit sines: variance A²/2 each
    decay = _egg_crate_decay_lengths_px(32.0, 64.0, areal_parameters.ACF_THRESHOLD)
    assert values["Sal"] == pytest.approx(decay.min() * PIXEL_UM, rel=0.01)
    assert values["Str"] == pytest.approx(decay.min() / decay.max(), rel=0.01)
    # A square grid decays fastest along its diagonals: Str below 1 although it looks isotropic-ish.
    square = areal_parameters.spatial_parameters(_egg_crate(0.8, 32.0, 32.0), pixel_size_um=PIXEL_UM)
    decay = _egg_crate_decay_lengths_px(32.0, 32.0, areal_parameters.ACF_THRESHOLD)
    assert square["Str"] == pytest.approx(decay.min() / decay.max(), rel=0.01)


def test_single_sine_heights_and_undefined_str():
    rows, cols = np.indices((256, 512))
    z = 1.2 * np.sin(2 * np.pi * cols / 32.0)
    values = areal_parameters.areal_parameters(z, pixel_size_um=PIXEL_UM, features=False)
    samples = 1.2 * np.sin(2 * np.pi * np.arange(32) / 32.0)  # one sampled period (2 A / pi continuously)
    assert values["Sa"] == pytest.approx(np.mean(np.abs(samples)), rel=1e-9)
    assert values["Sq"] == pytest.approx(1.2 / np.sqrt(2), rel=1e-9)
    assert values["Ssk"] == pytest.approx(0.0, abs=1e-9)
    assert values["Sku"] == pytest.approx(1.5, rel=1e-9)
    assert values["Sz"] == pytest.approx(2.4, rel=1e-6)
    assert values["Sal"] == pytest.approx(32.0 * np.arccos(0.2) / (2 * np.pi) * PIXEL_UM, rel=0.01)
    # Along the crests f_ACF never decays: the slowest decay, and Str, are undetermined.
    assert np.isnan(values["Str"])


@pytest.mark.parametrize("direction_deg", [0.0, 17.0, 30.0, 90.0, 120.0, 163.5])
def test_std_is_the_direction_heights_vary_fastest(direction_deg):
    rows, cols = np.indices((256, 300))
    theta = np.radians(direction_deg)
    # y points up the map, to row 0.
    z = np.sin(2 * np.pi * (cols * np.cos(theta) - rows * np.sin(theta)) / 19.3)
    found = areal_parameters.texture_direction_deg(z)
    assert abs((found - direction_deg + 90.0) % 180.0 - 90.0) <= 0.5


def test_tilted_plane_gives_its_slope_and_developed_area():
    rows, cols = np.indices((64, 80))
    gx, gy = 0.3, -0.4
    z = (gx * cols - gy * rows) * PIXEL_UM
    values = areal_parameters.hybrid_parameters(z, pixel_size_um=PIXEL_UM)
    assert values["Sdq"] == pytest.approx(np.hypot(gx, gy), rel=1e-12)
    assert values["Sdr"] == pytest.approx((np.sqrt(1 + gx**2 + gy**2) - 1) * 100, rel=1e-12)


# A material ratio curve made of three straight pieces: peaks from 3 µm down to 1 µm over the top
# 10 %, a core from 1 down to -1 µm over the next 80 % and dales from -1 down to -4 µm. Every 40 %
# window inside the core has the same, smallest secant, and the equivalent line is the core itself.
_KNOTS_RATIO = [0.0, 10.0, 90.0, 100.0]
_KNOTS_HEIGHT = [3.0, 1.0, -1.0, -4.0]


def _piecewise_abbott_surface(shape=(512, 512)) -> np.ndarray:
    count = shape[0] * shape[1]
    ratio = (np.arange(count) + 0.5) * 100.0 / count
    heights = np.interp(ratio, _KNOTS_RATIO, _KNOTS_HEIGHT)
    return np.random.default_rng(0).permutation(heights).reshape(shape)


def _analytic_functional_parameters() -> dict[str, float]:
    core_slope = (-1.0 - 1.0) / 80.0
    upper = 1.0 - 10.0 * core_slope  # the core line at 0 %: 1.25
    lower = upper + 100.0 * core_slope  # and at 100 %: -1.25
    smr1 = (3.0 - upper) / 0.2  # where the peak piece z = 3 - 0.2 mr meets it
    smr2 = 90.0 + (-1.0 - lower) / 0.3  # where the dale piece z = -1 - 0.3 (mr - 90) does
    ratio = np.linspace(0.0, 100.0, 1_000_001)
    height = np.interp(ratio, _KNOTS_RATIO, _KNOTS_HEIGHT)
    mean = np.trapezoid(height, ratio) / 100.0  # parameters are about the mean height
    height, upper, lower = height - mean, upper - mean, lower - mean

    def material(p):
        return np.trapezoid(np.clip(height - np.interp(p, ratio, height), 0, None), ratio) / 100.0

    def void(p):
        return np.trapezoid(np.clip(np.interp(p, ratio, height) - height, 0, None), ratio) / 100.0

    return {
        "Sk": upper - lower,
        "Spk": 3.0 - mean - upper,  # each protruding piece is a straight line: its triangle's height
        "Svk": lower - (-4.0 - mean),
        "Smr1": smr1,
        "Smr2": smr2,
        "Vmp": material(10.0),
        "Vmc": material(80.0) - material(10.0),
        "Vvc": void(10.0) - void(80.0),
        "Vvv": void(80.0),
    }


def test_known_abbott_curve_gives_its_sk_family_and_volumes():
    values = areal_parameters.functional_parameters(_piecewise_abbott_surface())
    expected = _analytic_functional_parameters()
    assert expected["Sk"] == pytest.approx(2.5)
    for name, value in expected.items():
        assert values[name] == pytest.approx(value, rel=2e-3, abs=1e-4), name


def test_bumps_give_their_peak_density_and_curvature():
    spacing, sigma_px, height = 32, 5.0, 2.0
    rows, cols = np.indices((256, 256))
    z = np.zeros((256, 256))
    for r in range(spacing // 2, 256, spacing):
        for c in range(spacing // 2, 256, spacing):
            z += height * np.exp(-((rows - r) ** 2 + (cols - c) ** 2) / (2 * sigma_px**2))
    values = areal_parameters.feature_parameters(z, pixel_size_um=PIXEL_UM)
    # 8 x 8 bumps; the 28 whose hills reach the border are incomplete and left out.
    area = z.size * PIXEL_UM**2
    assert values["Spd"] == pytest.approx(36 / area, rel=1e-12)
    # Central second differences of a Gaussian at its top: 2 A (1 - exp(-1 / (2 s²))) / dx² per axis.
    assert values["Spc"] == pytest.approx(2 * height * (1 - np.exp(-1 / (2 * sigma_px**2))) / PIXEL_UM**2, rel=1e-3)
    # Ripples far below 5 % of Sz add thousands of local maxima; Wolf pruning merges them all.
    rippled = z + 0.02 * height * np.sin(2 * np.pi * cols / 3.7) * np.sin(2 * np.pi * rows / 4.3)
    assert areal_parameters.feature_parameters(rippled, pixel_size_um=PIXEL_UM)["Spd"] == pytest.approx(
        36 / area, rel=1e-12
    )


def test_holes_are_left_out_of_every_parameter():
    z = self_affine((256, 256), hurst=0.8, seed=4, max_wavelength_px=40)
    holes = z.copy()
    holes[100:112, 60:75] = np.nan
    holes[::29, ::31] = np.nan
    full = areal_parameters.areal_parameters(z, pixel_size_um=PIXEL_UM)
    partial = areal_parameters.areal_parameters(holes, pixel_size_um=PIXEL_UM)
    assert set(partial) == set(areal_parameters.UNITS)
    assert all(np.isfinite(v) for v in partial.values())
    for name in ("Sa", "Sq", "Sdq", "Sdr", "Sal", "Str", "Sk", "Vmc", "Vvc"):
        assert partial[name] == pytest.approx(full[name], rel=0.03), name
    assert partial["Std"] == full["Std"]


def test_bad_input_is_named():
    with pytest.raises(ValueError, match="pixel_size_um"):
        areal_parameters.areal_parameters(np.zeros((8, 8)), pixel_size_um=0.0)
    with pytest.raises(ValueError, match="z_um"):
        areal_parameters.height_parameters(np.zeros(8))
    with pytest.raises(ValueError, match="p_percent"):
        areal_parameters.functional_parameters(np.ones((8, 8)), p_percent=80, q_percent=10)

"""The surface texture chain as the product runs it (surface.roughness.analyse): its default
(plane, no filters) against an established implementation (surfalize), known truths through the
chain, and the profile sampling geometry."""

from __future__ import annotations

import numpy as np
import pytest
from surface_truth import centred_sa
from surfalize import Surface

from fractoscope import synthetic
from fractoscope.errors import InvalidInputError
from fractoscope.surface import form_removal, profile_parameters, profiles, roughness


@pytest.fixture(scope="module")
def rough_surface() -> np.ndarray:
    tilt = np.add.outer(0.02 * np.arange(256), -0.01 * np.arange(256))
    return synthetic.self_affine_surface((256, 256), hurst=0.8, rms_um=1.5, seed=7) + tilt


def test_areal_parameters_agree_with_surfalize(rough_surface):
    pixel_um = 0.2
    ours = roughness.analyse(rough_surface, pixel_size_um=pixel_um).parameters
    reference = Surface(rough_surface.copy(), pixel_um, pixel_um).level()
    for name in ("Sa", "Sq", "Ssk", "Sku", "Sp", "Sv", "Sz", "Sdq"):
        assert ours[name] == pytest.approx(getattr(reference, name)(), rel=1e-6), name
    # surfalize divides by the width and height of the whole grid, we by the complete cells.
    assert ours["Sdr"] == pytest.approx(reference.Sdr(), rel=0.02)


def test_unknown_points_are_left_out(rough_surface):
    holes = rough_surface.copy()
    holes[100:110, 50:60] = np.nan
    values = roughness.analyse(holes, pixel_size_um=0.2).parameters
    assert all(np.isfinite(values[name]) for name in ("Sa", "Sq", "Sdr", "Sk", "Vmc", "Sal"))
    assert values["Sa"] == pytest.approx(roughness.analyse(rough_surface, pixel_size_um=0.2).parameters["Sa"], rel=0.02)


@pytest.mark.parametrize("hurst", [0.6, 0.8, 0.9])
def test_hurst_exponent_of_self_affine_surfaces(hurst):
    surface = synthetic.self_affine_surface((512, 512), hurst=hurst, rms_um=1.0, seed=3, min_wavelength_px=2.0)
    metrics = roughness.analyse(surface, pixel_size_um=0.1).legacy()
    assert metrics["hurst_exponent"] == pytest.approx(hurst, abs=0.08)
    assert metrics["fractal_dimension"] == pytest.approx(3 - metrics["hurst_exponent"])
    assert metrics["hurst_fit_min_um"] == pytest.approx(0.4, rel=0.3)  # 4 windows of 1 px


@pytest.mark.parametrize("form", ["plane", "poly3", "sphere", "cylinder"])
def test_a_known_form_plus_roughness_gives_the_roughness_sa_back(form):
    """Through the whole chain (no filters): within 1 % of the roughness's own Sa."""
    texture = synthetic.self_affine_surface((384, 384), hurst=0.7, rms_um=0.5, seed=11, max_wavelength_px=30)
    rows, cols = np.indices(texture.shape) * 0.25
    shapes = {
        "plane": 0.05 * cols - 0.03 * rows,
        "poly3": 2e-4 * cols**3 - 0.01 * cols * rows + 0.04 * rows**2,
        "sphere": np.sqrt(400.0**2 - (cols - 48) ** 2 - (rows - 48) ** 2),
        "cylinder": np.sqrt(150.0**2 - (cols - 48) ** 2),
    }
    analysis = roughness.analyse(shapes[form] + texture, pixel_size_um=0.25, chain=roughness.surface_chain(form=form))
    assert analysis.chain.form == form
    assert analysis.parameters["Sa"] == pytest.approx(centred_sa(texture), rel=0.01)


def test_levelling_on_a_region_keeps_a_step_outside_it():
    x = np.arange(256) * 0.5
    substrate = np.zeros((256, 256), bool)
    substrate[:, :80] = True
    step = np.where(substrate, 0.0, 3.0)
    z = 0.02 * x[None, :] + 0.01 * x[:, None] + step
    levelled = roughness.analyse(z, pixel_size_um=0.5, levelling_region=substrate)
    assert levelled.chain.levelled_on_region
    assert levelled.parameters["Sz"] == pytest.approx(3.0, rel=1e-6)


@pytest.mark.slow
def test_the_chain_reports_its_cutoffs_and_uncertainties(rough_surface):
    chain = roughness.surface_chain(form="poly2", lambda_s_um=0.6, lambda_c_um=12.0, direction_deg=30.0, window_px=3)
    analysis = roughness.analyse(
        rough_surface, pixel_size_um=0.2, chain=chain, sigma_um=0.02, tilt_rel_uncertainty=0.01
    )
    assert (analysis.chain.lambda_s_um, analysis.chain.lambda_c_um, analysis.chain.window_px) == (0.6, 12.0, 3.0)
    assert set(analysis.uncertainty.u_tilt) >= {"Sa", "Sq", "Sz"}
    assert analysis.uncertainty.u_tilt["Sa"] == pytest.approx(0.01 * analysis.parameters["Sa"])
    assert analysis.uncertainty.noise_bias["Sq"] > 0
    fits = analysis.hurst.fits["hhc"]
    assert (fits["along"].direction_deg, fits["across"].direction_deg) == (30.0, 120.0)
    assert analysis.psd_q_per_um.size == analysis.psd_um4.size > 10


@pytest.mark.parametrize(
    ("options", "field"),
    [
        ({"form": "poly9"}, "form"),
        ({"lambda_s_um": -1.0}, "s_filter_um"),
        ({"lambda_s_um": 5.0, "lambda_c_um": 2.0}, "s_filter_um"),
        ({"window_px": 0.0}, "window_px"),
        ({"direction_deg": float("nan")}, "direction_deg"),
    ],
)
def test_bad_settings_name_their_field(options, field):
    with pytest.raises(InvalidInputError) as raised:
        roughness.surface_chain(**options)
    assert raised.value.field == field


@pytest.mark.slow
@pytest.mark.parametrize(
    ("cutoffs", "field"), [({"lambda_s_um": 1e300}, "s_filter_um"), ({"lambda_c_um": 1e9}, "l_filter_um")]
)
def test_a_cutoff_far_beyond_the_field_is_refused_naming_its_filter(rough_surface, cutoffs, field):
    """A Gaussian much wider than the field is flat across it: such a cut-off (the fuzzed API's
    1e300) filters nothing and is refused, by the areal chain and the profile chain alike."""
    with pytest.raises(InvalidInputError) as raised:
        roughness.analyse(rough_surface, pixel_size_um=0.2, chain=roughness.surface_chain(**cutoffs))
    assert raised.value.field == field and "times the field" in raised.value.message
    with pytest.raises(
        ValueError, match=next(iter(cutoffs))
    ):  # beyond the field, or (lambda_s) above the default lambda_c
        profile_parameters.roughness_profile(rough_surface[0], spacing_um=0.2, **cutoffs)
    edge = 10 * 256 * 0.2  # MAX_CUTOFF_FIELDS times the longer side: still taken
    assert np.isfinite(
        roughness.analyse(rough_surface, pixel_size_um=0.2, chain=roughness.surface_chain(lambda_c_um=edge)).parameters[
            "Sa"
        ]
    )


def test_profile_parameters_of_a_cosine_on_a_slope():
    # A cosine symmetric about the middle is orthogonal to the line, so de-tilting leaves it whole.
    distance = np.linspace(0, 100, 100001)
    heights = 2.0 * np.cos(2 * np.pi * (distance - 50) / 10) + 0.3 * distance
    spacing = distance[1] - distance[0]
    line_removed = form_removal.remove_profile_form(heights, spacing_um=spacing, form="plane")
    values = profile_parameters.profile_parameters(line_removed, spacing_um=spacing)
    assert values["Ra"] == pytest.approx(2 * 2.0 / np.pi, rel=1e-3)  # mean |cos| = 2/pi
    assert values["Rq"] == pytest.approx(2.0 / np.sqrt(2), rel=1e-3)
    assert values["Rz"] == pytest.approx(4.0, rel=1e-3)
    assert values["Rsk"] == pytest.approx(0.0, abs=1e-3)
    assert values["Rku"] == pytest.approx(1.5, rel=1e-3)


def test_profile_forms_remove_an_arc_and_a_polynomial():
    x = np.arange(4000) * 0.05
    wave = 0.2 * np.sin(2 * np.pi * x / 5.0)
    arc = np.sqrt(300.0**2 - (x - 90.0) ** 2)
    for form, shape in (("sphere", arc), ("poly4", 1e-6 * (x - 100) ** 4 - 1e-3 * x**2)):
        residual = form_removal.remove_profile_form(shape + wave, spacing_um=0.05, form=form)
        assert np.sqrt(np.mean((residual - residual.mean() - wave) ** 2)) < 0.03 * 0.2, form


def test_polyline_positions_keep_vertices_and_spacing():
    positions, distances = profiles.polyline_positions(np.array([[0, 0], [3, 4], [3, 10]]), spacing_um=0.5)
    assert distances[-1] == pytest.approx(11.0)
    assert [3.0, 4.0] in positions.tolist()
    assert np.diff(distances).max() <= 0.5 + 1e-12


@pytest.mark.parametrize(
    ("cutoffs", "field"), [({"lambda_c_um": 0.1}, "l_filter_um"), ({"lambda_s_um": 5e-324}, "s_filter_um")]
)
def test_a_cutoff_below_two_pixels_is_refused_naming_its_filter(rough_surface, cutoffs, field):
    """Wavelengths under two pixels are not sampled: a cut-off there filters nothing (the probe's
    lambda_c of 0.1 µm at 0.5 µm pixels ended in a division by zero)."""
    with pytest.raises(InvalidInputError) as raised:
        roughness.analyse(rough_surface, pixel_size_um=0.5, chain=roughness.surface_chain(**cutoffs))
    assert raised.value.field == field and "2 sampling steps" in raised.value.message
    with pytest.raises(ValueError, match="2 sampling steps"):
        profile_parameters.roughness_profile(rough_surface[0], spacing_um=0.5, **{"lambda_s_um": 0.0, **cutoffs})


def test_a_flat_field_has_zero_heights_and_no_shape_parameters():
    flat = np.full((64, 64), 5.0)
    analysis = roughness.analyse(flat, pixel_size_um=0.5, sigma_um=0.01, tilt_rel_uncertainty=0.01)
    values = analysis.parameters
    assert max(values["Sa"], values["Sq"], values["Sz"]) < 1e-12  # the plane's rounding
    assert np.isnan(values["Ssk"]) and np.isnan(values["Sku"])  # undefined, not 0
    assert np.isfinite(analysis.uncertainty.u_total["Sa"]) and np.isnan(analysis.uncertainty.u_total.get("Sq", np.nan))


def test_scattered_points_are_refused_and_a_long_strip_is_analysed():
    scattered = np.full((64, 64), np.nan)
    scattered[::3, ::3] = np.random.default_rng(1).normal(size=scattered[::3, ::3].shape)
    with pytest.raises(InvalidInputError, match="scattered") as raised:
        roughness.analyse(scattered, pixel_size_um=0.5)
    assert raised.value.field == "region"
    strip = synthetic.self_affine_surface((16, 4096), hurst=0.8, rms_um=1.0, seed=3)
    values = roughness.analyse(strip, pixel_size_um=0.1).parameters
    assert values["Sq"] > 0 and np.isfinite(values["Sdq"]) and np.isfinite(values["Std"])


def test_an_exponent_outside_zero_to_one_is_noted():
    """A sine is not self-affine: its H comes out above 1, and the note says what that means."""
    x = np.arange(256) * 0.5
    sine = np.sin(2 * np.pi * np.add.outer(x, x) / 60.0)
    hurst = roughness.analyse(sine, pixel_size_um=0.5, chain=roughness.surface_chain(form="none", window_px=1.0)).hurst
    assert any(not 0 <= fit.hurst <= 1 for fits in hurst.fits.values() for fit in fits.values())
    assert any("not self-affine" in fit.not_determinable for fits in hurst.fits.values() for fit in fits.values())

"""Form removal: a known form plus roughness gives the roughness back."""

from __future__ import annotations

import functools

import numpy as np
import pytest
from surface_truth import centred_sa, self_affine

from fractoscope.surface import form_removal

PIXEL_UM = 0.5
SIZE = 512


@pytest.fixture(scope="module")
def roughness() -> np.ndarray:
    # Wavelengths up to 16 px only: a rougher field's own low-order polynomial content (which any
    # fit rightly takes for form) would then be well under 1 % of its Sa even for degree 6.
    return self_affine((SIZE, SIZE), hurst=0.8, seed=3, rms_um=0.5, max_wavelength_px=16)


def _grid():
    rows, cols = np.indices((SIZE, SIZE))
    return cols * PIXEL_UM, rows * PIXEL_UM


def _cylinder_heights(x, y, *, azimuth_deg, elevation, radius_um, axis_point):
    u = np.array([np.cos(np.radians(azimuth_deg)), np.sin(np.radians(azimuth_deg)), elevation])
    u /= np.linalg.norm(u)
    dx, dy = x - axis_point[0], y - axis_point[1]
    lateral = dx * u[0] + dy * u[1]
    qa, qb, qc = 1 - u[2] ** 2, -2 * u[2] * lateral, dx**2 + dy**2 - lateral**2 - radius_um**2
    return axis_point[2] + (-qb + np.sqrt(qb**2 - 4 * qa * qc)) / (2 * qa)


def _forms() -> dict[str, np.ndarray]:
    x, y = _grid()
    return {
        "plane": 3.0 + 0.01 * x - 0.02 * y,
        "poly2": 1e-4 * (x - 100) ** 2 + 2e-4 * (y - 80) * (x - 30) + 0.01 * y,
        "poly4": 2e-8 * (x - 120) ** 4 - 1e-7 * (y - 60) ** 3 * (x / 100),
        "poly6": 1e-12 * (x - 128) ** 6 + 1e-9 * (y - 100) ** 4 * (x / 100),
        "sphere": 50.0 + np.sqrt(2000.0**2 - (x - 130) ** 2 - (y - 120) ** 2) - 2000.0,
        "cylinder": _cylinder_heights(
            x, y, azimuth_deg=30.0, elevation=0.01, radius_um=1500.0, axis_point=(128, 128, -1500.0)
        ),
    }


@pytest.mark.slow
@pytest.mark.parametrize("form", ["plane", "poly2", "poly4", "poly6", "sphere", "cylinder"])
def test_known_form_plus_roughness_gives_the_roughness_sa_back(roughness, form):
    fit = form_removal.remove_form(_forms()[form] + roughness, pixel_size_um=PIXEL_UM, form=form)
    assert centred_sa(fit.residual_um) == pytest.approx(centred_sa(roughness), rel=0.01)
    assert np.allclose(fit.residual_um + fit.form_um, _forms()[form] + roughness)


@pytest.mark.slow
def test_sphere_and_cylinder_geometry_is_recovered(roughness):
    fit = functools.partial(form_removal.remove_form, pixel_size_um=PIXEL_UM, max_fit_points=65_536)
    sphere = fit(_forms()["sphere"] + roughness, form="sphere")
    assert sphere.parameters["radius_um"] == pytest.approx(2000.0, rel=0.03)
    assert sphere.parameters["centre_um"][:2] == pytest.approx([130.0, 120.0], abs=2.0)
    assert sphere.parameters["convex"]
    cylinder = fit(_forms()["cylinder"] + roughness, form="cylinder")
    assert cylinder.parameters["radius_um"] == pytest.approx(1500.0, rel=0.03)
    assert cylinder.parameters["axis_azimuth_deg"] == pytest.approx(30.0, abs=0.5)
    # A bowl (concave) is fitted as well as a dome.
    bowl = fit(-_forms()["sphere"] + roughness, form="sphere")
    assert not bowl.parameters["convex"]
    assert centred_sa(bowl.residual_um) == pytest.approx(centred_sa(roughness), rel=0.01)


def test_outliers_do_not_pull_the_robust_fit(roughness):
    z = _forms()["poly2"] + roughness
    # 3 % of the points, all in one quarter of the field, 50 RMS high: mismatches in a textureless
    # corner, which pull a least-squares fit's slope and curvature.
    x, y = _grid()
    spikes = (np.random.default_rng(5).random(z.shape) < 0.12) & (x > 128) & (y > 128)
    z[spikes] += 25.0
    robust = form_removal.remove_form(z, pixel_size_um=PIXEL_UM, form="poly2")
    plain = form_removal.remove_form(z, pixel_size_um=PIXEL_UM, form="poly2", robust=False)
    truth = centred_sa(roughness[~spikes])
    assert centred_sa(robust.residual_um[~spikes]) == pytest.approx(truth, rel=0.01)
    assert abs(centred_sa(plain.residual_um[~spikes]) / truth - 1) > 0.05
    assert robust.inlier_fraction == pytest.approx(0.97, abs=0.01)


def test_levelling_on_a_region_keeps_a_step_outside_it(roughness):
    x, y = _grid()
    substrate = x < 120.0
    z = 0.02 * x + 0.01 * y + np.where(substrate, 0.0, 4.0) + roughness
    fit = form_removal.remove_form(z, pixel_size_um=PIXEL_UM, form="plane", region=substrate)
    assert np.median(fit.residual_um[~substrate]) - np.median(fit.residual_um[substrate]) == pytest.approx(
        4.0, abs=0.05
    )
    everywhere = form_removal.remove_form(z, pixel_size_um=PIXEL_UM, form="plane")
    assert abs(np.median(everywhere.residual_um[~substrate]) - np.median(everywhere.residual_um[substrate]) - 4.0) > 0.5


def test_holes_stay_holes_and_do_not_move_the_fit(roughness):
    z = _forms()["poly4"] + roughness
    holes = z.copy()
    holes[100:160, 200:290] = np.nan
    holes[::37, ::41] = np.nan
    fit = form_removal.remove_form(holes, pixel_size_um=PIXEL_UM, form="poly4")
    assert np.array_equal(np.isnan(fit.residual_um), np.isnan(holes))
    assert np.isfinite(fit.form_um).all()
    assert centred_sa(fit.residual_um) == pytest.approx(centred_sa(roughness[np.isfinite(holes)]), rel=0.01)


def test_large_maps_are_fitted_on_a_regular_subsample(roughness):
    fit = form_removal.remove_form(
        _forms()["poly2"] + roughness, pixel_size_um=PIXEL_UM, form="poly2", max_fit_points=10_000
    )
    assert 2_500 <= fit.fit_points <= 10_000
    assert centred_sa(fit.residual_um) == pytest.approx(centred_sa(roughness), rel=0.01)


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"form": "poly7"}, "form must be one of"),
        ({"pixel_size_um": 0.0}, "pixel_size_um"),
        ({"region": np.ones((3, 3), dtype=bool)}, "region has shape"),
        ({"region": np.zeros((SIZE, SIZE), dtype=bool)}, "region"),
    ],
)
def test_bad_arguments_are_named(roughness, options, message):
    arguments = {"pixel_size_um": PIXEL_UM, "form": "plane"} | options
    with pytest.raises(ValueError, match=message):
        form_removal.remove_form(roughness, **arguments)


@pytest.mark.parametrize("form", ["sphere", "cylinder"])
@pytest.mark.parametrize("robust", [False, True])
def test_a_flat_or_tilted_surface_is_the_curved_forms_limit(form, robust):
    """A least-squares sphere or cylinder includes the plane as its infinite-radius limit, so it
    never leaves more than the plane does: on a tilted plane a cylinder fit started at the
    quadratic fit alone left 2.5 µm RMS, a sphere on a constant map 12 µm."""
    x, y = (values[:128, :128] for values in _grid())
    for z in (0.3 * x - 0.1 * y + 2.0, np.full(x.shape, 5.0)):
        fit = form_removal.remove_form(z, pixel_size_um=PIXEL_UM, form=form, robust=robust)
        assert np.isfinite(fit.residual_um).all()
        assert np.abs(fit.residual_um).max() < 1e-4
        assert fit.parameters["radius_um"] > 1e4


@pytest.mark.parametrize("form", ["sphere", "cylinder"])
def test_a_straight_profile_is_the_arcs_limit(form):
    x_um = np.arange(400) * PIXEL_UM
    for profile in (0.3 * x_um + 2.0, np.full(x_um.shape, 3.0)):
        assert np.abs(form_removal.remove_profile_form(profile, spacing_um=PIXEL_UM, form=form)).max() < 1e-6
    arc = np.sqrt(500.0**2 - (x_um - 90.0) ** 2) - 500.0
    assert np.abs(form_removal.remove_profile_form(arc, spacing_um=PIXEL_UM, form=form)).max() < 1e-6

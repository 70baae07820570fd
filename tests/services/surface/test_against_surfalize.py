"""Every parameter that both compute, against surfalize (an independent implementation of ISO 25178-2
and ISO 21920-2), on the same surfaces; each tolerance says where and why the definitions differ."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from surface_truth import self_affine
from surfalize import Profile, Surface
from surfalize.filter import GaussianFilter

from fractoscope.surface import areal_parameters, form_removal, iso_filters, profile_parameters

PIXEL_UM = 0.2

# Same definitions, same arithmetic up to rounding.
EXACT = ("Sa", "Sq", "Ssk", "Sku", "Sp", "Sv", "Sz", "Sdq", "Sdr", "Spc")
# Both find where the unbiased f_ACF first falls to 0.2 along rays from the origin; surfalize casts
# a ray to every pixel on the edge of the region above the threshold and interpolates cubically, we
# cast one every 0.5° and interpolate linearly.
SPATIAL_REL = 0.02
# surfalize samples the material ratio curve at 10 000 quantiles and integrates the volumes up to
# the nearest sample; we interpolate a 65 536-class height histogram.
FUNCTIONAL_REL = 0.01
FUNCTIONAL = ("Sk", "Spk", "Svk", "Smr1", "Smr2", "Vmp", "Vmc", "Vvc", "Vvv")


def _surfaces() -> dict[str, np.ndarray]:
    rows, cols = np.indices((256, 256))
    return {
        "isotropic": self_affine((256, 256), hurst=0.8, seed=7, rms_um=1.5, max_wavelength_px=40),
        # Every other column of a 256 x 512 field: features half as wide as they are tall.
        "anisotropic": self_affine((256, 512), hurst=0.7, seed=5, max_wavelength_px=30)[:, ::2],
        "sine grid": 0.8 * np.sin(2 * np.pi * cols / 32.0) + 0.5 * np.sin(2 * np.pi * rows / 21.3),
    }


def _theirs(z: np.ndarray) -> dict[str, float]:
    surface = Surface(z.copy(), PIXEL_UM, PIXEL_UM)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return {name: float(getattr(surface, name)()) for name in areal_parameters.UNITS}


@pytest.fixture(scope="module", params=list(_surfaces()))
def both(request):
    z = _surfaces()[request.param]
    return request.param, z, areal_parameters.areal_parameters(z, pixel_size_um=PIXEL_UM), _theirs(z)


def test_height_hybrid_and_curvature_parameters_agree_exactly(both):
    _, _, ours, theirs = both
    for name in EXACT:
        assert ours[name] == pytest.approx(theirs[name], rel=1e-9), name


def test_spatial_parameters_agree(both):
    _, _, ours, theirs = both
    for name in ("Sal", "Str"):
        # Both say NaN where f_ACF does not decay in some direction (the sine grid's Str).
        assert ours[name] == pytest.approx(theirs[name], rel=SPATIAL_REL, nan_ok=True), name


def test_texture_direction_agrees_where_there_is_one(both):
    name, _, ours, theirs = both
    if name == "isotropic":
        pytest.skip("an isotropic surface has no texture direction: both answers are noise")
    # surfalize sums |F| over angular bins of the frequency grid, we integrate it along rays.
    assert abs((ours["Std"] - theirs["Std"] + 90.0) % 180.0 - 90.0) <= 2.0


def test_functional_parameters_agree(both):
    _, _, ours, theirs = both
    for name in FUNCTIONAL:
        assert ours[name] == pytest.approx(theirs[name], rel=FUNCTIONAL_REL, abs=1e-4), name


def test_peak_density_agrees_with_the_area_convention_spelled_out(both):
    _, z, ours, theirs = both
    # The same significant peaks; surfalize divides by the (cols - 1)(rows - 1) cells' area, we by
    # the known points' count times the pixel area.
    rows, cols = z.shape
    assert ours["Spd"] == pytest.approx(theirs["Spd"] * (rows - 1) * (cols - 1) / (rows * cols), rel=1e-12)


def test_least_squares_forms_agree():
    z = self_affine((200, 240), hurst=0.8, seed=2) + np.add.outer(0.01 * np.arange(200) ** 1.5, -0.02 * np.arange(240))
    for degree, form in ((1, "plane"), (3, "poly3"), (5, "poly5")):
        theirs = Surface(z.copy(), PIXEL_UM, PIXEL_UM).detrend_polynomial(degree=degree).data
        # Same space of polynomials (surfalize's monomials, our Legendre basis), plain least squares.
        ours = form_removal.remove_form(z, pixel_size_um=PIXEL_UM, form=form, robust=False).residual_um
        assert np.allclose(ours, theirs, atol=1e-9), form


def test_gaussian_filters_agree_away_from_the_edges():
    z = self_affine((300, 300), hurst=0.8, seed=9)
    interior = (slice(60, 240), slice(60, 240))
    for cutoff in (1.0, 16.0):  # sigma 0.9 px (our direct path) and 15 px (our FFT path)
        theirs = GaussianFilter(cutoff, "highpass")(Surface(z.copy(), PIXEL_UM, PIXEL_UM)).data
        ours = iso_filters.l_filter(z, pixel_size_um=PIXEL_UM, lambda_c_um=cutoff)
        # Same sigma; surfalize reflects the data at the edges (we renormalise the Gaussian there),
        # and cuts its kernel at 4 sigma (we at 5, or not at all by FFT): 1e-4 of the tails' weight.
        assert np.max(np.abs(ours - theirs)[interior]) < 5e-4 * z.std()


def test_profile_parameters_agree():
    z = self_affine((8, 8192), hurst=0.7, seed=2, max_wavelength_px=200)[3]
    ours = profile_parameters.profile_parameters(z, spacing_um=0.05)
    theirs = Profile(z.copy(), 0.05)
    for name in ("Ra", "Rq", "Rsk", "Rku", "Rp", "Rv", "Rz", "Rt"):
        assert ours[name] == pytest.approx(getattr(theirs, name)(), rel=1e-9), name
    for name in ("Rk", "Rpk", "Rvk", "Rmr1", "Rmr2"):
        assert ours[name] == pytest.approx(getattr(theirs, name)(), rel=FUNCTIONAL_REL), name
    # ISO 21920-2's 7-point derivative against surfalize's first difference: equal for a
    # well-sampled profile (here 200+ samples per shortest wavelength would give 1e-4).
    assert ours["Rdq"] == pytest.approx(theirs.Rdq(), rel=0.01)


def test_a_known_abbott_curve_agrees_with_surfalize():
    """The analytic Abbott surface of test_areal_parameters (heights whose material ratio curve is
    three straight pieces, shuffled over the grid): both find the same Sk family and volumes within
    FUNCTIONAL_REL, and the same heights exactly."""
    count = 512 * 512
    ratio = (np.arange(count) + 0.5) * 100.0 / count
    z = (
        np.random.default_rng(0)
        .permutation(np.interp(ratio, [0.0, 10.0, 90.0, 100.0], [3.0, 1.0, -1.0, -4.0]))
        .reshape(512, 512)
    )
    ours = areal_parameters.functional_parameters(z) | areal_parameters.height_parameters(z)
    theirs = Surface(z.copy(), PIXEL_UM, PIXEL_UM)
    assert ours["Sk"] == pytest.approx(2.5, rel=2e-3)  # the core line from 1.25 to -1.25 µm (test_areal_parameters)
    for name in FUNCTIONAL:
        assert ours[name] == pytest.approx(getattr(theirs, name)(), rel=FUNCTIONAL_REL, abs=1e-4), name
    for name in ("Sa", "Sq", "Ssk", "Sku", "Sp", "Sv", "Sz"):
        assert ours[name] == pytest.approx(getattr(theirs, name)(), rel=1e-9), name

"""The default method's matching sigma against the known heights of synthetic pairs with exact
tilts (2 % noise): 58-82 % of the errors within one sigma and 90-99 % within two, on the
renderer its constants were fitted on and on one they were not; on renderers whose shading
misleads the matcher more, calibrated per pair by the disagreement of its two refined directions,
58-80 % and 89-99 % (the full table, with the issue's 60-76 % and 92-98 % targets:
benchmarks/sigma_calibration.py)."""

import numpy as np
import pytest
from conftest import dimple_pair, fracture_pair, inner_mask

from fractoscope import synthetic
from fractoscope.sem.image import SemImage
from fractoscope.stereo.inputs import MatchingOptions
from fractoscope.stereo.pipeline import compute_height_map


def _coverage(pair, physics=synthetic.DEFAULT_PHYSICS) -> dict:
    options = MatchingOptions(tilt_uncertainty_deg=0.0, detector_from_tilt_axis_deg=physics.detector_from_tilt_axis_deg)
    first, second = (SemImage(image, None, None, 0) for image in (pair.first, pair.second))
    result = compute_height_map(
        first, second, tilt_deg=(-5.0, 5.0), pixel_size_um=synthetic.REFERENCE_PIXEL_SIZE_UM, options=options
    )
    known = inner_mask(pair.z_seen_um.shape) & np.isfinite(result.z_um)
    error = result.z_um[known] - pair.z_seen_um[known]
    ratio = np.abs(error - np.median(error)) / result.sigma_um[known]
    return {"within_one_sigma": np.mean(ratio < 1.0), "within_two_sigma": np.mean(ratio < 2.0)}


@pytest.mark.parametrize("make_pair", [fracture_pair, dimple_pair], ids=["self-affine", "dimples"])
def test_matching_sigma_covers_the_errors_as_a_sigma_should(make_pair):
    """Default renderer, 2 % noise (the fitted one)."""
    measured = _coverage(make_pair())
    assert 0.58 <= measured["within_one_sigma"] <= 0.82
    assert 0.90 <= measured["within_two_sigma"] <= 0.99


def test_matching_sigma_holds_on_a_renderer_it_was_not_fitted_on():
    """Coarser texture and a weaker secant law: the sigma was not tuned on it."""
    physics = synthetic.PHYSICS_VARIANTS["secant_k0.6_coarse_texture"]
    measured = _coverage(dimple_pair(physics=physics), physics)
    assert 0.58 <= measured["within_one_sigma"] <= 0.82
    assert 0.90 <= measured["within_two_sigma"] <= 0.99


@pytest.mark.parametrize(
    ("name", "kind"),
    [("lambert", "self_affine"), ("secant_k1.6_side_detector", "dimples")],
    ids=["lambert-self-affine", "side-detector-dimples"],
)
def test_matching_sigma_is_calibrated_per_pair_on_renderers_it_was_not_fitted_on(name, kind):
    """Measured 61.7 % and 91.1 % (Lambert, self-affine), 67.3 % and 91.9 % (secant k 1.6 with a
    side detector in the chamber, dimples); with one constant scale for every pair, as before,
    52.5 % and 83.9 %, 55.4 % and 81.3 %."""
    physics = synthetic.PHYSICS_VARIANTS[name]
    pair = synthetic.render_stereo_pair(
        synthetic.reference_surface(kind, 704, seed=1),
        pixel_size_um=synthetic.REFERENCE_PIXEL_SIZE_UM,
        tilt_deg=(-5.0, 5.0),
        output_shape=(640, 640),
        seed=1,
        physics=physics,
    )
    measured = _coverage(pair, physics)
    assert 0.58 <= measured["within_one_sigma"] <= 0.80
    assert 0.89 <= measured["within_two_sigma"] <= 0.99

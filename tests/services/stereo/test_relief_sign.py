"""Which way up the relief is (issue 36): the detector's lighting tells the true relief from its
mirror image, `auto` puts it the right way up and says so, and where the images cannot tell it
the tilts as given are kept with a warning, never a silent inversion."""

import numpy as np
import pytest

from fractoscope import synthetic
from fractoscope.sem.image import SemImage
from fractoscope.stereo import relief_sign
from fractoscope.stereo.inputs import MatchingOptions
from fractoscope.stereo.pipeline import compute_series_height_map
from fractoscope.stereo.relief_sign import ReliefSignMode

PIXEL_SIZE_UM = 0.1


def _pair(kind: str, tilt_deg, seed: int):
    surface = synthetic.reference_surface(kind, 256 + 64, seed=seed)
    return synthetic.render_stereo_pair(
        surface, pixel_size_um=PIXEL_SIZE_UM, tilt_deg=tilt_deg, output_shape=(256, 256), seed=seed
    )


@pytest.mark.parametrize("kind", ["self_affine", "dimples"])
def test_the_true_relief_is_told_from_its_mirror_image(kind):
    pair = _pair(kind, (-5.0, 5.0), seed=3)
    z_px = pair.z_seen_um / PIXEL_SIZE_UM
    true = relief_sign.relief_sign_from_shading(pair.first, z_px, detector_azimuth_deg=90.0)
    mirrored = relief_sign.relief_sign_from_shading(pair.first, -z_px, detector_azimuth_deg=90.0)
    assert true.decided and not true.inverted and true.strength > 0.8
    assert mirrored.decided and mirrored.inverted and mirrored.strength < -0.8
    # The renderer's detector is at the top: said to be at the bottom, the verdict turns round.
    assert relief_sign.relief_sign_from_shading(pair.first, z_px, detector_azimuth_deg=270.0).inverted


def test_a_detector_along_the_tilt_direction_or_unknown_decides_nothing():
    pair = _pair("dimples", (-5.0, 5.0), seed=3)
    z_px = pair.z_seen_um / PIXEL_SIZE_UM
    for azimuth in (0.0, 180.0, float("nan")):
        verdict = relief_sign.relief_sign_from_shading(pair.first, z_px, detector_azimuth_deg=azimuth)
        assert not verdict.decided and verdict.cue == "none" and verdict.reason


def _heights(pair, stated, **options):
    views = [SemImage(pair.first, stated[0], PIXEL_SIZE_UM, 0), SemImage(pair.second, stated[1], PIXEL_SIZE_UM, 0)]
    return compute_series_height_map(views, options=MatchingOptions(**options))


def _correlation(z_um, truth_um) -> float:
    known = np.isfinite(z_um)
    return float(np.corrcoef(z_um[known], truth_um[known])[0, 1])


@pytest.mark.slow
def test_auto_puts_a_relief_given_with_reversed_tilts_the_right_way_up_and_says_so():
    pair = _pair("dimples", (0.0, 5.0), seed=5)
    result = _heights(pair, (0.0, -5.0))
    assert _correlation(result.z_um, pair.z_seen_um) > 0.95
    assert result.report["relief_sign"] == "inverted" and result.report["relief_sign_decided"]
    assert result.report["relief_sign_cue"] == "shading" and result.report["relief_sign_confidence"] > 0.999
    assert result.report["tilt_deg"] == [0.0, 5.0]  # the tilts the heights used
    assert any("inverted under the tilts as given" in warning for warning in result.report["warnings"])
    assert result.report["parameters"]["relief_sign"] == "auto"


@pytest.mark.slow
def test_nominal_keeps_the_tilts_as_given_and_warns_where_the_images_disagree():
    pair = _pair("dimples", (0.0, 5.0), seed=5)
    kept = _heights(pair, (0.0, -5.0), relief_sign=ReliefSignMode.NOMINAL)
    assert _correlation(kept.z_um, pair.z_seen_um) < -0.95
    assert kept.report["relief_sign"] == "nominal"
    assert any("other way up" in warning for warning in kept.report["warnings"])
    forced = _heights(pair, (0.0, 5.0), relief_sign=ReliefSignMode.INVERTED)
    assert _correlation(forced.z_um, pair.z_seen_um) < -0.95 and forced.report["relief_sign"] == "inverted"


@pytest.mark.slow
def test_where_the_images_cannot_tell_the_tilts_as_given_are_kept_with_a_warning():
    """A flat specimen with material contrast only: no slope lights anything."""
    flat = np.zeros((256 + 64, 256 + 64))
    pair = synthetic.render_stereo_pair(
        flat, pixel_size_um=PIXEL_SIZE_UM, tilt_deg=(-5.0, 5.0), output_shape=(256, 256), seed=2
    )
    result = _heights(pair, (5.0, -5.0))
    assert result.report["relief_sign"] == "nominal" and not result.report["relief_sign_decided"]
    assert any("could not be told from the images" in warning for warning in result.report["warnings"])

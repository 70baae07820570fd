"""Which way up the relief is (issues 36, 46): the detector's lighting tells the true relief from
its mirror image only against a known detector place, at any azimuth; without one it is evidence
and never overrides the tilts; `auto` puts a relief the right way up where a cue decides and says
which cue and premise did, and keeps the tilts as given otherwise."""

import dataclasses

import numpy as np
import pytest

from fractoscope import synthetic
from fractoscope.sem.image import SemImage
from fractoscope.sem.metadata import InstrumentKey
from fractoscope.stereo import lighting
from fractoscope.stereo.inputs import MatchingOptions
from fractoscope.stereo.pipeline import compute_series_height_map
from fractoscope.stereo.relief_sign import ReliefSignMode
from fractoscope.synthetic.physics import SemPhysics

PIXEL_SIZE_UM = 0.1


def _pair(kind: str, tilt_deg, seed: int, physics: SemPhysics = synthetic.DEFAULT_PHYSICS):
    surface = synthetic.reference_surface(kind, 256 + 64, seed=seed)
    return synthetic.render_stereo_pair(
        surface, pixel_size_um=PIXEL_SIZE_UM, tilt_deg=tilt_deg, output_shape=(256, 256), seed=seed, physics=physics
    )


def _side_detector(azimuth_deg: float) -> SemPhysics:
    """A side detector in the chamber at `azimuth_deg` as displayed, as on another microscope."""
    return SemPhysics(detector_azimuth_deg=azimuth_deg, detector_in_chamber=True, detector_strength=0.5)


def _exact_views(pair, tilt_deg):
    """Both views on the first's grid through the exact parallax, and the true heights (px)."""
    z_px = pair.z_seen_um / PIXEL_SIZE_UM
    cols = np.arange(z_px.shape[1]) - (z_px.shape[1] - 1) / 2
    first, second = np.radians(tilt_deg)
    x_px = (cols[None, :] - z_px * np.sin(first)) / np.cos(first)
    second_px = x_px * np.cos(second) + z_px * np.sin(second) + (z_px.shape[1] - 1) / 2
    on_first = np.array(
        [np.interp(row_px, np.arange(z_px.shape[1]), row) for row_px, row in zip(second_px, pair.second)]
    )
    return [pair.first.astype(np.float32), on_first.astype(np.float32)], z_px


@pytest.mark.parametrize("azimuth_deg", [0.0, 90.0, 135.0, 180.0, 270.0])
def test_a_known_detector_tells_the_true_relief_from_its_mirror_image_at_any_azimuth(azimuth_deg):
    """Along the tilt direction too (0°, 180°): two tilts separate the detector's lighting from
    the yield law's response to the beam's tilt."""
    tilts = (-5.0, 5.0)
    physics = _side_detector(azimuth_deg)
    views, z_px = _exact_views(_pair("self_affine", tilts, seed=3, physics=physics), tilts)
    place = physics.detector_from_tilt_axis_deg
    true = lighting.relief_sign_from_lighting(
        lighting.block_lighting(views, tilts, z_px), detector_from_tilt_axis_deg=place
    )
    mirrored_tilts = (-tilts[0], -tilts[1])
    mirrored = lighting.relief_sign_from_lighting(
        lighting.block_lighting(views, mirrored_tilts, -z_px), detector_from_tilt_axis_deg=place
    )
    assert true.decided and not true.inverted and true.cue == "lighting"
    assert mirrored.decided and mirrored.inverted
    # Said to lie opposite, the detector turns the verdict round.
    opposite = lighting.relief_sign_from_lighting(
        lighting.block_lighting(views, tilts, z_px), detector_from_tilt_axis_deg=place + 180.0
    )
    assert opposite.decided and opposite.inverted


def test_the_lighting_direction_is_measured_where_the_detector_lies():
    tilts = (0.0, 5.0)
    for azimuth_deg in (30.0, 200.0):
        physics = _side_detector(azimuth_deg)
        views, z_px = _exact_views(_pair("dimples", tilts, seed=4, physics=physics), tilts)
        found, sigma = lighting.block_lighting(views, tilts, z_px).significant_direction()
        error = (found - physics.detector_from_tilt_axis_deg + 180.0) % 360.0 - 180.0
        assert abs(error) < 20.0 and sigma < 10.0, (azimuth_deg, found, sigma)


def test_images_without_lighting_from_a_side_show_no_direction():
    """In-lens: no detector term at all."""
    tilts = (-5.0, 5.0)
    in_lens = SemPhysics(detector_strength=0.0)
    views, z_px = _exact_views(_pair("self_affine", tilts, seed=3, physics=in_lens), tilts)
    assert lighting.block_lighting(views, tilts, z_px).significant_direction() is None


def _heights(pair, stated, *, instrument: InstrumentKey | None = None, **options):
    views = [
        SemImage(image, tilt, PIXEL_SIZE_UM, 0, instrument=instrument)
        for image, tilt in zip((pair.first, pair.second), stated)
    ]
    return compute_series_height_map(views, options=MatchingOptions(**options))


def _correlation(z_um, truth_um) -> float:
    known = np.isfinite(z_um)
    return float(np.corrcoef(z_um[known], truth_um[known])[0, 1])


@pytest.mark.parametrize("azimuth_deg", [90.0, 270.0])
def test_without_the_detectors_place_reversed_tilts_are_kept_and_the_lighting_is_only_evidence(azimuth_deg):
    """Issue 46: an assumed place decided the answer, so a detector at the bottom gave correct
    heights upside down. Unknown, it decides nothing, whichever side it is on."""
    pair = _pair("dimples", (-5.0, 5.0), seed=5, physics=_side_detector(azimuth_deg))
    result = _heights(pair, (-5.0, 5.0))
    assert _correlation(result.z_um, pair.z_seen_um) > 0.95
    report = result.report
    assert report["relief_sign"] == "nominal" and not report["relief_sign_decided"]
    assert report["detector_source"] == "unknown" and np.isnan(report["detector_from_tilt_axis_deg_used"])
    assert "follow the tilts as given" in report["relief_sign_sentence"]
    assert "the image's " + ("top" if azimuth_deg == 90.0 else "bottom") in report["relief_sign_evidence"]
    assert abs((report["lighting_from_tilt_axis_deg"] - (azimuth_deg - 90.0) + 180.0) % 360.0 - 180.0) < 20.0


@pytest.mark.slow
def test_auto_puts_a_relief_given_with_reversed_tilts_the_right_way_up_where_the_detector_is_given():
    physics = _side_detector(250.0)
    pair = _pair("dimples", (0.0, 5.0), seed=5, physics=physics)
    result = _heights(pair, (0.0, -5.0), detector_from_tilt_axis_deg=physics.detector_from_tilt_axis_deg)
    assert _correlation(result.z_um, pair.z_seen_um) > 0.95
    report = result.report
    assert report["relief_sign"] == "inverted" and report["relief_sign_decided"]
    assert report["relief_sign_cue"] == "lighting" and report["detector_source"] == "given"
    assert report["tilt_deg"] == [0.0, 5.0]  # the tilts the heights used
    sentence = report["relief_sign_sentence"]
    assert "inverted" in sentence and "lighting of a detector at 160° from the tilt axis, as given" in sentence
    assert sentence in report["warnings"]
    assert report["parameters"]["relief_sign"] == "auto"


@pytest.mark.slow
def test_nominal_keeps_the_tilts_as_given_and_warns_where_the_images_disagree():
    physics = _side_detector(90.0)
    pair = _pair("dimples", (0.0, 5.0), seed=5, physics=physics)
    place = physics.detector_from_tilt_axis_deg
    kept = _heights(pair, (0.0, -5.0), relief_sign=ReliefSignMode.NOMINAL, detector_from_tilt_axis_deg=place)
    assert _correlation(kept.z_um, pair.z_seen_um) < -0.95
    assert kept.report["relief_sign"] == "nominal"
    assert any("the other way up" in warning for warning in kept.report["warnings"])
    forced = _heights(pair, (0.0, 5.0), relief_sign=ReliefSignMode.INVERTED)
    assert _correlation(forced.z_um, pair.z_seen_um) < -0.95 and forced.report["relief_sign"] == "inverted"


@pytest.mark.slow
def test_where_the_images_cannot_tell_the_tilts_as_given_are_kept_and_the_sentence_says_so():
    """A flat specimen with material contrast only: no slope lights anything, even with the
    detector's place known."""
    flat = np.zeros((256 + 64, 256 + 64))
    pair = synthetic.render_stereo_pair(
        flat, pixel_size_um=PIXEL_SIZE_UM, tilt_deg=(-5.0, 5.0), output_shape=(256, 256), seed=2
    )
    result = _heights(pair, (5.0, -5.0), detector_from_tilt_axis_deg=0.0)
    assert result.report["relief_sign"] == "nominal" and not result.report["relief_sign_decided"]
    assert "cannot tell which way up" in result.report["relief_sign_sentence"]
    assert not any("which way up" in warning for warning in result.report["warnings"])  # the usual case


@pytest.mark.slow
def test_an_in_lens_detector_named_by_the_metadata_is_reported_without_a_side():
    pair = _pair("self_affine", (-5.0, 5.0), seed=6, physics=SemPhysics(detector_strength=0.0))
    in_lens = InstrumentKey("Zeiss", "Auriga 60", "InLens", 0.0)
    result = _heights(pair, (5.0, -5.0), instrument=in_lens)
    report = result.report
    assert report["detector_source"] == "in-lens" and not report["relief_sign_decided"]
    assert "an in-lens detector, without a side" in report["relief_sign_sentence"]
    assert report["instrument"] == dataclasses.asdict(in_lens)


def test_typed_tilts_that_run_against_the_files_stage_tilts_get_a_warning():
    pair = _pair("self_affine", (-5.0, 5.0), seed=7)
    views = [SemImage(image, tilt, PIXEL_SIZE_UM, 0) for image, tilt in zip((pair.first, pair.second), (-5.0, 5.0))]
    result = compute_series_height_map(views, tilt_deg=(5.0, -5.0), options=MatchingOptions(method="window_zncc"))
    assert any("run the other way from the stage tilts their files record" in w for w in result.report["warnings"])
    agreeing = compute_series_height_map(views, tilt_deg=(-4.0, 4.0), options=MatchingOptions(method="window_zncc"))
    assert not any("run the other way" in warning for warning in agreeing.report["warnings"])

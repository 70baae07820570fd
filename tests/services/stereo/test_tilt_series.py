"""Tilt self-calibration from three or more views: known angles recovered from disparities."""

from __future__ import annotations

import numpy as np
import pytest

from fractoscope.stereo import tilt_series


def _views(true_tilt_deg, *, noise_px=0.05, points=20_000, seed=0):
    rng = np.random.default_rng(seed)
    x = rng.uniform(-320, 320, points)
    z = rng.normal(0, 25, points)
    angles = np.radians(true_tilt_deg)
    offsets = rng.normal(0, 2, len(angles))
    seen = np.stack([x * np.cos(a) + z * np.sin(a) + o for a, o in zip(angles, offsets)])
    disparities = seen - seen[0] + rng.normal(0, noise_px, seen.shape)
    return x, z, seen[0], disparities


@pytest.mark.parametrize("nominal", [(-5.3, 0.4, 4.6), (-5.0, 0.5, 5.5), (-4.5, -0.5, 5.0)])
def test_tilt_differences_are_recovered_from_wrong_nominal_angles(nominal):
    true = np.array([-5.0, 0.0, 5.0])
    _, _, seen_first, disparities = _views(true)
    estimate = tilt_series.estimate_tilts(seen_first, disparities, nominal)
    assert estimate.tilt_deg[0] == nominal[0]  # the reference keeps its tilt: only differences are observable
    assert np.abs(np.diff(estimate.tilt_deg) - np.diff(true)).max() < 0.01
    assert 0 < estimate.sigma_deg[1] < 0.01 and estimate.residual_px == pytest.approx(0.05 / np.sqrt(2), rel=0.3)


@pytest.mark.parametrize("true", [(-3.0, 0.0, 3.0), (-6.0, 0.0, 6.0)])
def test_a_magnification_error_moves_the_tilts_by_its_sigma_term(true):
    """A view 1e-4 too large adds 1e-4·x to its disparities, as a change of cos t would; the
    sigma's magnification term predicts the tilt error that causes, and dwarfs the fit's own."""
    epsilon = 1e-4
    true = np.array(true)
    _, _, seen_first, disparities = _views(true, noise_px=0.0)
    clean = tilt_series.estimate_tilts(seen_first, disparities, true, magnification_sigma=[0.0, 0.0, epsilon])
    disparities[2] += epsilon * seen_first
    moved = tilt_series.estimate_tilts(seen_first, disparities, true)
    shift_deg = np.abs(moved.tilt_deg - true)
    assert shift_deg[2] > 10 * moved.sigma_deg[2]  # the fit alone does not see it
    assert shift_deg[2] == pytest.approx(clean.sigma_deg[2], rel=0.05)
    assert shift_deg[1] == pytest.approx(clean.sigma_deg[1], rel=0.05, abs=1e-6)


def test_errors_shared_within_blocks_are_covered_by_the_cluster_robust_sigma():
    """Matching errors correlate over a window and more: points of one block share theirs. Taken
    for independent the points claim a sigma that the tilts miss by far (both within two sigmas
    in 2 of 40 trials); with the blocks as the independent samples they mostly fall within it
    (measured 33 of 40: the sigma is still about 1.6 times small on these 64 blocks, see
    `tilt_series._jackknife_sigma`)."""
    true = np.array([-5.0, 0.0, 5.0])
    within = {"independent": 0, "blocks": 0}
    trials = 40
    for seed in range(trials):
        rng = np.random.default_rng(seed)
        x, _, seen_first, disparities = _views(true, noise_px=0.02, points=4000, seed=seed)
        y = rng.uniform(-320, 320, x.size)
        block = (np.floor((x + 320) / 80) * 8 + np.floor((y + 320) / 80)).astype(int)  # 8 x 8 blocks
        disparities = disparities + rng.normal(0, 0.3, (len(true), 64))[:, block]
        for name, cluster in (("independent", None), ("blocks", block)):
            estimate = tilt_series.estimate_tilts(seen_first, disparities, true, cluster=cluster)
            within[name] += bool(np.all(np.abs(estimate.tilt_deg - true) <= 2 * estimate.sigma_deg))
    assert within["independent"] < 0.25 * trials
    assert within["blocks"] >= 0.75 * trials


def test_two_views_reduce_to_the_pair_formula():
    tilts = (-4.0, 6.0)
    _, _, seen_first, disparities = _views(np.array(tilts), noise_px=0.0)
    z_px, _ = tilt_series.heights_px(seen_first, disparities, tilts)
    t1, t2 = np.radians(tilts)
    pair = ((seen_first + disparities[1]) * np.cos(t1) - seen_first * np.cos(t2)) / np.sin(
        t2 - t1
    )  # z = (x2 cos t1 - x1 cos t2) / sin(t2 - t1)
    assert np.allclose(z_px - z_px.mean(), pair - pair.mean(), atol=1e-9)


def test_two_views_cannot_be_calibrated():
    _, _, seen_first, disparities = _views(np.array([-5.0, 5.0]))
    with pytest.raises(ValueError, match="three or more"):
        tilt_series.estimate_tilts(seen_first, disparities, (-5.0, 5.0))


@pytest.mark.slow
def test_three_synthetic_sem_views_with_wrong_nominal_tilts():
    """-5/0/+5 degree views of a known surface; the nominal tilts are off by up to 0.5 degree."""
    from fractoscope import synthetic
    from fractoscope.sem.image import SemImage
    from fractoscope.stereo.inputs import MatchingOptions
    from fractoscope.stereo.pipeline import compute_series_height_map

    true = (-5.0, 0.0, 5.0)
    surface = synthetic.self_affine_surface((704, 704), hurst=0.8, rms_um=2.5, seed=5)
    images, truth = synthetic.render_tilt_series(
        surface, pixel_size_um=0.1, tilt_deg=true, output_shape=(640, 640), seed=5
    )
    views = [SemImage(image, None, 0.1, 0) for image in images]
    nominal = (-5.0, 0.5, 5.5)  # both tilt steps read 10 % large, as a stage readout may
    wrong = compute_series_height_map(views, tilt_deg=nominal)
    calibrated = compute_series_height_map(views, tilt_deg=nominal, options=MatchingOptions(calibrate_tilt=True))

    report = calibrated.report
    assert np.abs(np.diff(report["tilt_deg"]) - np.diff(true)).max() < 0.05
    assert report["tilt_deg_nominal"] == list(nominal) and max(report["tilt_sigma_deg"]) < 0.1
    # The sigma is honest: it covers the actual errors (the fit's own, which assumes independent
    # errors, was 5 to 10 times smaller than them before the magnification term).
    errors = np.abs(np.array(report["tilt_deg"]) - true)[1:]
    assert np.all(errors < 2 * np.array(report["tilt_sigma_deg"])[1:])

    def scale_and_rms_percent(z_um):
        known = np.isfinite(z_um)
        rows, cols = np.nonzero(known)
        design = np.column_stack([truth[known], rows, cols, np.ones(known.sum())])
        fit, *_ = np.linalg.lstsq(design, z_um[known], rcond=None)
        design_plane = design[:, 1:]
        error = z_um[known] - truth[known]
        error -= design_plane @ np.linalg.lstsq(design_plane, error, rcond=None)[0]  # the frame's tilt is unobservable
        return fit[0], 100 * np.sqrt(np.mean(error**2)) / np.ptp(truth)

    wrong_scale, _ = scale_and_rms_percent(wrong.z_um)
    scale, rms_percent = scale_and_rms_percent(calibrated.z_um)
    assert abs(wrong_scale - 1) > 0.05  # the nominal tilts make every height ~6 % wrong
    assert abs(scale - 1) < 0.01
    assert rms_percent < 1.5


@pytest.mark.slow
@pytest.mark.parametrize(
    "true_axis_deg, given_axis_deg, rotation_deg, warned",
    [
        (60.0, 60.0, 0.0, False),
        (60.0, 64.0, 0.0, True),
        (90.0, 85.5, 0.0, True),
        (90.0, 90.0, 3.0, False),
        (80.0, 80.0, -3.0, False),
    ],
)
def test_tilt_axis_is_estimated_from_the_parallax_and_a_wrong_one_is_flagged(
    true_axis_deg, given_axis_deg, rotation_deg, warned
):
    """A second view turned by the stage (3°, which the principal direction of the displacements
    once took for an axis 22° off) is no wrong axis."""
    from conftest import fracture_pair

    from fractoscope.sem.image import SemImage
    from fractoscope.stereo.pipeline import compute_height_map

    pair = fracture_pair(tilt_axis_deg=true_axis_deg, rotation_deg=rotation_deg, seed=2)
    result = compute_height_map(
        SemImage(pair.first, None, None, 0),
        SemImage(pair.second, None, None, 0),
        tilt_deg=(-5, 5),
        pixel_size_um=0.1,
        tilt_axis_deg=given_axis_deg,
    )
    assert result.report["tilt_axis_deg_estimated"] == pytest.approx(true_axis_deg, abs=1.0)
    assert bool(result.report["warnings"]) == warned


@pytest.mark.slow
@pytest.mark.parametrize("third", ["the first again", "noise"])
def test_a_view_that_is_not_the_area_tilted_as_stated_is_refused_by_name(third):
    """Calibration mends tilts a few percent off; a third view that repeats the first (zero
    parallax for a 12° step, which the fit once turned into a tilt of 172 ± 7948° and heights of
    -9e5 µm) or shows nothing of it is an INVALID_ARGUMENT naming that view (with the first one
    when the fit moved both), not a result; the views in their right order pass."""
    from fractoscope import synthetic
    from fractoscope.errors import InvalidInputError
    from fractoscope.sem.image import SemImage
    from fractoscope.stereo.inputs import MatchingOptions
    from fractoscope.stereo.pipeline import compute_series_height_map

    surface = synthetic.self_affine_surface((384, 384), hurst=0.8, rms_um=2.5, seed=5)
    images, _ = synthetic.render_tilt_series(
        surface, pixel_size_um=0.1, tilt_deg=(-6.0, 0.0, 6.0), output_shape=(320, 320), seed=5
    )
    noise = np.random.default_rng(0).integers(0, 256, images[0].shape, dtype=np.uint8)
    views = [
        SemImage(image, None, 0.1, 0)
        for image in (images[0], images[1], images[0] if third == "the first again" else noise)
    ]
    with pytest.raises(InvalidInputError) as refused:
        compute_series_height_map(views, tilt_deg=(-6.0, 0.0, 6.0), options=MatchingOptions(calibrate_tilt=True))
    assert refused.value.field.startswith(("images[2]", "images")) and "images[2]" in str(refused.value)
    good = compute_series_height_map(
        [SemImage(image, None, 0.1, 0) for image in images],
        tilt_deg=(-6.0, 0.0, 6.0),
        options=MatchingOptions(calibrate_tilt=True),
    )
    assert np.abs(np.array(good.report["tilt_deg"]) - (-6.0, 0.0, 6.0)).max() < 0.5


def test_unknown_magnification_uncertainty_keeps_sigma_and_warns(monkeypatch):
    """When a view's magnification can be measured neither on the matched images nor from SIFT
    features (a featureless view), the calibrated tilts' sigma is unknown: the report says NaN
    and warns, and sigma_um falls back to the nominal tilt uncertainty instead of turning NaN."""
    import dataclasses

    from fractoscope import synthetic
    from fractoscope.sem.image import SemImage
    from fractoscope.stereo import alignment
    from fractoscope.stereo.inputs import MatchingOptions
    from fractoscope.stereo.pipeline import compute_series_height_map

    true = (-5.0, 0.0, 5.0)
    surface = synthetic.self_affine_surface((384, 384), hurst=0.8, rms_um=2.5, seed=5)
    images, _ = synthetic.render_tilt_series(surface, pixel_size_um=0.1, tilt_deg=true, output_shape=(320, 320), seed=5)
    views = [SemImage(image, None, 0.1, 0) for image in images]
    featureless = alignment.estimate_alignment
    monkeypatch.setattr(
        alignment,
        "estimate_alignment",
        lambda *a, **k: dataclasses.replace(featureless(*a, **k), scale_sigma=float("nan")),
    )
    monkeypatch.setattr(alignment, "residual_misplacement", lambda *a, **k: None)
    result = compute_series_height_map(views, tilt_deg=true, options=MatchingOptions(calibrate_tilt=True))

    assert np.isnan(result.report["tilt_sigma_deg"][1:]).all()
    assert any("uncertainty is unknown" in warning for warning in result.report["warnings"])
    # The reference keeps the given tilt; the others are the calibration's, the pixel size the file's.
    assert result.report["tilt_source"] == ["argument", "tilt_calibration", "tilt_calibration"]
    assert result.report["pixel_size_source"] == "metadata" and result.report["parameters"]["calibrate_tilt"]
    known = np.isfinite(result.z_um)
    assert known.mean() > 0.9 and np.isfinite(result.sigma_um[known]).all()


@pytest.mark.slow
def test_a_series_whose_views_disagree_with_their_tilts_is_flagged_without_calibration():
    """-5/0/+5° views with the first repeated as the third: the heights came out at a fifth of
    the relief with no word; the views' misses now draw a warning, and a consistent series none."""
    from fractoscope import synthetic
    from fractoscope.sem.image import SemImage
    from fractoscope.stereo.pipeline import compute_series_height_map

    surface = synthetic.self_affine_surface((384, 384), hurst=0.8, rms_um=2.5, seed=5)
    images, _ = synthetic.render_tilt_series(
        surface, pixel_size_um=0.1, tilt_deg=(-5.0, 0.0, 5.0), output_shape=(320, 320), seed=5
    )
    consistent = compute_series_height_map(
        [SemImage(image, None, 0.1, 0) for image in images], tilt_deg=(-5.0, 0.0, 5.0)
    )
    repeated = compute_series_height_map(
        [SemImage(images[i], None, 0.1, 0) for i in (0, 1, 0)], tilt_deg=(-5.0, 0.0, 5.0)
    )
    assert not any("disagree" in warning for warning in consistent.report["warnings"])
    assert any(
        "views disagree with their tilts" in warning and "images[2]" in warning
        for warning in repeated.report["warnings"]
    )

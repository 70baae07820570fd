"""The relief's sign from occlusion (issue 46, item 2): geometry alone, no detector. Rounded
particles tell it for either sign of the tilt step and say when the tilts were given reversed;
sharp steps, whose mirror image is an equally good explanation of the pair, and fracture surfaces
without steep walls stay undecided."""

import numpy as np
import pytest

from fractoscope import synthetic
from fractoscope.stereo import matching, occlusion
from fractoscope.synthetic.physics import material_contrast

PIXEL_SIZE_UM = 0.1
TEXTURE_ONLY = synthetic.PHYSICS_VARIANTS["texture_only"]


def _votes(kind: str, tilt_deg, size_px: int, seed: int) -> np.ndarray:
    pair = synthetic.render_surface_pair(kind, size_px, tilt_deg=tilt_deg, seed=seed, physics=TEXTURE_ONLY)
    first, second = pair.first.astype(np.float32), pair.second.astype(np.float32)
    matched = matching.match_disparity(first, second, max_disparity_px=size_px // 4, method="window_zncc")
    return occlusion.wall_votes(first, second, matched.disparity_px)


@pytest.mark.slow
@pytest.mark.parametrize("tilt_deg", [(-5.0, 5.0), (5.0, -5.0)])
def test_rounded_particles_tell_the_relief_from_its_mirror_image_for_either_tilt_step(tilt_deg):
    votes = _votes("particles", tilt_deg, 512, seed=2)
    step = np.sign(tilt_deg[1] - tilt_deg[0])
    as_rendered = occlusion.verdict(votes, tilt_step_sign=step)
    reversed_ = occlusion.verdict(votes, tilt_step_sign=-step)
    assert as_rendered.decided and not as_rendered.inverted and as_rendered.cue == "occlusion"
    assert as_rendered.strength > 0.8 and as_rendered.blocks >= 11
    assert reversed_.decided and reversed_.inverted and reversed_.strength < -0.8


@pytest.mark.slow
@pytest.mark.parametrize(
    ("kind", "tilt_deg"), [("sharp_steps", (0.0, 5.0)), ("sharp_steps", (5.0, -5.0)), ("self_affine", (-5.0, 5.0))]
)
def test_sharp_steps_and_fracture_surfaces_stay_undecided(kind, tilt_deg):
    votes = _votes(kind, tilt_deg, 384, seed=3)
    step = np.sign(tilt_deg[1] - tilt_deg[0])
    assert not occlusion.verdict(votes, tilt_step_sign=step).decided
    assert not occlusion.verdict(votes, tilt_step_sign=-step).decided


def test_a_sharp_step_and_its_mirror_image_give_the_same_pair():
    """The random-dot stereogram argument: a step up at (0°, t) and, at (0°, -t), a step down moved
    by its height times tan t render the same pair, but for the column the wall is drawn in."""
    size_px, height_um = 256, 10.0
    tilt_deg = float(np.degrees(np.arctan(0.09)))  # the wall moves by 9 px
    columns = np.arange(size_px + 64)
    rows = np.ones((size_px + 64, 1))
    raised = np.where(columns < 160, height_um, 0.0) * rows
    mirrored = np.where(columns < 169, -height_um, 0.0) * rows
    # The material belongs to the plane, not to the relief: both readings of the pair carry it.
    material = material_contrast((2 * (size_px + 64),) * 2, TEXTURE_ONLY, seed=3)[::2, ::2].copy()
    settings = dict(
        pixel_size_um=PIXEL_SIZE_UM,
        output_shape=(size_px, size_px),
        noise_fraction=0.0,
        material=material,
        physics=TEXTURE_ONLY,
    )
    up = synthetic.render_stereo_pair(raised, tilt_deg=(0.0, tilt_deg), **settings)
    down = synthetic.render_stereo_pair(mirrored, tilt_deg=(0.0, -tilt_deg), **settings)
    np.testing.assert_array_equal(up.first, down.first)
    differing = np.abs(up.second.astype(int) - down.second.astype(int)) > 1
    assert 0 < differing.sum() <= 2 * size_px and np.ptp(np.nonzero(differing)[1]) <= 3
    # The truths differ: the first reading's surface is the second's negated, shifted by 9 px.
    assert up.z_seen_um.max() == pytest.approx(height_um, abs=0.5)
    assert down.z_seen_um.min() == pytest.approx(-height_um, abs=0.5)


def test_the_votes_turn_round_with_the_pair_seen_from_behind():
    """Columns reversed, a positive tilt step reads as a negative one: every wall's vote changes
    sign, and nothing else does (the procedure has no preferred direction)."""
    pair = synthetic.render_surface_pair("particles", 256, tilt_deg=(-5.0, 5.0), seed=4, physics=TEXTURE_ONLY)
    first, second = pair.first.astype(np.float32), pair.second.astype(np.float32)
    disparity = matching.match_disparity(first, second, max_disparity_px=64, method="window_zncc")
    votes = occlusion.wall_votes(first, second, disparity.disparity_px)
    flipped = occlusion.wall_votes(first[:, ::-1], second[:, ::-1], -disparity.disparity_px[:, ::-1])
    assert sum(len(view) for view in votes) > 0 and all(np.all(view > 0) for view in votes)
    for view, turned in zip(votes, flipped):
        assert sorted(turned) == sorted(-view)


def test_the_second_views_disparities_invert_the_firsts():
    columns = np.arange(64, dtype=np.float64)
    disparity = np.tile(3.0 + 0.1 * columns, (2, 1))
    disparity[1, 30:40] = np.nan
    inverted = occlusion.inverted_disparity(disparity)
    # The first's column c lies at u = 3 + 1.1 c in the second, whose disparity back is c - u.
    u = np.arange(64)[np.isfinite(inverted[0])]
    np.testing.assert_allclose(inverted[0, u], (u - 3.0) / 1.1 - u, atol=1e-9)
    assert np.isnan(inverted[1, 37:46]).all() and np.isfinite(inverted[1, 3:35]).all()


def test_the_two_views_contours_must_agree():
    """Twelve walls agreeing at one view's contours and none at the other's decide nothing: a
    photometric effect of one view's incidence could have made them."""
    one_sided = (np.ones(12, np.int8), np.zeros(0, np.int8))
    both = (np.ones(10, np.int8), np.array([1] * 9 + [-1], np.int8))
    assert not occlusion.verdict(one_sided, tilt_step_sign=1.0).decided
    assert "do not agree" in occlusion.verdict(one_sided, tilt_step_sign=1.0).reason
    told = occlusion.verdict(both, tilt_step_sign=-1.0)
    assert told.decided and told.inverted and told.blocks == 20


def test_no_tilt_step_or_mismatched_arrays_are_refused_plainly():
    votes = (np.ones(10, np.int8), np.ones(10, np.int8))
    assert not occlusion.verdict(votes, tilt_step_sign=0.0).decided
    assert occlusion.verdict(votes, tilt_step_sign=float("nan")).reason
    with pytest.raises(ValueError, match="one shape"):
        occlusion.relief_sign_from_occlusion(np.zeros((4, 4)), np.zeros((4, 5)), np.zeros((4, 4)), tilt_step_sign=1.0)

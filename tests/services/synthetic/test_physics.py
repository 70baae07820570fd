"""The renderer's configurable physics (synthetic.physics): yield laws, edge contrast, detector."""

import numpy as np
import pytest

from fractoscope import synthetic
from fractoscope.synthetic import physics

PIXEL_UM = 0.1


def _plane(slope_cols: float, shape=(32, 48)) -> np.ndarray:
    """Heights (µm) of a plane rising by `slope_cols` µm per µm along the columns."""
    return np.broadcast_to(slope_cols * PIXEL_UM * np.arange(shape[1], dtype=np.float64), shape).copy()


def _signal(z_um, law_physics, tilt_deg):
    material = np.zeros_like(z_um)
    return physics.secondary_electron_yield(z_um, PIXEL_UM, np.radians(tilt_deg), material, law_physics)[8:-8, 8:-8]


@pytest.mark.parametrize(
    ("law", "expected"),
    [
        ("secant", lambda c: 0.3 + 0.7 / c**1.5),
        ("lambert", lambda c: 0.3 + 0.7 * c**1.5),
        ("tanh", lambda c: 0.3 + 0.7 * (1.0 + np.tanh(1.5 * (1.0 / c - 1.0)))),
        ("none", lambda c: 1.0),
    ],
)
def test_each_yield_law_gives_its_formula_of_the_incidence_on_a_plane(law, expected):
    law_physics = synthetic.SemPhysics(yield_law=law, yield_exponent=1.5, se2_fraction=0.3, detector_strength=0.0)
    slope, tilt_deg = 0.6, 5.0
    # The beam (-sin t, 0, cos t) against the normal (-p, 0, 1) / sqrt(1 + p²).
    cos_incidence = (np.cos(np.radians(tilt_deg)) + slope * np.sin(np.radians(tilt_deg))) / np.hypot(1.0, slope)
    signal = _signal(_plane(slope), law_physics, tilt_deg)
    np.testing.assert_allclose(signal, expected(cos_incidence), rtol=1e-9)


def test_a_detector_on_the_specimen_lights_both_views_alike_and_one_in_the_chamber_does_not():
    """Facets facing the detector (towards the right of the image) are brighter; with the detector
    in the chamber the stage's tilt turns it, so the two views see that lighting differently."""
    plane = _plane(-0.5)  # falls to the right: its normal leans to the right, towards the detector
    common = dict(yield_law="none", detector_azimuth_deg=0.0, detector_elevation_deg=30.0, detector_strength=0.6)
    on_specimen = synthetic.SemPhysics(**common)
    in_chamber = synthetic.SemPhysics(**common, detector_in_chamber=True)
    assert _signal(plane, on_specimen, 0.0).mean() > _signal(_plane(0.5), on_specimen, 0.0).mean() + 0.2
    assert np.allclose(_signal(plane, on_specimen, -5.0), _signal(plane, on_specimen, 5.0))
    left, right = _signal(plane, in_chamber, -5.0), _signal(plane, in_chamber, 5.0)
    # In the specimen's frame a tilt t raises the detector to 30° + t; the normal leans 26.6° towards it.
    normal_deg = np.degrees(np.arctan(0.5))
    facing = [np.cos(np.radians(90.0 - normal_deg - (30.0 + t))) for t in (-5.0, 5.0)]
    np.testing.assert_allclose([left.mean(), right.mean()], [0.4 + 0.6 * f for f in facing], rtol=1e-9)


def test_edge_contrast_brightens_convex_ridges_and_leaves_valleys():
    columns = np.arange(64, dtype=np.float64)
    ridge = np.broadcast_to(-0.1 * np.abs(columns - 32.0), (40, 64)).copy()  # µm, a sharp crest
    edged = synthetic.SemPhysics(yield_law="none", detector_strength=0.0, edge_contrast=0.8)
    crest, valley = _signal(ridge, edged, 0.0), _signal(-ridge, edged, 0.0)
    assert crest[:, 24].max() > 1.3 and np.allclose(crest[:, :10], 1.0)  # flanks 14 px off stay as they were
    assert np.allclose(valley[:, 2:-2], 1.0)  # (the edges of the array are mirrored, so convex there)


def test_variants_render_other_images_than_the_default_and_bad_physics_is_refused():
    surface = synthetic.reference_surface("dimples", 128, seed=3)
    render = dict(pixel_size_um=PIXEL_UM, tilt_deg=5.0, seed=2)
    default = synthetic.render_sem_view(surface, **render).image
    assert np.array_equal(default, synthetic.render_sem_view(surface, **render, physics=synthetic.SemPhysics()).image)
    assert len(synthetic.PHYSICS_VARIANTS) >= 4
    for variant in synthetic.PHYSICS_VARIANTS.values():
        image = synthetic.render_sem_view(surface, **render, physics=variant).image
        assert np.mean(np.abs(image.astype(float) - default)) > 5.0
    with pytest.raises(ValueError, match="yield_law"):
        synthetic.SemPhysics(yield_law="cosine")
    with pytest.raises(ValueError, match="se2_fraction"):
        synthetic.SemPhysics(se2_fraction=1.5)

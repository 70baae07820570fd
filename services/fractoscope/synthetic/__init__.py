"""Synthetic fracture surfaces and the SEM images they give: the known truth for tests, benchmarks
and the demo. `surfaces` makes height fields, `rendering` the SEM views of them, `metrics` scores
a measured height map against the truth, `examples` writes the demo specimen as a user gives it;
`physics` says how a surface makes an image (the default renderer and its variants); `textures`
gives flat textured specimens seen displaced by a known amount."""

from fractoscope.synthetic.metrics import HeightErrors, height_errors, hidden_in_second_view
from fractoscope.synthetic.physics import DEFAULT_PHYSICS, PHYSICS_VARIANTS, SemPhysics
from fractoscope.synthetic.rendering import (
    MultiscaleSpecimen,
    RenderedView,
    StereoPair,
    render_multiscale_specimen,
    render_sem_view,
    render_stereo_pair,
    render_surface_pair,
    render_tilt_series,
)
from fractoscope.synthetic.surfaces import (
    OVERVIEW_PIXEL_SIZE_UM,
    REFERENCE_PIXEL_SIZE_UM,
    REFERENCE_SURFACES,
    WALL_MORPHOLOGIES,
    cleavage_surface,
    dimple_surface,
    overview_dimple_surface,
    reference_surface,
    self_affine_surface,
    surface,
    wall_surface,
)
from fractoscope.synthetic.textures import displaced_pair, sem_texture, shifted_texture_pair, speckle_texture

__all__ = [
    "DEFAULT_PHYSICS",
    "HeightErrors",
    "MultiscaleSpecimen",
    "OVERVIEW_PIXEL_SIZE_UM",
    "PHYSICS_VARIANTS",
    "REFERENCE_PIXEL_SIZE_UM",
    "REFERENCE_SURFACES",
    "RenderedView",
    "SemPhysics",
    "StereoPair",
    "cleavage_surface",
    "dimple_surface",
    "displaced_pair",
    "height_errors",
    "hidden_in_second_view",
    "reference_surface",
    "render_multiscale_specimen",
    "overview_dimple_surface",
    "render_sem_view",
    "render_stereo_pair",
    "render_surface_pair",
    "render_tilt_series",
    "self_affine_surface",
    "sem_texture",
    "shifted_texture_pair",
    "speckle_texture",
    "surface",
    "WALL_MORPHOLOGIES",
    "wall_surface",
]

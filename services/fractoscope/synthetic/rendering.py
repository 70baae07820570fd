"""The SEM images a known surface gives: single views, stereo pairs, tilt series and a
multi-scale specimen.

Surfaces are (rows, cols) float64 height fields in micrometres on a square grid of
`pixel_size_um` (see surfaces). Images are rendered by parallel projection at a stage tilt about the vertical
(column) axis through the image centre: a surface point at column offset x (pixels from the centre
column) and height z appears at column offset ``x cos t + (z / pixel_size) sin t``. Contrast follows
`physics`: by default the secondary-electron secant law of the beam incidence angle, lit by a side
detector, plus a weak material contrast; other yield laws, edge contrast, detectors and textures
are `physics.PHYSICS_VARIANTS`. Gaussian noise on top.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from fractoscope.synthetic.physics import DEFAULT_PHYSICS, SemPhysics, material_contrast, secondary_electron_yield
from fractoscope.synthetic.surfaces import REFERENCE_PIXEL_SIZE_UM, self_affine_surface, surface

_SUPERSAMPLING = 2


@dataclass(frozen=True)
class RenderedView:
    """One rendered SEM view.

    image: (rows, cols) uint8 or uint16 grey image.
    z_seen_um: (rows, cols) float64, height of the surface point seen at each pixel, µm.
    """

    image: np.ndarray
    z_seen_um: np.ndarray


def render_sem_view(
    z_um: np.ndarray,
    *,
    pixel_size_um: float,
    tilt_deg: float,
    noise_fraction: float = 0.02,
    seed: int = 0,
    material_seed: int = 0,
    material: np.ndarray | None = None,
    bits: int = 8,
    shading_tilt_deg: float | None = None,
    physics: SemPhysics = DEFAULT_PHYSICS,
) -> RenderedView:
    """Renders `z_um` (rows, cols, µm) seen at stage tilt `tilt_deg` about the vertical axis.

    Gaussian noise (drawn from `seed`, so different per view) has a standard deviation of
    `noise_fraction` of the image's grey range; the material contrast belongs to the surface and
    comes from `material` (relative yield change, same grid as `z_um`) or else is drawn from
    `material_seed`; all views of one surface must share it. The secondary-electron shading
    depends on the beam's incidence, so on the tilt, as in a microscope; a `shading_tilt_deg`
    given for every view instead makes it a fixed property of the surface like the material
    contrast, which tells how much of a matching error that dependence causes. `physics`: the
    yield law, edge contrast, detector and the drawn material contrast's spectrum.
    """
    # Render on a finer grid and average down: the finite probe blurs detail below one pixel.
    fine_um = cv2.resize(z_um, None, fx=_SUPERSAMPLING, fy=_SUPERSAMPLING, interpolation=cv2.INTER_CUBIC)
    fine_pixel_um = pixel_size_um / _SUPERSAMPLING
    rows, cols = fine_um.shape
    tilt_rad = np.radians(tilt_deg)
    if material is None:
        fine_material = material_contrast(fine_um.shape, physics, seed=material_seed)
    else:
        fine_material = cv2.resize(material, None, fx=_SUPERSAMPLING, fy=_SUPERSAMPLING, interpolation=cv2.INTER_CUBIC)
    shading_rad = tilt_rad if shading_tilt_deg is None else np.radians(shading_tilt_deg)
    shading = secondary_electron_yield(fine_um, fine_pixel_um, shading_rad, fine_material, physics)
    x_px = np.arange(cols) - (cols - 1) / 2.0
    projected = x_px[None, :] * np.cos(tilt_rad) + fine_um / fine_pixel_um * np.sin(tilt_rad)
    projected = visible_sheet_px(projected, tilt_rad)
    image = np.empty((rows, cols))
    z_seen_um = np.empty((rows, cols))
    for row in range(rows):
        source_x = np.interp(x_px, projected[row], x_px)
        image[row] = np.interp(source_x, x_px, shading[row])
        z_seen_um[row] = np.interp(source_x, x_px, fine_um[row])
    image = cv2.resize(image, z_um.shape[::-1], interpolation=cv2.INTER_AREA)
    z_seen_um = cv2.resize(z_seen_um, z_um.shape[::-1], interpolation=cv2.INTER_AREA)
    rng = np.random.default_rng(seed)
    low, high = np.percentile(image, [0.5, 99.5])
    image = (image - low) / (high - low)
    image += rng.normal(0.0, noise_fraction, image.shape)
    full_scale = 2**bits - 1
    grey = np.clip(0.1 + 0.8 * image, 0.0, 1.0) * full_scale
    return RenderedView(np.round(grey).astype(np.uint8 if bits == 8 else np.uint16), z_seen_um)


def visible_sheet_px(projected_px: np.ndarray, tilt_rad: float) -> np.ndarray:
    """Image positions (rows, cols) of a surface's points along each row, x cos t + z sin t, with
    the hidden ones folded onto the point that hides them: at each image position the viewer sees
    the crossing nearest to it, the leftmost one for t > 0 (a higher point appears further right
    and hides what lies right of it) and the rightmost one for t < 0."""
    if tilt_rad >= 0.0:
        return np.maximum.accumulate(projected_px, axis=1)
    return np.minimum.accumulate(projected_px[:, ::-1], axis=1)[:, ::-1]


@dataclass(frozen=True)
class StereoPair:
    """A rendered pair: both images (rows, cols) and the truth on the first image's grid, µm."""

    first: np.ndarray
    second: np.ndarray
    z_seen_um: np.ndarray


def render_stereo_pair(
    z_um: np.ndarray,
    *,
    pixel_size_um: float,
    tilt_deg: tuple[float, float],
    output_shape: tuple[int, int],
    tilt_axis_deg: float = 90.0,
    second_shift_px: tuple[float, float] = (0.0, 0.0),
    second_rotation_deg: float = 0.0,
    noise_fraction: float = 0.02,
    seed: int = 0,
    material: np.ndarray | None = None,
    bits: int = 8,
    shading_tilt_deg: float | None = None,
    physics: SemPhysics = DEFAULT_PHYSICS,
) -> StereoPair:
    """Renders `z_um` at both tilts about an axis at `tilt_axis_deg` in the image (counter-clockwise
    from the column axis as displayed), then misplaces the second image by a rotation about its
    centre and a (column, row) shift, as an imperfect stage does. `z_um` must be larger than
    `output_shape` to leave room for the rotation; the centre of the canvas is kept. See
    `render_sem_view` for `shading_tilt_deg` and `physics`."""
    views = [
        render_sem_view(
            z_um,
            pixel_size_um=pixel_size_um,
            tilt_deg=t,
            noise_fraction=noise_fraction,
            seed=seed + i,
            material=material,
            bits=bits,
            shading_tilt_deg=shading_tilt_deg,
            physics=physics,
        )
        for i, t in enumerate(tilt_deg)
    ]
    rows, cols = z_um.shape
    centre = ((cols - 1) / 2.0, (rows - 1) / 2.0)
    to_image = cv2.getRotationMatrix2D(centre, tilt_axis_deg - 90.0, 1.0)
    misplace = cv2.getRotationMatrix2D(centre, second_rotation_deg, 1.0)
    misplace[:, 2] += second_shift_px
    out_rows, out_cols = output_shape
    top, left = (rows - out_rows) // 2, (cols - out_cols) // 2

    def place(values: np.ndarray, extra: np.ndarray | None = None) -> np.ndarray:
        placed = cv2.warpAffine(values.astype(np.float32), to_image, (cols, rows), flags=cv2.INTER_LINEAR)
        if extra is not None:
            placed = cv2.warpAffine(placed, extra, (cols, rows), flags=cv2.INTER_LINEAR)
        return placed[top : top + out_rows, left : left + out_cols]

    dtype = views[0].image.dtype
    first = np.round(place(views[0].image)).astype(dtype)
    second = np.round(place(views[1].image, misplace)).astype(dtype)
    return StereoPair(first, second, place(views[0].z_seen_um).astype(np.float64))


def render_surface_pair(kind: str, size_px: int, *, tilt_deg: tuple[float, float], seed: int, **render) -> StereoPair:
    """`surfaces.surface(kind)` of seed `seed` (on a canvas 64 px larger) rendered as a pair of
    (size_px, size_px) at REFERENCE_PIXEL_SIZE_UM and `tilt_deg`, its noise drawn from `seed`;
    `render`: more of render_stereo_pair's settings."""
    return render_stereo_pair(
        surface(kind, size_px + 64, seed=seed),
        pixel_size_um=REFERENCE_PIXEL_SIZE_UM,
        tilt_deg=tilt_deg,
        output_shape=(size_px, size_px),
        seed=seed,
        **render,
    )


@dataclass(frozen=True)
class MultiscaleSpecimen:
    """An overview pair and a higher-magnification ROI pair of one known surface.

    The truths are heights seen at each pixel of each first image, µm. `roi_origin_px` is where the
    ROI's first-image pixel (0, 0) appears in the overview's first image, (col, row) overview pixels.
    """

    overview: StereoPair
    roi: StereoPair
    overview_pixel_size_um: float
    roi_pixel_size_um: float
    roi_origin_px: tuple[float, float]
    tilt_deg: tuple[float, float]


def render_multiscale_specimen(
    *,
    overview_shape: tuple[int, int] = (512, 512),
    roi_shape: tuple[int, int] = (512, 512),
    zoom: int = 4,
    roi_centre_px: tuple[float, float] = (300.0, 220.0),
    pixel_size_um: float = 1.0,
    rms_um: float = 25.0,
    tilt_deg: tuple[float, float] = (-5.0, 5.0),
    seed: int = 0,
) -> MultiscaleSpecimen:
    """Renders a self-affine fracture surface (H = 0.8) as an overview pair at `pixel_size_um` and
    an ROI pair `zoom` times finer centred on `roi_centre_px` (col, row) of the overview. The ROI
    sees the overview's surface (upsampled) plus detail finer than 4 overview pixels."""
    margin = 32
    canvas = (overview_shape[0] + 2 * margin, overview_shape[1] + 2 * margin)
    coarse_um = self_affine_surface(canvas, hurst=0.8, rms_um=rms_um, seed=seed)
    # Material contrast belongs to the specimen, so both magnifications see the same pattern.
    coarse_material = self_affine_surface(canvas, hurst=0.3, rms_um=0.15, seed=seed + 2, min_wavelength_px=2.0)
    overview = render_stereo_pair(
        coarse_um,
        pixel_size_um=pixel_size_um,
        tilt_deg=tilt_deg,
        output_shape=overview_shape,
        seed=seed + 10,
        material=coarse_material,
    )
    fine_canvas = (roi_shape[0] + 2 * margin, roi_shape[1] + 2 * margin)
    centre_col, centre_row = roi_centre_px[0] + margin, roi_centre_px[1] + margin
    upsampled, fine_material = _zoomed_in((coarse_um, coarse_material), fine_canvas, (centre_col, centre_row), zoom)
    # The self-affine spectrum continued below 4 overview pixels: RMS scales as wavelength^H.
    detail = self_affine_surface(
        fine_canvas, hurst=0.8, rms_um=rms_um * (4.0 / max(canvas)) ** 0.8, seed=seed + 1, max_wavelength_px=4.0 * zoom
    )
    fine_material += self_affine_surface(
        fine_canvas, hurst=0.3, rms_um=0.05, seed=seed + 3, max_wavelength_px=2.0 * zoom
    )
    roi = render_stereo_pair(
        upsampled.astype(np.float64) + detail,
        pixel_size_um=pixel_size_um / zoom,
        tilt_deg=tilt_deg,
        output_shape=roi_shape,
        seed=seed + 30,
        material=fine_material.astype(np.float64),
    )
    origin_col = centre_col + (margin - (fine_canvas[1] - 1) / 2) / zoom - margin
    origin_row = centre_row + (margin - (fine_canvas[0] - 1) / 2) / zoom - margin
    # Parallel projection shrinks x by cos(tilt) about each rendering's own centre, which shifts
    # the ROI's picture by (overview centre - ROI centre)(1 - cos t1) in the overview's image.
    shrink = 1.0 - np.cos(np.radians(tilt_deg[0]))
    origin_col += ((canvas[1] - 1) / 2 - centre_col) * shrink
    return MultiscaleSpecimen(
        overview, roi, pixel_size_um, pixel_size_um / zoom, (float(origin_col), float(origin_row)), tilt_deg
    )


def _zoomed_in(
    coarse: tuple[np.ndarray, ...], fine_shape: tuple[int, int], centre_px: tuple[float, float], zoom: int
) -> list[np.ndarray]:
    """Each `coarse` canvas (rows, cols) resampled (bicubic, mirrored at the edges, float32) onto a
    canvas of `fine_shape` (rows, cols) `zoom` times finer, centred on its `centre_px` (col, row)."""
    # Fine canvas pixel (a, b) sits at coarse canvas (centre + (a - mid) / zoom) for both axes.
    rows_f, cols_f = np.indices(fine_shape, dtype=np.float32)
    map_col = centre_px[0] + (cols_f - (fine_shape[1] - 1) / 2) / zoom
    map_row = centre_px[1] + (rows_f - (fine_shape[0] - 1) / 2) / zoom
    return [
        cv2.remap(values.astype(np.float32), map_col, map_row, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
        for values in coarse
    ]


def render_tilt_series(
    z_um: np.ndarray,
    *,
    pixel_size_um: float,
    tilt_deg: tuple[float, ...],
    output_shape: tuple[int, int],
    noise_fraction: float = 0.02,
    seed: int = 0,
    physics: SemPhysics = DEFAULT_PHYSICS,
) -> tuple[list[np.ndarray], np.ndarray]:
    """Views of `z_um` at every tilt about a vertical axis (centre crops of `output_shape`), and the
    truth: heights seen at each pixel of the first view, µm. See `render_sem_view` for `physics`."""
    views = [
        render_sem_view(
            z_um, pixel_size_um=pixel_size_um, tilt_deg=t, noise_fraction=noise_fraction, seed=seed + i, physics=physics
        )
        for i, t in enumerate(tilt_deg)
    ]
    rows, cols = z_um.shape
    top, left = (rows - output_shape[0]) // 2, (cols - output_shape[1]) // 2
    crop = (slice(top, top + output_shape[0]), slice(left, left + output_shape[1]))
    return [view.image[crop] for view in views], views[0].z_seen_um[crop]

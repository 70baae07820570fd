"""Height map files analysed as a specimen's ROI is: an npz of `fracto height`
(formats.height_npz) or an X3P file, read into one HeightFile (its heights, the pixel size it
records, its matching noise apart from the tilt's share), whose roughness (`roughness_of_file`)
and report (`report_of_file`) are those a specimen of one ROI gets."""

from __future__ import annotations

import re
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fractoscope.errors import InvalidInputError
from fractoscope.formats.height_npz import HeightMapFile, read_height_npz
from fractoscope.formats.x3p import read_x3p
from fractoscope.reconstruction.build import store_height_map
from fractoscope.report import write_report
from fractoscope.specimen.queries import ChainRequest, roughness_of_map
from fractoscope.stereo.matching import DEFAULT_WINDOW_PX
from fractoscope.store.folder import SpecimenStore
from fractoscope.surface import roughness
from fractoscope.surface.measurement import tilt_share


@dataclass(frozen=True)
class HeightFile:
    """A height map file: heights (rows, cols) µm, NaN unknown; the pixel size it records, µm
    (None: none); where its pixel (0, 0) lies (x, y) µm; the matching window its heights were
    measured with, px (1 for an X3P file, which says nothing of it); its matching noise, µm
    (None: not recorded), the tilt's share ε_z (surface.measurement.tilt_share; None: not known)
    and its interpolated points (None: not recorded); the matching report and datum it records."""

    z_um: np.ndarray
    recorded_pixel_size_um: float | None
    origin_um: tuple[float, float] = (0.0, 0.0)
    window_px: float = 1.0
    sigma_um: np.ndarray | None = None
    tilt_rel_uncertainty: float | None = None
    filled: np.ndarray | None = None
    report: dict = field(default_factory=dict)
    datum: dict | None = None


def read_height_file(path: Path) -> HeightFile:
    """An .x3p or an .npz file of `fracto height` (InvalidInputError naming the file when an X3P
    file's pixels are not square)."""
    if path.suffix.lower() == ".x3p":
        surface = read_x3p(path)
        if not np.isclose(surface.step_x_um, surface.step_y_um, rtol=1e-6):
            raise InvalidInputError(
                str(path), f"pixels of {surface.step_x_um:g} x {surface.step_y_um:g} µm are not square"
            )
        return HeightFile(surface.z_um, surface.step_x_um, surface.origin_um)
    stored = read_height_npz(path)
    sigma_um, tilt_rel = matching_noise(stored)
    return HeightFile(
        stored.z_um.astype(np.float64),
        stored.pixel_size_um,
        window_px=DEFAULT_WINDOW_PX,
        sigma_um=sigma_um,
        tilt_rel_uncertainty=tilt_rel,
        filled=stored.filled,
        # The calibration as recorded, where the file keeps no matching report that states it.
        report={**(stored.calibration.to_report() if stored.calibration else {}), **stored.record.get("report", {})},
        datum=stored.record.get("datum"),
    )


def matching_noise(stored: HeightMapFile) -> tuple[np.ndarray | None, float | None]:
    """The matching noise of an npz height map, µm, on its grid, and the tilt's share of its
    sigma (None: not recorded): the chain propagates the tilt part, which scales all heights
    together, apart from the noise."""
    sigma_um = stored.local_sigma_um if stored.local_sigma_um is not None else stored.sigma_um
    tilt_rel = None
    if stored.calibration is not None and stored.local_sigma_um is not None:
        tilt_rel = tilt_share(
            stored.calibration.tilt_deg,
            tilt_uncertainty_deg=stored.record.get("report", {}).get("tilt_uncertainty_deg"),
        )
    return sigma_um, tilt_rel


def roughness_of_file(
    height_file: HeightFile, chain: ChainRequest, *, pixel_size_um: float
) -> roughness.SurfaceAnalysis:
    """The chain on a height map file, on a grid of `pixel_size_um`, as GetRoughness answers it
    for a specimen's ROI (specimen.queries.roughness_of_map)."""
    return roughness_of_map(
        height_file.z_um,
        pixel_size_um=pixel_size_um,
        origin_um=height_file.origin_um,
        sigma_um=height_file.sigma_um,
        filled=height_file.filled,
        tilt_rel_uncertainty=height_file.tilt_rel_uncertainty,
        chain=chain,
        default_window_px=height_file.window_px,
    )


def report_of_file(height_file: HeightFile, outputs: list[Path], *, name: str, pixel_size_um: float) -> None:
    """The measurement report of a height map file called `name`, written to each of `outputs`
    (.html, .pdf): the map is stored as a specimen of one ROI in a temporary data folder and
    reported as specimens are."""
    specimen_id = re.sub(r"[^A-Za-z0-9_-]", "-", Path(name).stem)[:64] or "height-map"
    with tempfile.TemporaryDirectory(prefix="fracto-report-") as folder:
        specimen = store_height_map(
            SpecimenStore(Path(folder)),
            specimen_id,
            height_file.z_um,
            pixel_size_um=pixel_size_um,
            report=height_file.report,
            sigma_um=height_file.sigma_um,
            filled=height_file.filled,
            tilt_rel_uncertainty=height_file.tilt_rel_uncertainty,
            datum=height_file.datum,
        )
        for output in outputs:
            written = write_report(
                specimen,
                Path(folder),
                file_format=output.suffix.lower().removeprefix("."),
                subject=f"height map file {name}",
            )
            shutil.move(written, output)

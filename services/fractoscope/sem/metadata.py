"""Calibration from SEM vendors' TIFF metadata (as tifffile decodes it): stage tilt, pixel size,
the image height without the data bar, and the nominal magnification."""

from __future__ import annotations

import re

import numpy as np

_LENGTH_TO_UM = {"pm": 1e-6, "nm": 1e-3, "µm": 1.0, "um": 1.0, "μm": 1.0, "mm": 1e3, "m": 1e6}


def _length_um(entry) -> float | None:
    """A Zeiss (name, value, unit) entry as micrometres."""
    if not isinstance(entry, tuple) or len(entry) < 3:
        return None
    value, unit = entry[1], str(entry[2])
    if not isinstance(value, (int, float)) or unit not in _LENGTH_TO_UM or value <= 0:
        return None
    return float(value) * _LENGTH_TO_UM[unit]


def zeiss_calibration(metadata: dict, shape: tuple[int, int]) -> tuple[float | None, float | None]:
    """Stage tilt from ``Stage at T`` and pixel size from ``Image Pixel Size`` (or Width / scan line).

    ``Tilt Angle`` is the tilt-correction setting and ``Pixel Size`` refers to the screen store
    resolution, so neither is used.
    """
    tilt = metadata.get("ap_stage_at_t")
    tilt_deg = float(tilt[1]) if isinstance(tilt, tuple) and isinstance(tilt[1], (int, float)) else None
    pixel_size_um = _length_um(metadata.get("ap_image_pixel_size"))
    if pixel_size_um is None:
        width_um = _length_um(metadata.get("ap_width"))
        if width_um is not None:
            pixel_size_um = width_um / max(shape)
    return tilt_deg, pixel_size_um


def fei_calibration(metadata: dict) -> tuple[float | None, float | None, int | None]:
    """Stage tilt (``[Stage] StageT``, radians), pixel size (``[Scan] PixelWidth``, metres) and the
    image height without data bar (``[Image] ResolutionY``)."""
    stage, scan, image = (metadata.get(name) or {} for name in ("Stage", "Scan", "Image"))
    tilt_rad = stage.get("StageT")
    tilt_deg = float(np.degrees(tilt_rad)) if isinstance(tilt_rad, (int, float)) else None
    pixel_m = scan.get("PixelWidth")
    pixel_size_um = float(pixel_m) * 1e6 if isinstance(pixel_m, (int, float)) and pixel_m > 0 else None
    rows = image.get("ResolutionY")
    return tilt_deg, pixel_size_um, int(rows) if isinstance(rows, int) else None


_MAGNIFICATION = re.compile(r"^\s*([0-9]*\.?[0-9]+)\s*([kKM]?)\s*[xX]\s*$")


def zeiss_magnification(metadata: dict) -> float | None:
    """The nominal magnification of ``Mag`` ("1.00 K X" is 1000), None when absent or unreadable."""
    entry = metadata.get("ap_mag")
    text = entry[1] if isinstance(entry, tuple) and len(entry) >= 2 else None
    if isinstance(text, (int, float)):
        return float(text) if text > 0 else None
    found = _MAGNIFICATION.match(text) if isinstance(text, str) else None
    if not found:
        return None
    value = float(found[1]) * {"": 1.0, "k": 1e3, "K": 1e3, "M": 1e6}[found[2]]
    return value if value > 0 else None

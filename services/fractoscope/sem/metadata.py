"""Calibration from SEM vendors' TIFF metadata (as tifffile decodes it): stage tilt, pixel size,
the image height without the data bar, the nominal magnification, and the instrument (model,
detector, scan rotation) that keys an instrument profile. Neither vendor records where a side
detector lies in the image: only whether the detector is one in the lens, by its name."""

from __future__ import annotations

import re
from dataclasses import dataclass
from datetime import datetime

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


@dataclass(frozen=True)
class InstrumentKey:
    """What an image file says about the microscope that took it: the key of an instrument
    profile (`sem.instruments`). Empty strings where the file does not say.

    vendor: "Zeiss" or "FEI/Thermo Fisher"; model: the vendor's name of the microscope;
    detector: the signal's detector as the vendor names it ("SE2", "InLens", "ETD", "TLD");
    scan_rotation_deg: the scan rotation the image was taken at, degrees as the vendor counts it
    (0 where the file says scan rotation is off).
    """

    vendor: str
    model: str
    detector: str
    scan_rotation_deg: float

    def describe(self) -> str:
        """ "Zeiss Auriga 60, detector SE2, scan rotation 0°"."""
        return f"{self.vendor} {self.model}, detector {self.detector}, scan rotation {self.scan_rotation_deg:g}°"


def zeiss_instrument(metadata: dict) -> InstrumentKey | None:
    """The instrument of a Zeiss SmartSEM image: ``Sem`` (model), the detector of ``Signal A``
    (the displayed channel), and ``Scan Rotation`` where ``Scan Rot`` is on; None without a model."""
    model = _zeiss_text(metadata.get("dp_sem"))
    if not model:
        return None
    detector = _zeiss_text(metadata.get("dp_detector_channel"))
    rotation = metadata.get("ap_scanrotation")
    rotation_on = metadata.get("dp_scan_rot")
    rotation_deg = 0.0
    if isinstance(rotation_on, tuple) and rotation_on[1] is True and isinstance(rotation, tuple):
        rotation_deg = float(rotation[1]) if isinstance(rotation[1], (int, float)) else float("nan")
    return InstrumentKey("Zeiss", model, detector, rotation_deg)


def fei_instrument(metadata: dict) -> InstrumentKey | None:
    """The instrument of an FEI / Thermo Fisher image: ``[System] SystemType`` (model),
    ``[Detectors] Name`` and ``[Beam] ScanRotation`` (radians; ``[EScan]``'s where ``[Beam]`` has
    none); None without a model."""
    system, detectors = (metadata.get(name) or {} for name in ("System", "Detectors"))
    model = str(system.get("SystemType") or system.get("Type") or "").strip()
    if not model:
        return None
    rotation_rad = next(
        (
            (metadata.get(section) or {}).get("ScanRotation")
            for section in ("Beam", "EScan")
            if isinstance((metadata.get(section) or {}).get("ScanRotation"), (int, float))
        ),
        0.0,
    )
    detector = str(detectors.get("Name") or "").strip()
    return InstrumentKey("FEI/Thermo Fisher", model, detector, round(float(np.degrees(rotation_rad)), 6))


def zeiss_acquired_at(metadata: dict) -> str | None:
    """When a Zeiss image was taken, ISO 8601 local time ("2016-03-08T10:39:14"), from ``Date``
    and ``Time``; None when absent or unreadable."""
    return _iso_time(_zeiss_text(metadata.get("ap_date")), _zeiss_text(metadata.get("ap_time")), ("%d %b %Y",))


def fei_acquired_at(metadata: dict) -> str | None:
    """When an FEI / Thermo Fisher image was taken, ISO 8601 local time, from ``[User] Date`` and
    ``Time`` (month first, as the instruments write it); None when absent or unreadable."""
    user = metadata.get("User") or {}
    return _iso_time(str(user.get("Date") or ""), str(user.get("Time") or ""), ("%m/%d/%Y",))


def _iso_time(date_text: str, time_text: str, date_formats: tuple[str, ...]) -> str | None:
    for date_format in date_formats:
        for time_format in ("%H:%M:%S", "%I:%M:%S %p", ""):
            try:
                stamp = datetime.strptime(f"{date_text} {time_text}".strip(), f"{date_format} {time_format}".strip())
            except ValueError:
                continue
            return stamp.isoformat(timespec="seconds")
    return None


def _zeiss_text(entry) -> str:
    return str(entry[1]).strip() if isinstance(entry, tuple) and len(entry) >= 2 and entry[1] is not None else ""


# Detectors inside the column or the lens collect secondary electrons from all sides alike, so
# their images are not lit from a side (Zeiss InLens, FEI / Thermo Fisher TLD and the T1-T3 and
# in-column detectors of newer columns); names as the vendors write them, compared case-blind.
_IN_LENS_DETECTORS = ("inlens", "in-lens", "in lens", "tld", "through lens", "t1", "t2", "t3", "icd")
# Everhart-Thornley detectors at a side port of the chamber: lit from one side.
_SIDE_DETECTORS = ("se2", "etd")


def detector_has_side(detector: str) -> bool | None:
    """Whether a detector so named lights the image from one side (an Everhart-Thornley detector
    at a chamber port) or from none (in the lens or column); None where the name does not say."""
    name = detector.strip().lower()
    if name in _IN_LENS_DETECTORS or name.startswith(("inlens", "in-lens", "in lens")):
        return False
    if name in _SIDE_DETECTORS or name.startswith("everhart"):
        return True
    return None

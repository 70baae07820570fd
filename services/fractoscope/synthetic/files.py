"""SEM image files as a microscope writes them: TIFFs with FEI / Thermo Fisher metadata (the INI
text of tag 34682: stage tilt, pixel size, instrument, detector, scan rotation), for tests of
what the product reads from files."""

from __future__ import annotations

import io

import numpy as np
import tifffile

_FEI_HELIOS_TAG = 34682


def fei_tiff(
    image: np.ndarray,
    *,
    tilt_deg: float,
    pixel_size_um: float,
    model: str = "Quanta 250 FEG",
    detector: str = "ETD",
    scan_rotation_deg: float = 0.0,
    acquired: tuple[str, str] = ("03/08/2016", "10:39:14 AM"),
) -> bytes:
    """The bytes of a TIFF of `image` (rows, cols, uint8 or uint16) whose FEI metadata records
    the stage tilt, pixel size, instrument model, detector, scan rotation and the (date, time) of
    acquisition given, as the instruments write them (month first)."""
    ini = (
        f"[User]\nDate={acquired[0]}\nTime={acquired[1]}\n"
        f"[System]\nType=SEM\nSystemType={model}\n"
        f"[Beam]\nScanRotation={np.radians(scan_rotation_deg):.9g}\n"
        f"[Stage]\nStageT={np.radians(tilt_deg):.9g}\n"
        f"[Scan]\nPixelWidth={pixel_size_um * 1e-6:.9g}\n"
        f"[Detectors]\nNumber=1\nName={detector}\nMode=SE\n"
        f"[Image]\nResolutionX={image.shape[1]}\nResolutionY={image.shape[0]}\n"
    )
    buffer = io.BytesIO()
    tifffile.imwrite(buffer, image, extratags=[(_FEI_HELIOS_TAG, "s", 0, ini, True)])
    return buffer.getvalue()

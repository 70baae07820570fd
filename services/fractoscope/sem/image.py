"""Reading SEM images and their calibration (stage tilt, pixel size) from TIFF and PNG files.

Supported metadata: Zeiss SmartSEM (TIFF tag 34118) and FEI / Thermo Fisher (tags 34680, 34682),
both decoded by tifffile and read by `metadata`. Pixels are returned as stored (rows, cols); an
instrument data bar at the bottom is detected and reported, not silently kept as image content.
"""

from __future__ import annotations

import io
import logging
import os
from dataclasses import dataclass

import numpy as np
import tifffile
from PIL import Image

from fractoscope.errors import InvalidInputError
from fractoscope.sem.metadata import fei_calibration, zeiss_calibration, zeiss_magnification

# Corrupt files are reported to the caller as InvalidInputError; tifffile's own log lines about
# them would only repeat that on the server's stderr.
logging.getLogger("tifffile").setLevel(logging.CRITICAL)

# Largest image accepted, pixels: a small file may declare a huge image (a decompression bomb).
MAX_IMAGE_PIXELS = int(os.environ.get("FRACTO_MAX_IMAGE_PIXELS", 16384 * 16384))
# Pillow's own bomb check (89 Mpx by default) would refuse PNGs within our limit as corrupt; ours
# runs on the PNG header before Pillow sees the file.
Image.MAX_IMAGE_PIXELS = max(Image.MAX_IMAGE_PIXELS or 0, MAX_IMAGE_PIXELS)
_TIFF_MAGIC = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")
_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@dataclass(frozen=True)
class SemImage:
    """One grey SEM image with what its file says about it.

    pixels: (rows, cols) uint8 or uint16, as stored, including any data bar.
    tilt_deg: stage tilt in degrees, None when the file does not say.
    pixel_size_um: lateral pixel size in micrometres, None when the file does not say.
    data_bar_rows: number of bottom rows that are an instrument data bar, not image.
    """

    pixels: np.ndarray
    tilt_deg: float | None
    pixel_size_um: float | None
    data_bar_rows: int

    @property
    def image(self) -> np.ndarray:
        """The pixels without the data bar, (rows - data_bar_rows, cols)."""
        return self.pixels[: self.pixels.shape[0] - self.data_bar_rows]


# The smallest side an image may have, data bar excluded (a correlation window needs room).
_MIN_SIDE_PX = 32


def read_sem_image(content: bytes, *, field: str = "image") -> SemImage:
    """Decodes a TIFF or PNG file's bytes; `field` names the input in error messages."""
    if _is_png(content, field):
        pixels, tilt_deg, pixel_size_um, bar_rows = _read_png(content, field), None, None, None
    else:
        pixels, tilt_deg, pixel_size_um, bar_rows = _read_tiff(content, field)
    if pixels.ndim != 2:
        raise InvalidInputError(field, f"expected a grey image, got pixels of shape {pixels.shape}")
    _check_size(pixels.shape, field)
    if bar_rows is not None and pixels.shape[0] - bar_rows < _MIN_SIDE_PX:
        raise InvalidInputError(
            field,
            f"its metadata puts {pixels.shape[0] - bar_rows} of its {pixels.shape[0]} rows above the data bar "
            f"(ResolutionY), fewer than {_MIN_SIDE_PX}",
        )
    if bar_rows is None:
        bar_rows = detect_data_bar_rows(pixels)
    return SemImage(pixels, tilt_deg, pixel_size_um, bar_rows)


def image_shape(content: bytes, *, field: str = "image") -> tuple[int, int]:
    """(rows, cols) that a TIFF or PNG file declares, from its header, without decoding it: for
    estimates before any work. Errors as read_sem_image's, the pixel limit included."""
    if _is_png(content, field):
        shape = _png_shape(content, field)
    else:
        try:
            with tifffile.TiffFile(io.BytesIO(content)) as tiff:
                shape = int(tiff.pages.first.imagelength), int(tiff.pages.first.imagewidth)
        except Exception as exc:  # as in _read_tiff
            raise InvalidInputError(
                field, f"unreadable TIFF, corrupt or truncated ({type(exc).__name__}: {exc})"
            ) from None
    _check_size(shape, field)
    return shape


def _is_png(content: bytes, field: str) -> bool:
    """True for a PNG file, False for a TIFF file; InvalidInputError for anything else."""
    if not content:
        raise InvalidInputError(field, "the image file is empty")
    if content[:8] == _PNG_MAGIC:
        return True
    if content[:4] in _TIFF_MAGIC:
        return False
    raise InvalidInputError(field, "not a TIFF or PNG file")


def _png_shape(content: bytes, field: str) -> tuple[int, int]:
    """(rows, cols) from a PNG's IHDR chunk, which must come first."""
    if len(content) < 24 or content[12:16] != b"IHDR":
        raise InvalidInputError(field, "unreadable PNG, corrupt or truncated (no IHDR chunk)")
    return int.from_bytes(content[20:24], "big"), int.from_bytes(content[16:20], "big")


def _read_png(content: bytes, field: str) -> np.ndarray:
    _check_size(_png_shape(content, field), field)
    try:
        with Image.open(io.BytesIO(content)) as picture:
            if picture.mode in ("RGB", "RGBA", "P", "LA"):
                picture = picture.convert("L")
            pixels = np.asarray(picture)
    except InvalidInputError:
        raise
    except Exception as exc:  # Pillow raises many types for corrupt files
        raise InvalidInputError(field, f"unreadable PNG, corrupt or truncated ({type(exc).__name__}: {exc})") from None
    return _as_grey_integer(pixels, field)


def _read_tiff(content: bytes, field: str):
    try:
        with tifffile.TiffFile(io.BytesIO(content)) as tiff:
            page = tiff.pages.first
            _check_size((page.imagelength, page.imagewidth), field)
            pixels = page.asarray()
            if page.planarconfig == tifffile.PLANARCONFIG.SEPARATE and pixels.ndim == 3:
                pixels = np.moveaxis(pixels, 0, -1)  # colour planes first: samples last, as contiguous files
            if page.photometric == tifffile.PHOTOMETRIC.PALETTE and page.colormap is not None:
                pixels = _palette_to_grey(pixels, page.colormap)
            zeiss = tiff.sem_metadata if tiff.is_sem else None
            fei = tiff.fei_metadata if tiff.is_fei else None
    except InvalidInputError:
        raise
    except Exception as exc:  # tifffile and imagecodecs raise many types for corrupt files
        raise InvalidInputError(field, f"unreadable TIFF, corrupt or truncated ({type(exc).__name__}: {exc})") from None
    pixels = _as_grey_integer(pixels, field)
    if zeiss:
        tilt_deg, pixel_size_um = zeiss_calibration(zeiss, pixels.shape)
        return pixels, tilt_deg, pixel_size_um, None
    if fei:
        tilt_deg, pixel_size_um, image_rows = fei_calibration(fei)
        bar_rows = pixels.shape[0] - image_rows if image_rows and 0 < image_rows < pixels.shape[0] else None
        return pixels, tilt_deg, pixel_size_um, bar_rows
    return pixels, None, None, None


def _check_size(shape, field: str) -> None:
    """InvalidInputError unless a (rows, cols) `shape` is at least _MIN_SIDE_PX a side and within
    the pixel limit."""
    rows, cols = (int(v) for v in shape)
    if min(rows, cols) < _MIN_SIDE_PX:
        raise InvalidInputError(
            field, f"expected an image of at least {_MIN_SIDE_PX}x{_MIN_SIDE_PX} pixels, got {cols}x{rows}"
        )
    if rows * cols > MAX_IMAGE_PIXELS:
        raise InvalidInputError(
            field, f"{cols}x{rows} pixels is larger than the limit of {MAX_IMAGE_PIXELS} (FRACTO_MAX_IMAGE_PIXELS)"
        )


def _palette_to_grey(indices: np.ndarray, colormap: np.ndarray) -> np.ndarray:
    """Palette images from SEM software are grey ramps; map indices through the red channel."""
    ramp = np.asarray(colormap[0], dtype=np.float64)
    scale = 255.0 / 65535.0 if ramp.max() > 255 else 1.0
    return np.round(ramp * scale).astype(np.uint8)[indices]


def _as_grey_integer(pixels: np.ndarray, field: str) -> np.ndarray:
    if pixels.size == 0:
        raise InvalidInputError(field, f"the image has no pixels (shape {pixels.shape})")
    if pixels.ndim == 3 and pixels.shape[-1] in (3, 4):
        pixels = pixels[..., :3].mean(axis=-1)
    if pixels.dtype in (np.uint8, np.uint16):
        return pixels
    if np.issubdtype(pixels.dtype, np.floating) or np.issubdtype(pixels.dtype, np.integer):
        values = pixels.astype(np.float64)
        if not np.all(np.isfinite(values)):
            raise InvalidInputError(field, "the image contains NaN or infinite values")
        # The grey range between the 0.01 and 99.99 % points: one hot pixel (1e30 in a float
        # image) must not crush the rest into one grey level.
        low, high = (float(value) for value in np.percentile(values, [0.01, 99.99]))
        span = high - low if high > low else 1.0
        return np.round(np.clip((values - low) / span, 0.0, 1.0) * 65535.0).astype(np.uint16)
    raise InvalidInputError(field, f"unsupported pixel type {pixels.dtype}")


def detect_data_bar_rows(pixels: np.ndarray, *, max_fraction: float = 0.2) -> int:
    """Rows at the bottom that form an instrument data bar, 0 when there is none.

    A data bar is drawn in the image's extreme values (black background, white text and frames),
    so its rows are almost entirely at the minimum or maximum grey level; image rows are not.
    """
    values = pixels.astype(np.float32)
    low, high = float(values.min()), float(values.max())
    tolerance = 0.02 * max(high - low, 1.0)
    at_extreme = (values - low < tolerance) | (high - values < tolerance)
    flat_rows = at_extreme.mean(axis=1) > 0.9
    limit = int(pixels.shape[0] * max_fraction)
    count = 0
    while count < limit and flat_rows[-1 - count]:
        count += 1
    return count


def nominal_magnification(content: bytes) -> float | None:
    """The magnification a TIFF file's metadata states (Zeiss SmartSEM ``Mag``; FEI files state
    none that is the nominal one), None for other files. For labels and for finding pixel sizes by
    magnification; heights use the pixel size."""
    try:
        with tifffile.TiffFile(io.BytesIO(content)) as tiff:
            return zeiss_magnification(tiff.sem_metadata) if tiff.is_sem and tiff.sem_metadata else None
    except Exception:  # not a TIFF, or a corrupt one: read_sem_image reports those
        return None

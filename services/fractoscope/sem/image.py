"""Reading SEM images and their calibration (stage tilt, pixel size) from TIFF, PNG and JPEG files.

Supported metadata: Zeiss SmartSEM (TIFF tag 34118) and FEI / Thermo Fisher (tags 34680, 34682),
both decoded by tifffile and read by `metadata`. Pixels are returned as stored (rows, cols), 8 or
16 bits as the file holds them; colour is reduced to luminance (ITU-R BT.601 weights) and JPEG's
lossy compression is accepted, each with a note; an instrument data bar at the bottom is detected
and reported, not silently kept as image content. A TIFF whose directory, tags or pixel data lie
beyond the file's end (a truncated copy) is refused before any decoding: tifffile would read what
is there and drop the rest, the calibration among it, without a word.
"""

from __future__ import annotations

import io
import logging
import os
import struct
from dataclasses import dataclass

import numpy as np
import tifffile
from PIL import Image

from fractoscope.errors import InvalidInputError
from fractoscope.sem.metadata import (
    InstrumentKey,
    fei_acquired_at,
    fei_calibration,
    fei_instrument,
    zeiss_acquired_at,
    zeiss_calibration,
    zeiss_instrument,
    zeiss_magnification,
)

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
_JPEG_MAGIC = b"\xff\xd8\xff"
# ITU-R BT.601 luma weights of R, G, B (those of Pillow's "L" mode too).
LUMA_WEIGHTS = (0.299, 0.587, 0.114)
JPEG_NOTE = (
    "a JPEG file: its lossy compression (8 x 8 pixel blocks, quantised fine texture) biases the matching "
    "towards the block grid and smooths sub-pixel detail; give TIFF or PNG where the microscope saves them"
)
COLOUR_NOTE = "a colour image, reduced to its luminance 0.299 R + 0.587 G + 0.114 B (ITU-R BT.601)"


@dataclass(frozen=True)
class SemImage:
    """One grey SEM image with what its file says about it.

    pixels: (rows, cols) uint8 or uint16, as stored, including any data bar.
    tilt_deg: stage tilt in degrees, None when the file does not say.
    pixel_size_um: lateral pixel size in micrometres, None when the file does not say.
    data_bar_rows: number of bottom rows that are an instrument data bar, not image.
    notes: what the reading changed or what may bias results (JPEG, colour), each naming the file.
    instrument: the microscope, detector and scan rotation the file names (None where it names none).
    acquired_at: when the image was taken, ISO 8601 local time, None where the file does not say.
    """

    pixels: np.ndarray
    tilt_deg: float | None
    pixel_size_um: float | None
    data_bar_rows: int
    notes: tuple[str, ...] = ()
    instrument: InstrumentKey | None = None
    acquired_at: str | None = None

    @property
    def image(self) -> np.ndarray:
        """The pixels without the data bar, (rows - data_bar_rows, cols)."""
        return self.pixels[: self.pixels.shape[0] - self.data_bar_rows]


# The smallest side an image may have, data bar excluded (a correlation window needs room).
_MIN_SIDE_PX = 32
# The longest side: OpenCV's remaps and warps refuse images of SHRT_MAX (32767) px or more a side.
MAX_SIDE_PX = 32766
# The most one side may be a multiple of the other (a stitched strip of views stays well within).
MAX_ASPECT = 64


def read_sem_image(content: bytes, *, field: str = "image") -> SemImage:
    """Decodes a TIFF, PNG or JPEG file's bytes; `field` names the input in error messages and notes."""
    kind = _file_kind(content, field)
    if kind == "TIFF":
        pixels, tilt_deg, pixel_size_um, bar_rows, instrument, acquired_at = _read_tiff(content, field)
    else:
        pixels, tilt_deg, pixel_size_um, bar_rows = _read_with_pillow(content, field, kind), None, None, None
        instrument = acquired_at = None
    notes = [f"{field}: {JPEG_NOTE}"] if kind == "JPEG" else []
    if pixels.ndim == 3 and pixels.shape[-1] in (3, 4):
        pixels, coloured = _luminance(pixels)
        notes += [f"{field}: {COLOUR_NOTE}"] if coloured else []
    if pixels.ndim != 2:
        raise InvalidInputError(
            field, f"expected a grey or RGB image, got pixels of shape {pixels.shape} (rows, cols, ...)"
        )
    pixels = _as_grey_integer(pixels, field)
    _check_size(pixels.shape, field)
    if bar_rows is not None and pixels.shape[0] - bar_rows < _MIN_SIDE_PX:
        raise InvalidInputError(
            field,
            f"its metadata puts {pixels.shape[0] - bar_rows} of its {pixels.shape[0]} rows above the data bar "
            f"(ResolutionY), fewer than {_MIN_SIDE_PX}",
        )
    if bar_rows is None:
        bar_rows = detect_data_bar_rows(pixels)
    return SemImage(pixels, tilt_deg, pixel_size_um, bar_rows, tuple(notes), instrument, acquired_at)


def image_shape(content: bytes, *, field: str = "image") -> tuple[int, int]:
    """(rows, cols) that a TIFF, PNG or JPEG file declares, from its header, without decoding it:
    for estimates before any work. Errors as read_sem_image's, the pixel limit included."""
    kind = _file_kind(content, field)
    if kind == "PNG":
        shape = _png_shape(content, field)
    elif kind == "JPEG":
        shape = _jpeg_shape(content, field)
    else:
        _check_tiff_complete(content, field)
        try:
            with tifffile.TiffFile(io.BytesIO(content)) as tiff:
                shape = int(tiff.pages.first.imagelength), int(tiff.pages.first.imagewidth)
        except Exception as exc:  # as in _read_tiff
            raise InvalidInputError(
                field, f"unreadable TIFF, corrupt or truncated ({type(exc).__name__}: {exc})"
            ) from None
    _check_size(shape, field)
    return shape


def _file_kind(content: bytes, field: str) -> str:
    """ "TIFF", "PNG" or "JPEG" by the file's magic bytes; InvalidInputError for anything else."""
    if not content:
        raise InvalidInputError(field, "the image file is empty")
    if content[:8] == _PNG_MAGIC:
        return "PNG"
    if content[:3] == _JPEG_MAGIC:
        return "JPEG"
    if content[:4] in _TIFF_MAGIC:
        return "TIFF"
    raise InvalidInputError(field, "not a TIFF, PNG or JPEG file")


def _png_shape(content: bytes, field: str) -> tuple[int, int]:
    """(rows, cols) from a PNG's IHDR chunk, which must come first."""
    if len(content) < 24 or content[12:16] != b"IHDR":
        raise InvalidInputError(field, "unreadable PNG, corrupt or truncated (no IHDR chunk)")
    return int.from_bytes(content[20:24], "big"), int.from_bytes(content[16:20], "big")


def _jpeg_shape(content: bytes, field: str) -> tuple[int, int]:
    """(rows, cols) from a JPEG's frame header, which Pillow reads without decoding the image."""
    try:
        with Image.open(io.BytesIO(content)) as picture:
            return picture.height, picture.width
    except Exception as exc:  # Pillow raises many types for corrupt files
        raise InvalidInputError(field, f"unreadable JPEG, corrupt or truncated ({type(exc).__name__}: {exc})") from None


def _read_with_pillow(content: bytes, field: str, kind: str) -> np.ndarray:
    """A PNG's or JPEG's pixels: (rows, cols) grey or (rows, cols, 3) RGB, as stored."""
    _check_size(_png_shape(content, field) if kind == "PNG" else _jpeg_shape(content, field), field)
    try:
        with Image.open(io.BytesIO(content)) as picture:
            if picture.mode in ("RGBA", "P", "LA", "CMYK", "YCbCr"):
                picture = picture.convert("RGB")
            return np.asarray(picture)
    except Exception as exc:  # Pillow raises many types for corrupt files
        raise InvalidInputError(
            field, f"unreadable {kind}, corrupt or truncated ({type(exc).__name__}: {exc})"
        ) from None


def _read_tiff(content: bytes, field: str):
    _check_tiff_complete(content, field)
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
    rows = pixels.shape[0]
    if zeiss:
        tilt_deg, pixel_size_um = zeiss_calibration(zeiss, pixels.shape[:2])
        return pixels, tilt_deg, pixel_size_um, None, zeiss_instrument(zeiss), zeiss_acquired_at(zeiss)
    if fei:
        tilt_deg, pixel_size_um, image_rows = fei_calibration(fei)
        bar_rows = rows - image_rows if image_rows and 0 < image_rows < rows else None
        return pixels, tilt_deg, pixel_size_um, bar_rows, fei_instrument(fei), fei_acquired_at(fei)
    return pixels, None, None, None, None, None


# Bytes per value of each TIFF field type (TIFF 6.0 and BigTIFF); unknown types count as 1.
_TIFF_TYPE_BYTES = {
    1: 1,
    2: 1,
    3: 2,
    4: 4,
    5: 8,
    6: 1,
    7: 1,
    8: 2,
    9: 4,
    10: 8,
    11: 4,
    12: 8,
    13: 4,
    16: 8,
    17: 8,
    18: 8,
}
# Tags whose value is the offset of a further directory (SubIFDs, Exif, GPS, Interoperability).
_SUB_IFD_TAGS = (330, 34665, 34853, 40965)
_STRIP_TAGS = ((273, 279), (324, 325))  # (StripOffsets, StripByteCounts), (TileOffsets, TileByteCounts)


def _check_tiff_complete(content: bytes, field: str) -> None:
    """InvalidInputError unless the first directory of a TIFF, the values of its tags, the
    directories they point to and its strips or tiles all lie within the file."""
    order = "<" if content[:2] == b"II" else ">"
    big = content[2:4] in (b"+\x00", b"\x00+")
    try:
        (first,) = struct.unpack_from(order + ("Q" if big else "I"), content, 8 if big else 4)
        end = _tiff_directory_end(content, first, order, big, depth=0)
    except struct.error:
        end = None
    if end is None or end > len(content):
        needed = "" if end is None else f" and its first image's data run to byte {end} or beyond"
        raise InvalidInputError(field, f"truncated or corrupt TIFF: the file has {len(content)} bytes{needed}")


def _tiff_directory_end(content: bytes, offset: int, order: str, big: bool, *, depth: int) -> int | None:
    """The last byte + 1 that a directory at `offset` uses (its entries, their values, the
    directories of _SUB_IFD_TAGS, and the strips or tiles it lists); None where it starts
    outside the file. struct.error where an entry runs past the end."""
    if not 8 <= offset < len(content) or depth > 2:
        return None if depth == 0 else offset
    count_format, entry_format, inline, entry_size = ("Q", "HHQQ", 8, 20) if big else ("H", "HHII", 4, 12)
    (count,) = struct.unpack_from(order + count_format, content, offset)
    first_entry = offset + (8 if big else 2)
    end = first_entry + count * entry_size + inline
    values = {}
    for index in range(count):
        tag, kind, number, value = struct.unpack_from(order + entry_format, content, first_entry + index * entry_size)
        size = _TIFF_TYPE_BYTES.get(kind, 1) * number
        if size > inline:
            end = max(end, value + size)
        if any(tag in pair for pair in _STRIP_TAGS):
            values[tag] = (kind, number, value)
        if tag in _SUB_IFD_TAGS and size <= inline and number == 1:
            end = max(end, _tiff_directory_end(content, value, order, big, depth=depth + 1) or len(content) + 1)
    for offsets_tag, counts_tag in _STRIP_TAGS:
        starts = _tiff_values(content, values.get(offsets_tag), order, big, end)
        lengths = _tiff_values(content, values.get(counts_tag), order, big, end)
        if len(starts) == len(lengths) and np.any(lengths > 0):  # an empty strip's offset may be anything
            end = max(end, int(np.max((starts + lengths)[lengths > 0])))
    return end


def _tiff_values(content: bytes, entry, order: str, big: bool, end: int) -> np.ndarray:
    """The integer values of an entry found by _tiff_directory_end, (n,) int64; none where they
    lie beyond the file (its end already says so)."""
    if entry is None:
        return np.zeros(0, np.int64)
    kind, number, value = entry
    dtype = {3: "u2", 4: "u4", 16: "u8"}.get(kind)
    if dtype is None:
        return np.zeros(0, np.int64)
    size = np.dtype(dtype).itemsize * number
    inline = 8 if big else 4
    if size <= inline:
        raw = struct.pack(order + ("Q" if big else "I"), value)[:size]
    elif value + size <= len(content):
        raw = content[value : value + size]
    else:
        return np.zeros(0, np.int64)
    return np.frombuffer(raw, dtype=order + dtype).astype(np.int64)


def _check_size(shape, field: str) -> None:
    """InvalidInputError unless a (rows, cols) `shape` has sides that check_sides takes and is
    within the pixel limit."""
    check_sides(shape, field)
    rows, cols = (int(v) for v in shape)
    if rows * cols > MAX_IMAGE_PIXELS:
        raise InvalidInputError(
            field, f"{cols}x{rows} pixels is larger than the limit of {MAX_IMAGE_PIXELS} (FRACTO_MAX_IMAGE_PIXELS)"
        )


def check_sides(shape, field: str) -> None:
    """InvalidInputError naming `field` unless an image or raster of (rows, cols) `shape` has
    sides of _MIN_SIDE_PX to MAX_SIDE_PX and a ratio of at most MAX_ASPECT between them."""
    rows, cols = (int(v) for v in shape)
    if min(rows, cols) < _MIN_SIDE_PX:
        raise InvalidInputError(
            field, f"expected an image of at least {_MIN_SIDE_PX}x{_MIN_SIDE_PX} pixels, got {cols}x{rows}"
        )
    if max(rows, cols) > MAX_SIDE_PX:
        raise InvalidInputError(
            field,
            f"{cols}x{rows} pixels has a side longer than {MAX_SIDE_PX} px, the most OpenCV's image "
            "operations take (SHRT_MAX - 1)",
        )
    if max(rows, cols) > MAX_ASPECT * min(rows, cols):
        raise InvalidInputError(
            field, f"{cols}x{rows} pixels is more than {MAX_ASPECT} times as long as it is wide, not an SEM image"
        )


def _palette_to_grey(indices: np.ndarray, colormap: np.ndarray) -> np.ndarray:
    """Palette images from SEM software are grey ramps; map indices through the red channel."""
    ramp = np.asarray(colormap[0], dtype=np.float64)
    scale = 255.0 / 65535.0 if ramp.max() > 255 else 1.0
    return np.round(ramp * scale).astype(np.uint8)[indices]


def _luminance(pixels: np.ndarray) -> tuple[np.ndarray, bool]:
    """(rows, cols, 3 or 4) colour -> (rows, cols) luminance by LUMA_WEIGHTS (alpha dropped), in
    the input's integer type where it is uint8 or uint16; and whether the channels differed (a grey
    image stored as RGB comes back as its one channel)."""
    rgb = pixels[..., :3]
    if np.array_equal(rgb[..., 0], rgb[..., 1]) and np.array_equal(rgb[..., 1], rgb[..., 2]):
        return rgb[..., 0].copy(), False
    luma = rgb.astype(np.float32) @ np.asarray(LUMA_WEIGHTS, np.float32)
    if pixels.dtype in (np.uint8, np.uint16):
        luma = np.clip(np.round(luma), 0, np.iinfo(pixels.dtype).max).astype(pixels.dtype)
    return luma, True


def _as_grey_integer(pixels: np.ndarray, field: str) -> np.ndarray:
    if pixels.size == 0:
        raise InvalidInputError(field, f"the image has no pixels (shape {pixels.shape}: rows, cols)")
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
    low, high = float(pixels.min()), float(pixels.max())
    tolerance = 0.02 * max(high - low, 1.0)
    limit = int(pixels.shape[0] * max_fraction)
    # Only the rows a bar may take are converted: the whole image took 10-28 s on a 16384² one.
    values = pixels[pixels.shape[0] - limit :].astype(np.float32)
    at_extreme = (values - low < tolerance) | (high - values < tolerance)
    flat_rows = at_extreme.mean(axis=1) > 0.9
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

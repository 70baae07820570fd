"""The .npz file of a height map: what `fracto height` writes and the other commands read back.

Arrays, on the reference image's grid (rows, cols), float32:
- `z_um` heights (NaN unknown) as every route keeps them (surface.measurement: cleaned, holes of
  a few pixels filled, levelled on the datum), `sigma_um` their one-sigma uncertainty (matching
  and tilt), `confidence` the peak correlation (as in the HeightMap message);
- `local_sigma_um`, the part of sigma_um that neighbouring heights do not share (the tilt error,
  which scales all heights together, left out; see stereo.geometry.matching_sigma_um);
- `filled` (bool), the heights interpolated rather than matched (absent in files written before
  it was kept);
- `views_used` (uint8), how many views of the series each height rests on (as in the HeightMap
  message), when the server counted them;
- `pixel_size_um` (a scalar) and `tilt_deg` (one per view), readable without this module;
- `tilt_deg_estimated` when the tilts were calibrated.

`record` is a JSON string: the software, the `calibration` (formats.calibration: tilts and pixel
size with their sources and sigmas), `tilt_axis_deg`, `max_slope` (the steepest slope the pair
can measure, stereo.geometry.max_measurable_slope), the matching `method`, `parameters` and
`report`, and the `datum` (where zero is: surface.datum.Datum.to_dict, or null).

Files written before the record existed hold z_um, sigma_um and confidence only; they read back
with `calibration` None, and commands then ask for what they need. A file with a `pixel_size_um`
array but no record (written with numpy alone) reads back with that pixel size.
"""

from __future__ import annotations

import json
import math
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fractoscope.errors import InvalidInputError
from fractoscope.formats.calibration import Calibration, software
from fractoscope.strict_json import json_ready


@dataclass(frozen=True)
class HeightMapFile:
    """A height map file's arrays (None where the file has none), its record, and the value of its
    `pixel_size_um` array (None without one)."""

    z_um: np.ndarray
    sigma_um: np.ndarray | None = None
    confidence: np.ndarray | None = None
    local_sigma_um: np.ndarray | None = None
    views_used: np.ndarray | None = None
    filled: np.ndarray | None = None
    calibration: Calibration | None = None
    record: dict = field(default_factory=dict)

    array_pixel_size_um: float | None = None

    @property
    def pixel_size_um(self) -> float | None:
        """The calibration's pixel size, else the `pixel_size_um` array's (a file with no record)."""
        return self.calibration.pixel_size_um if self.calibration else self.array_pixel_size_um

    @property
    def max_slope(self) -> float | None:
        return self.record.get("max_slope")


def write_height_npz(
    path: str | Path,
    *,
    z_um: np.ndarray,
    sigma_um: np.ndarray,
    confidence: np.ndarray,
    local_sigma_um: np.ndarray,
    calibration: Calibration,
    record: dict,
    tilt_deg_estimated: np.ndarray | None = None,
    views_used: np.ndarray | None = None,
    filled: np.ndarray | None = None,
) -> None:
    """Writes the file; `record` holds tilt_axis_deg, max_slope, method, parameters, report and
    datum (see the module's docstring), to which the software and calibration are added."""
    document = json_ready({"software": software(), "calibration": calibration.to_dict(), **record})
    arrays = {
        "z_um": np.asarray(z_um, np.float32),
        "sigma_um": np.asarray(sigma_um, np.float32),
        "confidence": np.asarray(confidence, np.float32),
        "local_sigma_um": np.asarray(local_sigma_um, np.float32),
        "pixel_size_um": np.float64(calibration.pixel_size_um),
        "tilt_deg": np.asarray(calibration.tilt_deg, np.float64),
        "record": np.str_(json.dumps(document, allow_nan=False)),
    }
    if tilt_deg_estimated is not None:
        arrays["tilt_deg_estimated"] = np.asarray(tilt_deg_estimated, np.float64)
    if views_used is not None:
        arrays["views_used"] = np.asarray(views_used, np.uint8)
    if filled is not None:
        arrays["filled"] = np.asarray(filled, bool)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, **arrays)


def read_height_npz(path: str | Path, *, field: str | None = None) -> HeightMapFile:
    """Reads a height map file; InvalidInputError naming `field` (default: the path) and what is
    wrong when it is none."""
    field = field or str(path)
    values = _arrays(path, field)
    z_um = values.get("z_um")
    if z_um is None or z_um.ndim != 2 or not _real(z_um):
        raise InvalidInputError(field, "holds no 2D z_um array of real numbers (write it with fracto height)")
    for name in ("sigma_um", "confidence", "local_sigma_um", "views_used", "filled"):
        if name in values and values[name].shape != z_um.shape:
            raise InvalidInputError(field, f"its {name} array has shape {values[name].shape}, its z_um {z_um.shape}")
        if name in values and not (_real(values[name]) or values[name].dtype == bool):
            raise InvalidInputError(field, f"its {name} array holds {values[name].dtype}, not real numbers")
    record = _record(values, field)
    try:
        calibration = Calibration.from_dict(record["calibration"]) if record.get("calibration") else None
    except KeyError as error:
        raise InvalidInputError(field, f"has an unreadable calibration in its record: no {error.args[0]}") from None
    except (ValueError, TypeError) as error:
        raise InvalidInputError(field, f"has an unreadable calibration in its record: {error}") from None
    return HeightMapFile(
        z_um=z_um,
        sigma_um=values.get("sigma_um"),
        confidence=values.get("confidence"),
        local_sigma_um=values.get("local_sigma_um"),
        views_used=values.get("views_used"),
        filled=values["filled"].astype(bool) if "filled" in values else None,
        calibration=calibration,
        record=record,
        array_pixel_size_um=_array_pixel_size_um(values, field),
    )


def _arrays(path: str | Path, field: str) -> dict[str, np.ndarray]:
    """Every array of the npz file at `path`."""
    if not zipfile.is_zipfile(path):
        raise InvalidInputError(
            field, "is not an npz file (a zip archive of .npy arrays): empty, truncated or of another kind"
        )
    try:
        with np.load(path, allow_pickle=False) as arrays:
            values = {name: arrays[name] for name in arrays.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as error:
        raise InvalidInputError(field, f"is an unreadable npz file ({type(error).__name__}: {error})") from None
    not_arrays = [name for name, value in values.items() if not isinstance(value, np.ndarray)]
    if not_arrays:
        raise InvalidInputError(field, f"is an unreadable npz file: {not_arrays[0]} is not a .npy array")
    return values


def _real(array: np.ndarray) -> bool:
    return np.issubdtype(array.dtype, np.floating) or np.issubdtype(array.dtype, np.integer)


def _record(values: dict[str, np.ndarray], field: str) -> dict:
    """The file's JSON record, {} for a file without one."""
    if "record" not in values:
        return {}
    try:
        record = json.loads(str(values["record"]))
    except ValueError as error:
        raise InvalidInputError(field, f"has an unreadable record: {error}") from None
    if not isinstance(record, dict):
        raise InvalidInputError(field, f"has an unreadable record: a JSON {type(record).__name__}, not an object")
    return record


def _array_pixel_size_um(values: dict[str, np.ndarray], field: str) -> float | None:
    """The `pixel_size_um` array's value, µm: None when the file has none."""
    if "pixel_size_um" not in values:
        return None
    array = values["pixel_size_um"]
    value = float(array.reshape(-1)[0]) if array.size == 1 and _real(array) else math.nan
    if not (math.isfinite(value) and value > 0):
        raise InvalidInputError(
            field, f"its pixel_size_um array must hold one positive finite number (µm), got {array.tolist()!r}"
        )
    return value

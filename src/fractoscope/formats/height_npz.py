"""The .npz file of a height map: what `fracto height` writes and the other commands read back.

Arrays, on the reference image's grid (rows, cols), float32:
- `z_um` heights (NaN unknown), `sigma_um` their one-sigma uncertainty, `confidence` the peak
  correlation (as in the HeightMap message);
- `local_sigma_um`, the part of sigma_um that neighbouring heights do not share (the tilt error,
  which scales all heights together, left out; see stereo.geometry.matching_sigma_um);
- `pixel_size_um` (a scalar) and `tilt_deg` (one per view), readable without this module;
- `tilt_deg_estimated` when the tilts were calibrated.

`record` is a JSON string: the software, the `calibration` (formats.calibration: tilts and pixel
size with their sources and sigmas), `tilt_axis_deg`, `max_slope` (the steepest slope the pair
can measure, stereo.geometry.max_measurable_slope), the matching `method`, `parameters` and
`report`, and the `datum` (where zero is: surface.datum.Datum.to_dict, or null).

Files written before the record existed hold z_um, sigma_um and confidence only; they read back
with `calibration` None, and commands then ask for what they need.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fractoscope.errors import InvalidInputError
from fractoscope.formats.calibration import Calibration, software


@dataclass(frozen=True)
class HeightMapFile:
    """A height map file's arrays (None where the file has none) and its record."""

    z_um: np.ndarray
    sigma_um: np.ndarray | None = None
    confidence: np.ndarray | None = None
    local_sigma_um: np.ndarray | None = None
    calibration: Calibration | None = None
    record: dict = field(default_factory=dict)

    @property
    def pixel_size_um(self) -> float | None:
        return self.calibration.pixel_size_um if self.calibration else None

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
) -> None:
    """Writes the file; `record` holds tilt_axis_deg, max_slope, method, parameters, report and
    datum (see the module's docstring), to which the software and calibration are added."""
    document = _json_ready({"software": software(), "calibration": calibration.to_dict(), **record})
    arrays = {
        "z_um": np.asarray(z_um, np.float32), "sigma_um": np.asarray(sigma_um, np.float32),
        "confidence": np.asarray(confidence, np.float32), "local_sigma_um": np.asarray(local_sigma_um, np.float32),
        "pixel_size_um": np.float64(calibration.pixel_size_um), "tilt_deg": np.asarray(calibration.tilt_deg, np.float64),
        "record": np.str_(json.dumps(document, allow_nan=False)),
    }
    if tilt_deg_estimated is not None:
        arrays["tilt_deg_estimated"] = np.asarray(tilt_deg_estimated, np.float64)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, **arrays)


def read_height_npz(path: str | Path, *, field: str = "heights") -> HeightMapFile:
    """Reads a height map file; InvalidInputError (naming `field`) when it is none."""
    try:
        with np.load(path, allow_pickle=False) as arrays:
            values = {name: arrays[name] for name in arrays.files}
    except (OSError, ValueError) as error:
        raise InvalidInputError(field, f"cannot read {path}: {error}") from None
    if "z_um" not in values or values["z_um"].ndim != 2:
        raise InvalidInputError(field, f"{path} holds no 2D z_um array (write it with fracto height)")
    record, calibration = {}, None
    if "record" in values:
        try:
            record = json.loads(str(values["record"]))
            calibration = Calibration.from_dict(record["calibration"]) if record.get("calibration") else None
        except (ValueError, KeyError, TypeError) as error:
            raise InvalidInputError(field, f"{path} has an unreadable record: {error}") from None
    return HeightMapFile(
        z_um=values["z_um"], sigma_um=values.get("sigma_um"), confidence=values.get("confidence"),
        local_sigma_um=values.get("local_sigma_um"), calibration=calibration, record=record,
    )


def _json_ready(value):
    """`value` with NaN and infinite numbers (unknown figures of a report) as None."""
    if isinstance(value, dict):
        return {key: _json_ready(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_ready(item) for item in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value

"""The calibration record that exported files carry: what the heights were computed with and where
each value came from, as JSON that X3P comments and TIFF descriptions hold alike."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from importlib import metadata

from fractoscope.formats._validate import require_positive
from fractoscope.stereo.inputs import ARGUMENT, METADATA, TILT_CALIBRATION

SOURCES = (METADATA, ARGUMENT, TILT_CALIBRATION)
"""Where a calibration value came from: the SEM file's metadata, the caller's argument, or the
tilt calibration of a series (which also gives its sigma)."""


@dataclass(frozen=True)
class Calibration:
    """Calibration of one height map.

    tilt_deg: stage tilt of each view, degrees, in view order.
    tilt_source: where each tilt came from, one of `SOURCES`.
    tilt_sigma_deg: one-sigma uncertainty of each tilt, degrees: the calibration's estimate where
        `tilt_source` is "tilt_calibration", the nominal tilt uncertainty otherwise; NaN if unknown.
    pixel_size_um: lateral pixel size of the SEM images, µm.
    pixel_size_source: where the pixel size came from, "metadata" or "argument".
    acquired_at: when the reference image was taken (ISO 8601 local time, its file's metadata),
        the date its tilts and pixel size are true of; "" where unknown.
    instrument: (vendor, model) of the microscope as the file names it; () where unknown.
    """

    tilt_deg: tuple[float, ...]
    tilt_source: tuple[str, ...]
    tilt_sigma_deg: tuple[float, ...]
    pixel_size_um: float
    pixel_size_source: str
    acquired_at: str = ""
    instrument: tuple[str, ...] = ()

    def __post_init__(self):
        for name in ("tilt_deg", "tilt_source", "tilt_sigma_deg", "instrument"):
            object.__setattr__(self, name, tuple(getattr(self, name)))
        views = len(self.tilt_deg)
        if views < 2 or not all(math.isfinite(t) for t in self.tilt_deg):
            raise ValueError(f"tilt_deg: need two or more finite tilts, got {self.tilt_deg}")
        for name in ("tilt_source", "tilt_sigma_deg"):
            if len(getattr(self, name)) != views:
                raise ValueError(f"{name}: {len(getattr(self, name))} entries for {views} tilts")
        bad = [s for s in self.tilt_source if s not in SOURCES]
        if bad:
            raise ValueError(f"tilt_source: {bad[0]!r} is none of {SOURCES}")
        if any(s < 0 for s in self.tilt_sigma_deg):  # NaN (unknown) passes
            raise ValueError(f"tilt_sigma_deg: must not be negative, got {self.tilt_sigma_deg}")
        require_positive(self.pixel_size_um, "pixel_size_um")
        if self.pixel_size_source not in SOURCES[:2]:
            raise ValueError(f"pixel_size_source: {self.pixel_size_source!r} is none of {SOURCES[:2]}")

    @property
    def tilt_calibrated(self) -> bool:
        """Whether any tilt comes from the tilt calibration rather than a nominal value."""
        return "tilt_calibration" in self.tilt_source

    def to_dict(self) -> dict:
        """JSON-ready: NaN (an unknown sigma) becomes None."""
        return {
            "tilt_deg": list(self.tilt_deg),
            "tilt_source": list(self.tilt_source),
            "tilt_sigma_deg": [s if math.isfinite(s) else None for s in self.tilt_sigma_deg],
            "tilt_calibrated": self.tilt_calibrated,
            "pixel_size_um": self.pixel_size_um,
            "pixel_size_source": self.pixel_size_source,
            "acquired_at": self.acquired_at or None,
            "instrument": list(self.instrument) or None,
        }

    def to_report(self) -> dict:
        """The matching report's fields (MatchingReport) that state this calibration, which
        `from_report` reads back: the nominal tilt uncertainty is the sigma of the first tilt not
        from the tilt calibration (NaN when all are)."""
        nominal_sigma = next(
            (s for s, source in zip(self.tilt_sigma_deg, self.tilt_source) if source != TILT_CALIBRATION), math.nan
        )
        return {
            "tilt_deg": list(self.tilt_deg),
            "tilt_source": list(self.tilt_source),
            "tilt_sigma_deg": list(self.tilt_sigma_deg),
            "pixel_size_um": self.pixel_size_um,
            "pixel_size_source": self.pixel_size_source,
            "parameters": {"tilt_uncertainty_deg": nominal_sigma},
        }

    @classmethod
    def from_report(cls, report: dict) -> Calibration | None:
        """The calibration a height map's matching report (MatchingReport's fields) states: each
        tilt's sigma is the calibration's estimate where calibrated, else the nominal tilt
        uncertainty of its parameters. None for a report that names no sources (one written
        before they were reported)."""
        tilts, sources = list(report.get("tilt_deg") or ()), list(report.get("tilt_source") or ())
        if not sources or len(sources) != len(tilts) or not report.get("pixel_size_source"):
            return None
        nominal_sigma = float((report.get("parameters") or {}).get("tilt_uncertainty_deg") or math.nan)
        calibrated_sigma = list(report.get("tilt_sigma_deg") or ())
        if len(calibrated_sigma) != len(tilts):
            calibrated_sigma = [math.nan] * len(tilts)
        sigma = [
            calibrated if source == TILT_CALIBRATION else nominal_sigma
            for source, calibrated in zip(sources, calibrated_sigma)
        ]
        instrument = report.get("instrument") or {}
        named = (instrument.get("vendor", ""), instrument.get("model", "")) if instrument.get("model") else ()
        return cls(
            tuple(tilts),
            tuple(sources),
            tuple(sigma),
            report["pixel_size_um"],
            report["pixel_size_source"],
            report.get("acquired_at") or "",
            named,
        )

    @classmethod
    def from_dict(cls, values: dict) -> Calibration:
        """The inverse of `to_dict`."""
        return cls(
            tilt_deg=tuple(values["tilt_deg"]),
            tilt_source=tuple(values["tilt_source"]),
            tilt_sigma_deg=tuple(math.nan if s is None else s for s in values["tilt_sigma_deg"]),
            pixel_size_um=values["pixel_size_um"],
            pixel_size_source=values["pixel_size_source"],
            acquired_at=values.get("acquired_at") or "",
            instrument=tuple(values.get("instrument") or ()),
        )


def software() -> str:
    """The writer of exported files as they name it: "Fractoscope <version>"."""
    try:
        return f"Fractoscope {metadata.version('fractoscope-services')}"
    except metadata.PackageNotFoundError:
        return "Fractoscope"


def export_description(calibration: Calibration | None, **fields) -> str:
    """The JSON document an exported file carries: the software, `fields` (e.g. the grid step) and
    the calibration (null when unknown). Parse it with `json.loads`; `Calibration.from_dict` reads
    its "calibration" entry back."""
    document = {"software": software(), **fields, "calibration": calibration.to_dict() if calibration else None}
    return json.dumps(document, allow_nan=False)

"""Instrument profiles: where a microscope's side detector lies, learned once and applied to the
images its metadata names, and where each image set's detector place comes from.

A profile is keyed by what the files record (`metadata.InstrumentKey`: vendor, model, detector,
scan rotation) and holds the detector's azimuth from the tilt axis as displayed, with its sigma.
Scan rotation turns the image of the tilt axis and of the detector together, so the azimuth from
the axis holds at any scan rotation, but only where the tilt axis given turns with it: a profile
applies at the scan rotation it was learned at, and elsewhere it is named, not used.

The profile file is JSON, ``{"profiles": [{"vendor": ..., "model": ..., "detector": ...,
"scan_rotation_deg": ..., "detector_from_tilt_axis_deg": ..., "sigma_deg": ...,
"learned_from": ..., "learned_on": ...}]}``; its path is FRACTO_INSTRUMENTS, else
$XDG_CONFIG_HOME/fractoscope/instruments.json (~/.config/... without XDG_CONFIG_HOME).
"""

from __future__ import annotations

import json
import math
import os
import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

from fractoscope.errors import InvalidInputError
from fractoscope.sem.metadata import InstrumentKey, detector_has_side

ENVIRONMENT_VARIABLE = "FRACTO_INSTRUMENTS"
# Scan rotations closer than this are one setting (the vendors store them to 0.1°).
_SAME_ROTATION_DEG = 0.5


@dataclass(frozen=True)
class InstrumentProfile:
    """Where one instrument's detector lies: `key`, and the detector's azimuth counter-clockwise
    from the tilt axis as displayed, degrees in (-180, 180], with its one-sigma; what it was
    learned from (file names) and when (ISO date)."""

    key: InstrumentKey
    detector_from_tilt_axis_deg: float
    sigma_deg: float
    learned_from: str = ""
    learned_on: str = ""

    @property
    def name(self) -> str:
        return self.key.describe()

    def applies_to(self, key: InstrumentKey) -> bool:
        """Whether `key` is this profile's instrument at this profile's scan rotation."""
        return self.same_detector(key) and abs(key.scan_rotation_deg - self.key.scan_rotation_deg) < _SAME_ROTATION_DEG

    def same_detector(self, key: InstrumentKey) -> bool:
        """Whether `key` names this profile's vendor, model and detector (case-blind)."""
        mine = (self.key.vendor, self.key.model, self.key.detector)
        return all(a.strip().lower() == b.strip().lower() for a, b in zip(mine, (key.vendor, key.model, key.detector)))


def profiles_path(environ: Mapping[str, str] = os.environ) -> Path:
    """The profile file's path: FRACTO_INSTRUMENTS, else the user's configuration folder's."""
    if environ.get(ENVIRONMENT_VARIABLE):
        return Path(environ[ENVIRONMENT_VARIABLE])
    config = Path(environ["XDG_CONFIG_HOME"]) if environ.get("XDG_CONFIG_HOME") else Path.home() / ".config"
    return config / "fractoscope" / "instruments.json"


def load_profiles(path: Path) -> tuple[InstrumentProfile, ...]:
    """The profiles in the file at `path` (none where there is no file); InvalidInputError naming
    the file and entry where it is not a profile file."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        return ()
    except OSError as error:
        raise InvalidInputError("instruments", f"cannot read the instrument profiles {path}: {error}") from None
    try:
        entries = json.loads(text)["profiles"]
        return tuple(_profile(entry) for entry in entries)
    except (ValueError, KeyError, TypeError) as error:
        raise InvalidInputError(
            "instruments", f"{path} is not an instrument profile file ({type(error).__name__}: {error})"
        ) from None


def save_profile(path: Path, profile: InstrumentProfile) -> tuple[InstrumentProfile, ...]:
    """Writes `profile` into the file at `path` (replacing one of the same instrument and scan
    rotation), atomically; returns the file's profiles."""
    kept = [old for old in load_profiles(path) if not old.applies_to(profile.key)]
    profiles = (*kept, profile)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    entries = [{**asdict(item.key), **{k: v for k, v in asdict(item).items() if k != "key"}} for item in profiles]
    with tempfile.NamedTemporaryFile("w", dir=path.parent, delete=False, suffix=".tmp", encoding="utf-8") as file:
        json.dump({"profiles": entries}, file, indent=1)
    os.replace(file.name, path)
    return profiles


def _profile(entry: dict) -> InstrumentProfile:
    key = InstrumentKey(
        str(entry["vendor"]), str(entry["model"]), str(entry["detector"]), float(entry["scan_rotation_deg"])
    )
    azimuth, sigma = float(entry["detector_from_tilt_axis_deg"]), float(entry["sigma_deg"])
    if not (math.isfinite(azimuth) and math.isfinite(key.scan_rotation_deg) and sigma >= 0):
        raise ValueError(f"profile {key.describe()}: azimuth, sigma and scan rotation must be finite")
    return InstrumentProfile(key, azimuth, sigma, str(entry.get("learned_from", "")), str(entry.get("learned_on", "")))


@dataclass(frozen=True)
class DetectorPlace:
    """Where the side detector lies for one image set, and how that is known.

    from_tilt_axis_deg: its azimuth from the tilt axis as displayed, degrees; NaN where not known.
    source: "given" (a request field, flag or manifest entry), "profile" (`profile` names it),
        "in-lens" (the metadata names a detector without a side: no lighting to tell by) or
        "unknown".
    note: what else the user should know (a profile for another scan rotation), or "".
    """

    from_tilt_axis_deg: float
    source: str
    profile: str = ""
    note: str = ""

    @property
    def known(self) -> bool:
        return math.isfinite(self.from_tilt_axis_deg)

    def describe(self) -> str:
        """How the place is known, in words: "given", "from the instrument profile 'Zeiss ...'"."""
        if self.source == "profile":
            return f"from the instrument profile '{self.profile}'"
        return {"given": "as given", "in-lens": "an in-lens detector, without a side"}.get(self.source, "not known")


def detector_place(
    instruments: Sequence[InstrumentKey | None], given_deg: float, profiles: Sequence[InstrumentProfile]
) -> DetectorPlace:
    """The detector's place for images whose files name `instruments` (one per image, None where
    a file names none): `given_deg` where finite, else the profile of their common instrument,
    else what the detector's name says (in-lens: no side), else not known."""
    if math.isfinite(given_deg):
        return DetectorPlace(float(given_deg), "given")
    keys = {key for key in instruments if key is not None}
    if len(keys) != 1 or None in instruments:
        note = "the images name different instruments; no profile applies" if len(keys) > 1 else ""
        return DetectorPlace(math.nan, "unknown", note=note)
    (key,) = keys
    for profile in profiles:
        if profile.applies_to(key):
            return DetectorPlace(profile.detector_from_tilt_axis_deg, "profile", profile.name)
    elsewhere = [profile for profile in profiles if profile.same_detector(key)]
    note = ""
    if elsewhere:
        rotations = ", ".join(f"{profile.key.scan_rotation_deg:g}°" for profile in elsewhere)
        note = (
            f"a profile of {key.vendor} {key.model}, detector {key.detector} exists for scan rotation {rotations}, "
            f"not these images' {key.scan_rotation_deg:g}°: learn one at this scan rotation"
        )
    if detector_has_side(key.detector) is False:
        return DetectorPlace(math.nan, "in-lens", note=note)
    return DetectorPlace(math.nan, "unknown", note=note)

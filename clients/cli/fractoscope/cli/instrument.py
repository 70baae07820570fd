"""`fracto instrument`: instrument profiles, where a microscope's side detector lies in its
images (sem.instruments). `learn` measures it on a pair or series whose relief is known, `list`
shows the profiles that height maps use automatically."""

from __future__ import annotations

import datetime
import math
from pathlib import Path

import numpy as np

from fractoscope.cli.common import SERVER_HELP, UsageError, connected, err, existing_file, print_json

# A known dome's centre (a disc of this share of the image's smaller side, as a radius) must stand
# above its border (beyond twice that) by this many of its heights' median sigma.
_DOME_CENTRE_SHARE = 0.2
_DOME_MIN_SIGMAS = 3.0


def add_parsers(commands) -> None:
    instrument = commands.add_parser("instrument", help="instrument profiles: where a microscope's detector lies")
    verbs = instrument.add_subparsers(dest="instrument_command", required=True)
    learn = verbs.add_parser(
        "learn",
        help="learn where the side detector lies from images whose relief is known, keyed by the instrument, "
        "detector and scan rotation their metadata names",
    )
    learn.add_argument("images", nargs="+", metavar="IMAGE", help="the reference image, then the other views")
    learn.add_argument(
        "--tilt", nargs="+", type=float, metavar="T", help="stage tilts, one per image (default: metadata)"
    )
    learn.add_argument("--pixel-size-um", type=float, help="pixel size in µm (default: metadata)")
    learn.add_argument("--tilt-axis-deg", type=float, help="tilt axis direction in the image, degrees (default 90)")
    learn.add_argument(
        "--relief",
        choices=("trusted", "known-dome"),
        default="trusted",
        help="what is known: trusted (default: the tilts and image order are right, so the heights are the right way "
        "up) or known-dome (a particle that stands up in the image's centre: the heights are turned so)",
    )
    learn.add_argument("--profiles", help="the profile file (default: FRACTO_INSTRUMENTS, else the user's config)")
    learn.add_argument("--server", help=SERVER_HELP)
    learn.add_argument("--json", action="store_true", help="print the learned profile as JSON")
    learn.set_defaults(run=command_learn)
    listed = verbs.add_parser("list", help="the instrument profiles height maps use")
    listed.add_argument("--profiles", help="the profile file (default: FRACTO_INSTRUMENTS, else the user's config)")
    listed.add_argument("--json", action="store_true", help="print them as JSON")
    listed.set_defaults(run=command_list)


def command_learn(args) -> int:
    from fractoscope.sem.instruments import InstrumentProfile, profiles_path, save_profile

    if len(args.images) < 2:
        raise UsageError("give at least two images (a stereo pair or a tilt series)")
    if args.tilt is not None and len(args.tilt) != len(args.images):
        raise UsageError(f"--tilt needs one angle per image: {len(args.images)} images, {len(args.tilt)} tilts")
    paths = [existing_file(image) for image in args.images]
    key = _instrument_of(paths)
    with connected(args.server) as client:
        result = client.compute_height_map(
            paths,
            tilt_deg=args.tilt,
            pixel_size_um=args.pixel_size_um,
            tilt_axis_deg=args.tilt_axis_deg,
            relief_sign="nominal",
        )
    report = result.report
    azimuth, sigma = report.get("lighting_from_tilt_axis_deg", math.nan), report.get("lighting_sigma_deg", math.nan)
    if azimuth is None or not math.isfinite(azimuth):
        raise UsageError(
            "the images show no lighting from a side (their blocks agree on no direction): a detector without a side, "
            "too little relief, or too little of the image measured; nothing learned"
        )
    if args.relief == "known-dome" and not _stands_up(result.z_um, result.sigma_um):
        azimuth = (azimuth + 360.0) % 360.0 - 180.0  # the heights were a pit: the dome is their mirror image
    profile = InstrumentProfile(
        key,
        round(float(azimuth), 2),
        round(float(sigma), 2),
        learned_from=", ".join(path.name for path in paths),
        learned_on=datetime.date.today().isoformat(),
    )
    path = Path(args.profiles) if args.profiles else profiles_path()
    save_profile(path, profile)
    if args.json:
        print_json({"profile": profile.name, "detector_from_tilt_axis_deg": profile.detector_from_tilt_axis_deg,
                    "sigma_deg": profile.sigma_deg, "file": str(path)})  # fmt: skip
    else:
        print(
            f"learned {profile.name}: the detector lies {profile.detector_from_tilt_axis_deg:.0f} ± "
            f"{profile.sigma_deg:.0f}° from the tilt axis; written to {path}"
        )
    return 0


def _instrument_of(paths: list[Path]):
    """The instrument the files name (all the same), before any matching; UsageError where they
    name none, several, or a detector without a side."""
    from fractoscope.sem.image import read_sem_image
    from fractoscope.sem.metadata import detector_has_side

    keys = {read_sem_image(path.read_bytes(), field=str(path)).instrument for path in paths}
    if None in keys:
        raise UsageError(
            "the metadata of some images names no instrument (vendor, model, detector), so a profile could never be "
            "applied to them; learn on the microscope's own TIFF files"
        )
    if len(keys) > 1:
        raise UsageError(f"the images name different instruments: {'; '.join(sorted(k.describe() for k in keys))}")
    (key,) = keys
    if detector_has_side(key.detector) is False:
        raise UsageError(
            f"the detector {key.detector} lies in the lens: its images are lit from no side, nothing to learn"
        )
    return key


def _stands_up(z_um: np.ndarray, sigma_um: np.ndarray) -> bool:
    """Whether the centre of a known dome's heights stands above their border; UsageError where
    neither it nor its mirror image does by _DOME_MIN_SIGMAS of their median sigma."""
    rows, cols = np.indices(z_um.shape)
    radius = np.hypot(rows - (z_um.shape[0] - 1) / 2, cols - (z_um.shape[1] - 1) / 2)
    centre_px = _DOME_CENTRE_SHARE * min(z_um.shape)
    rise = np.nanmedian(z_um[radius < centre_px]) - np.nanmedian(z_um[radius > 2 * centre_px])
    if not abs(rise) > _DOME_MIN_SIGMAS * np.nanmedian(sigma_um):
        raise UsageError(
            f"--relief known-dome: the image's centre stands {rise:.3g} µm from its border, within the heights' noise: "
            "no dome there; centre the particle, or use --relief trusted"
        )
    return bool(rise > 0)


def command_list(args) -> int:
    from fractoscope.sem.instruments import load_profiles, profiles_path

    path = Path(args.profiles) if args.profiles else profiles_path()
    profiles = load_profiles(path)
    if args.json:
        print_json({"file": str(path), "profiles": [
            {"profile": p.name, "detector_from_tilt_axis_deg": p.detector_from_tilt_axis_deg, "sigma_deg": p.sigma_deg,
             "learned_from": p.learned_from, "learned_on": p.learned_on} for p in profiles]})  # fmt: skip
        return 0
    if not profiles:
        err.print(f"no instrument profiles in {path}", markup=False)
    for profile in profiles:
        print(
            f"{profile.name}: detector {profile.detector_from_tilt_axis_deg:.0f} ± {profile.sigma_deg:.0f}° from the "
            f"tilt axis (learned from {profile.learned_from or 'unknown'} on {profile.learned_on or 'unknown'})"
        )
    return 0

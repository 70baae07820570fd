"""What every verb shares: the connection (a server, or the services in-process), progress bars,
usage errors and exit codes, and the wording of errors in terms of the command line."""

from __future__ import annotations

import argparse
import contextlib
import difflib
import json
import math
import os
import re
from collections.abc import Iterator
from pathlib import Path

from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

from fractoscope import strict_json
from fractoscope.client import FractoscopeClient
from fractoscope.errors import InvalidInputError
from fractoscope.rpc import wire
from fractoscope.rpc.manifest import image_entry, image_names, manifest_field
from fractoscope.v1 import common_pb2

err = Console(stderr=True)
SERVER_HELP = "HOST:PORT of a Fractoscope server (default: FRACTO_SERVER, else in-process)"


class UsageError(Exception):
    """A problem with the command line itself (missing file, bad value)."""


def server_address(explicit: str | None) -> str | None:
    """The server to use: the explicit one, else FRACTO_SERVER, else None (run in-process)."""
    return explicit or os.environ.get("FRACTO_SERVER") or None


@contextlib.contextmanager
def connected(server: str | None, data_dir: str | None = None) -> Iterator[FractoscopeClient]:
    """A client to `server`, FRACTO_SERVER, or services started in-process for this command: with
    `data_dir` all of them, specimens kept there; without, matching and meshing only, which write
    nothing to disk."""
    address = server_address(server)
    if address:
        with FractoscopeClient(address) as client:
            yield client
        return
    from fractoscope.runtime.process import keep_freed_memory
    from fractoscope.server.main import embedded_server

    keep_freed_memory()  # as fracto-server does: the services run in this process
    services = embedded_server(data_dir) if data_dir is not None else embedded_server(services=("matching", "meshing"))
    with services as local, FractoscopeClient(local) as client:
        yield client


@contextlib.contextmanager
def progress_bar(description: str, enabled: bool):
    """A progress bar on stderr; yields the callback that advances it."""
    if not enabled:
        yield lambda fraction, message: None
        return
    columns = (
        TextColumn("{task.description}"),
        BarColumn(),
        TextColumn("{task.percentage:>3.0f}%"),
        TimeElapsedColumn(),
    )
    with Progress(*columns, console=err, transient=True) as bar:
        task = bar.add_task(description, total=1.0)
        yield lambda fraction, message: bar.update(task, completed=fraction, description=f"{description}: {message}")


def print_json(document) -> None:
    """Prints a --json answer: strict JSON, unknown and infinite numbers null."""
    print(strict_json.dumps(document))


def calibrated_tilts(report: dict) -> str:
    """The tilts a matching report (MatchingReport's fields) estimated, with their sigmas and the
    nominal tilts they started from, as one line of text; "" when its tilts were not calibrated."""
    if "tilt_calibration" not in (report.get("tilt_source") or ()):
        return ""
    estimated = ", ".join(f"{t:+.3f} ± {s:.3f}" for t, s in zip(report["tilt_deg"], report["tilt_sigma_deg"]))
    nominal = ", ".join(f"{t:+.2f}" for t in report["tilt_deg_nominal"])
    return f"tilts estimated {estimated} ° (nominal {nominal}; residual {report['tilt_residual_px']:.3f} px)"


def relief_sign_sentence(report: dict) -> str:
    """The relief sign's verdict of a matching report (MatchingReport.relief_sign_sentence, the
    server's words), "" where the report has none or its warnings already say it."""
    sentence = report.get("relief_sign_sentence") or ""
    return "" if any(sentence and warning.startswith(sentence) for warning in report.get("warnings", ())) else sentence


def datum_sentence(datum: dict) -> str:
    """Where height zero is and the figures that say whether it is a measured level, from a datum
    (surface.datum.Datum.to_dict, or a Datum message as a dict), with its warning."""
    places = {
        "plane": "a plane through all heights",
        "substrate": "the substrate",
        "region": "the region's plane",
        "background": "the background plane (no substrate was found)",
    }
    sigma = datum.get("sigma_um")
    against = f" against a sigma of {sigma:.3g} µm" if sigma is not None and math.isfinite(sigma) else ""
    if datum["level"] == "none":
        sentence = "datum: none, the heights as measured (no plane subtracted)"
        return sentence + (f"; warning: {datum['warning']}" if datum.get("warning") else "")
    sentence = (
        f"datum: 0 µm on {places.get(datum['level'], datum['level'])}, tilted {datum['tilt_deg']:.2f}°; fitted on "
        f"{100 * datum['area_fraction']:.1f} % of the map ({100 * datum['measured_fraction']:.0f} % of it measured), "
        f"residual {datum['residual_rms_um']:.3g} µm RMS{against}"
    )
    return sentence + (f"; warning: {datum['warning']}" if datum.get("warning") else "")


def existing_file(text: str) -> Path:
    path = Path(text)
    if not path.is_file():
        raise UsageError(f"cannot read {text}: no such file")
    return path


# What a picture flag (--png, --plot) may write: matplotlib's raster and vector formats.
PICTURE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".pdf", ".svg")


def output_file(text: str, flag: str, *, suffixes: tuple[str, ...], inputs: tuple[Path, ...] = ()) -> Path:
    """The path a flag names for a file to write, checked before any work: a name ending in one of
    `suffixes` (lower case), in an existing folder, and none of `inputs` (UsageError naming the
    flag otherwise)."""
    path = Path(text)
    if path.suffix.lower() not in suffixes:
        raise UsageError(f"{flag}: give a file name ending in {' or '.join(suffixes)}, got {text!r}")
    if path.is_dir():
        raise UsageError(f"{flag}: {text} is a folder")
    if not path.parent.is_dir():
        raise UsageError(f"{flag}: no folder {path.parent} to write {path.name} into")
    if any(path.exists() and path.samefile(given) for given in inputs):
        raise UsageError(f"{flag}: {text} is one of the inputs; it would be overwritten")
    return path


def output_folder(text: str, flag: str) -> Path:
    """The folder a flag names for files to write (made as they are written), checked before any
    work: UsageError naming the flag if it, or the nearest existing folder above it, is a file."""
    path = Path(text)
    existing = next(candidate for candidate in (path, *path.absolute().parents) if candidate.exists())
    if not existing.is_dir():
        raise UsageError(f"{flag}: {existing} is a file, not a folder to write into")
    return path


def given_pixel_size_um(value: float | None) -> float | None:
    """--pixel-size-um checked as every command checks it (InvalidInputError naming it), None when
    not given."""
    from fractoscope.stereo.geometry import validate_pixel_size_um

    return None if value is None else validate_pixel_size_um(value)


def recorded_pixel_size_um(path: Path | str, recorded_um: float | None) -> float:
    """The pixel size file `path` records, checked as --pixel-size-um is."""
    if recorded_um is None:
        raise UsageError(f"{path} does not record its pixel size: give --pixel-size-um")
    from fractoscope.stereo.geometry import validate_pixel_size_um

    try:
        return validate_pixel_size_um(recorded_um)
    except InvalidInputError as error:
        raise InvalidInputError(str(path), f"its pixel size {error.message}; give --pixel-size-um") from None


# Request fields (as errors name them) that stand for a command-line flag.
_FIELD_FLAGS = [
    (re.compile(r"^(images\[\d*\]\.)?tilt_deg$"), "--tilt"),
    (re.compile(r"^(height_map\.)?pixel_size_um$"), "--pixel-size-um"),
    (re.compile(r"^tilt_axis_deg$"), "--tilt-axis-deg"),
    (re.compile(r"^parameters\.calibrate_tilt$"), "--calibrate-tilt"),
    (re.compile(r"^parameters\.normalize_local_contrast$"), "--local-contrast"),
    (re.compile(r"^level_count$"), "--levels"),
]
# Request fields whose flag is their name with dashes (s_filter_um: --s-filter-um), the chain's
# also as members of `chain`.
_DASHED_FIELD = re.compile(rf"^(chain\.)?({'|'.join(wire.CHAIN_FIELDS)})$|^(spacing_um|magnification|request_id)$")
_IMAGE_FIELD = re.compile(r"^images\[(\d+)\](\.image)?$")
# Request fields about the analysed data: the region, or the file or specimen analysed.
_AREA_FIELD = re.compile(r"^((area|specimen)\.)?region$")
_DATA_FIELD = re.compile(r"^(sigma_um|z_um)$")


def in_command_line_terms(field: str | None, message: str, args) -> str:
    """An error message about request `field` as the user wrote the command: the flag (`--tilt`)
    or the file (`right.tif`) instead of the request's field (`images[1].tilt_deg`)."""
    if not field:
        return message
    detail = message.split(": ", 1)[1] if message.startswith(f"{field}: ") else message
    named = _flag_or_file(field, args)
    return f"{named}: {detail}" if named else message


def _flag_or_file(field: str, args) -> str | None:
    """The flag or file that request `field` stands for in this command line, None if none."""
    for pattern, flag in _FIELD_FLAGS:
        if pattern.match(field):
            return flag
    dashed = _DASHED_FIELD.match(field)
    if dashed:
        return "--" + (dashed[2] or dashed[3]).replace("_", "-")
    if _AREA_FIELD.match(field) and getattr(args, "region", None) is not None:
        return "--region"
    if _AREA_FIELD.match(field) or _DATA_FIELD.match(field):
        return getattr(args, "source", None) or getattr(args, "specimen", None)
    image = _IMAGE_FIELD.match(field)
    images = getattr(args, "images", None) or []
    if image and int(image[1]) < len(images):
        return images[int(image[1])]
    if field.startswith("rois[") and getattr(args, "manifest", None):
        return _manifest_entry(Path(args.manifest), field)
    return None


def _manifest_entry(path: Path, field: str) -> str:
    """The image file (next to the manifest at `path`) that request `field` is about, else the
    manifest and its entry (manifest_field)."""
    entry = image_entry(field)
    name = None
    if entry:
        try:
            name = image_names(json.loads(path.read_bytes())["rois"][entry[0]])[entry[1]]
        except (OSError, ValueError, LookupError, TypeError, RecursionError):
            pass
    return (
        str(path.parent / name)
        if isinstance(name, str)
        else f"{path}: {manifest_field(field).removeprefix('manifest.')}"
    )


# gRPC's own words for a connection that closed during a call (the server stopped or restarted:
# its GOAWAY's text, or the socket's), as opposed to one that never opened.
_WENT_AWAY = ("cancelling all calls", "goaway", "connection reset")


def is_connection_failure(message: str) -> bool:
    """Whether an UNAVAILABLE status is gRPC's own (no connection), not one a service sent."""
    lowered = message.lower()
    return any(
        text in lowered
        for text in (
            "failed to connect",
            "connection refused",
            "dns resolution failed",
            "socket closed",
            "connections to all backends failing",
            *_WENT_AWAY,
        )
    )


def unavailable_sentence(server: str | None, message: str = "") -> str:
    """What to say when the server cannot be reached, or went away during the call (`message`,
    gRPC's, tells which), in one plain sentence instead of gRPC's transport terms."""
    address = server_address(server)
    if not address:
        return "the in-process Fractoscope services stopped answering; try again"
    if any(text in message.lower() for text in _WENT_AWAY):
        return f"the Fractoscope server at {address} closed the connection during the call (stopped?); try again"
    return (
        f"the Fractoscope server at {address} cannot be reached; start it (fracto-server) or point --server or "
        "FRACTO_SERVER at a running one"
    )


class SuggestingParser(argparse.ArgumentParser):
    """An argument parser whose errors are one line, as the other bad-input errors are, and say
    for an unknown choice what was probably meant."""

    def error(self, message: str):
        choice = re.search(r"invalid choice: '([^']*)' \(choose from (.*)\)", message)
        if choice:
            known = re.findall(r"'([^']*)'", choice[2])
            message += did_you_mean(choice[1], known)
        self.exit(2, f"error: {message} (see {self.prog} --help)\n")


def did_you_mean(word: str, known) -> str:
    """ "; did you mean X?" for the closest of `known` to `word`, or ""."""
    close = difflib.get_close_matches(word, list(known), n=1, cutoff=0.6)
    return f"; did you mean {close[0]}?" if close else ""


def reject_unknown(parser: argparse.ArgumentParser, args, extras: list[str]) -> None:
    """Exits with a usage error naming the arguments nobody took, and for a mistyped flag the flag
    of the chosen verb it is closest to."""
    if not extras:
        return
    verb = _subparser(parser, getattr(args, "command", None)) or parser
    flags = [flag for action in verb._actions for flag in action.option_strings]
    hint = next((did_you_mean(word.split("=", 1)[0], flags) for word in extras if word.startswith("--")), "")
    verb.error(f"unrecognized arguments: {' '.join(extras)}{hint}")


def _subparser(parser: argparse.ArgumentParser, name: str | None) -> argparse.ArgumentParser | None:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction) and name in action.choices:
            return action.choices[name]
    return None


def region_argument(text: str) -> tuple[float, float, float, float]:
    """X0,Y0,X1,Y1 in µm, for argparse."""
    try:
        x0, y0, x1, y1 = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected X0,Y0,X1,Y1 in µm, got {text!r}") from None
    return x0, y0, x1, y1


UNMEASURED = {"absent": common_pb2.UNMEASURED_AREAS_ABSENT, "flat": common_pb2.UNMEASURED_AREAS_FLAT}


def add_unmeasured_argument(parser: argparse.ArgumentParser) -> None:
    """`--unmeasured absent|flat`, read back through UNMEASURED (UnmeasuredAreas)."""
    parser.add_argument(
        "--unmeasured",
        choices=tuple(UNMEASURED),
        default="absent",
        help="where nothing was measured: draw nothing (absent, the default) or a flat grey floor at height zero",
    )

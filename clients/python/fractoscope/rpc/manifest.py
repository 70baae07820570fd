"""Specimen manifests: JSON naming a specimen and its ROIs and their image files, as ROI messages.
Shared by the client (a manifest file, images relative to it) and the HTTP API (a manifest
uploaded with its images).

    {"specimen": "steel-42",
     "rois": [{"id": "overview", "left": "o_l.tif", "right": "o_r.tif", "magnification": 500},
              {"id": "zoom", "left": "z_l.tif", "right": "z_r.tif", "magnification": 2000,
               "parent": "overview", "center_um": "auto", "tilt_deg": [-5, 5], "pixel_size_um": 0.05,
               "tilt_axis_deg": 90, "matching": {"propagate_at_full_resolution": true}}]}

"matching" holds MatchingParameters fields (see the protobuf API) for that ROI's pair. The
overview may name a "level" ("plane" or "substrate"): where height zero is (RoiSpec.level).
"""

from __future__ import annotations

import json
import re
import sys
from collections.abc import Callable, Sequence

from google.protobuf import json_format

from fractoscope.errors import InvalidInputError
from fractoscope.rpc.limits import MAX_ROIS
from fractoscope.v1 import common_pb2, tiles_pb2

_MANIFEST_KEYS = {"specimen", "rois"}
_KEYS = {
    "id",
    "left",
    "right",
    "tilt_deg",
    "pixel_size_um",
    "tilt_axis_deg",
    "magnification",
    "parent",
    "center_um",
    "matching",
    "level",
}


def parse_manifest(
    text: str | bytes,
    read_image: Callable[[str, str], bytes],
    *,
    source: str = "the manifest",
    max_image_bytes: int | None = None,
) -> tuple[str, list[tiles_pb2.RoiSpec]]:
    """(specimen id, ROI messages with the images' bytes) of a manifest's JSON text; `read_image(name,
    field)` returns the bytes of an image the manifest names (raising InvalidInputError naming
    `field` when it cannot). The whole manifest is checked before any image is read, and each file
    is read once however many ROIs name it. `max_image_bytes` bounds the images' bytes counted per
    ROI (each ROI's message carries its own copy). InvalidInputError names the bad entry; `source`
    names the manifest in messages."""
    manifest = _json(text, source)
    if not isinstance(manifest, dict) or not isinstance(manifest.get("specimen"), str):
        raise InvalidInputError("manifest.specimen", "the manifest must be an object with a specimen id")
    _refuse_repeated_key(manifest, "manifest")
    unknown = set(manifest) - _MANIFEST_KEYS
    if unknown:
        raise InvalidInputError("manifest", f"unknown keys {sorted(unknown)}; known: {sorted(_MANIFEST_KEYS)}")
    entries = manifest.get("rois")
    if not isinstance(entries, list) or not entries:
        raise InvalidInputError("manifest.rois", "must be a non-empty list")
    if len(entries) > MAX_ROIS:
        raise InvalidInputError("manifest.rois", f"at most {MAX_ROIS} ROIs make one specimen, got {len(entries)}")
    specs = [_roi(entry, index) for index, entry in enumerate(entries)]
    _add_images(specs, entries, read_image, max_image_bytes)
    return manifest["specimen"], specs


class _RepeatedKeys(dict):
    """A JSON object that gives its key `repeated` more than once (json.loads would keep the last unseen)."""

    def __init__(self, values: dict, repeated: str):
        super().__init__(values)
        self.repeated = repeated


def _object(pairs: list[tuple[str, object]]) -> dict:
    """json.loads's object_pairs_hook: a repeated key is marked here and refused where the manifest's
    structure is checked, which knows the entry's name."""
    seen = set()
    for key, _ in pairs:
        if key in seen:
            return _RepeatedKeys(dict(pairs), key)
        seen.add(key)
    return dict(pairs)


def _json(text: str | bytes, source: str):
    try:
        return json.loads(text, object_pairs_hook=_object)
    except (json.JSONDecodeError, UnicodeDecodeError, RecursionError) as error:
        raise InvalidInputError("manifest", f"{source} is not JSON: {error}") from None
    except ValueError:  # the integer digit limit that guards int() against quadratic time
        raise InvalidInputError(
            "manifest", f"{source} holds an integer of more than {sys.get_int_max_str_digits()} digits"
        ) from None


def _refuse_repeated_key(value: dict, where: str) -> None:
    if isinstance(value, _RepeatedKeys):
        raise InvalidInputError(f"{where}.{value.repeated}", "is given more than once")


_ROI_IMAGE_FIELD = re.compile(r"rois\[(\d+)\]\.images\[([01])\](\.image|\.tilt_deg)?")


def manifest_field(field: str) -> str:
    """The manifest entry that a ReconstructSpecimen request's `field` comes from:
    rois[i].images[0].image is manifest.rois[i].left, rois[i].images[1].tilt_deg is
    manifest.rois[i].tilt_deg, rois[i].parameters.x is manifest.rois[i].matching.x."""
    image = _ROI_IMAGE_FIELD.fullmatch(field)
    if image:
        return (
            f"manifest.rois[{image[1]}].{'tilt_deg' if image[3] == '.tilt_deg' else ('left', 'right')[int(image[2])]}"
        )
    return "manifest." + field.replace("].parameters.", "].matching.", 1)


def image_entry(field: str) -> tuple[int, str] | None:
    """(ROI index, "left" or "right"): the manifest's image file that a ReconstructSpecimen
    request's `field` (rois[i].images[j] or its .image) is about; None for any other field."""
    image = _ROI_IMAGE_FIELD.fullmatch(field)
    return (int(image[1]), ("left", "right")[int(image[2])]) if image and image[3] != ".tilt_deg" else None


def _roi(entry, index: int) -> tiles_pb2.RoiSpec:
    """An ROI entry's message, every key and number checked, its images named but not yet read."""
    where = f"manifest.rois[{index}]"
    if not isinstance(entry, dict):
        raise InvalidInputError(where, "must be an object")
    _refuse_repeated_key(entry, where)
    unknown = set(entry) - _KEYS
    if unknown:
        raise InvalidInputError(where, f"unknown keys {sorted(unknown)}; known: {sorted(_KEYS)}")
    for key in ("id", "left", "right"):
        if not isinstance(entry.get(key), str):
            raise InvalidInputError(f"{where}.{key}", "is required (a string)")
    if not isinstance(entry.get("parent", ""), str):
        raise InvalidInputError(f"{where}.parent", "must be the id of another ROI (a string)")
    tilts = entry.get("tilt_deg")
    if tilts is not None:
        tilts = _pair(tilts, f"{where}.tilt_deg", "must be two numbers [t1, t2]")
    spec = tiles_pb2.RoiSpec(
        id=entry["id"],
        parent=entry.get("parent", ""),
        magnification=_float(entry.get("magnification", 0.0), f"{where}.magnification"),
    )
    for side_index, side in enumerate(("left", "right")):
        image = spec.images.add()  # filled in place: nesting a built message would copy the image
        image.image.filename = entry[side].replace("\\", "/").rsplit("/", 1)[-1]
        if tilts is not None:
            image.tilt_deg = tilts[side_index]
    for key in ("pixel_size_um", "tilt_axis_deg"):
        if key in entry:
            setattr(spec, key, _float(entry[key], f"{where}.{key}"))
    centre = entry.get("center_um", "auto")
    if centre != "auto":
        x_um, y_um = _pair(centre, f"{where}.center_um", 'must be [x, y] in µm or "auto"')
        spec.center_um.CopyFrom(common_pb2.PointUm(x_um=x_um, y_um=y_um))
    if "level" in entry:
        # Its value is checked where it is used (tiles.messages.roi_request), whose errors name it too.
        if not isinstance(entry["level"], str) or entry.get("parent"):
            raise InvalidInputError(f"{where}.level", 'must be "plane" or "substrate", and is for the overview only')
        spec.level = entry["level"]
    if "matching" in entry:
        _matching(entry["matching"], spec.parameters, f"{where}.matching")
    return spec


def _matching(value, parameters, field: str) -> None:
    """`value`, an object of MatchingParameters fields, parsed into `parameters`."""
    if not isinstance(value, dict):
        raise InvalidInputError(field, "must be an object of MatchingParameters fields")
    _refuse_repeated_key(value, field)
    try:
        json_format.ParseDict(value, parameters)
    except json_format.ParseError as error:
        raise InvalidInputError(field, f"not MatchingParameters: {str(error).splitlines()[0]}") from None
    except OverflowError:  # an integer beyond a double, for a double field
        raise InvalidInputError(field, "holds a number too large for a double") from None


def _add_images(
    specs: list[tiles_pb2.RoiSpec],
    entries: Sequence[dict],
    read_image: Callable[[str, str], bytes],
    max_image_bytes: int | None,
) -> None:
    """Each ROI's images' bytes, each file read once; InvalidInputError naming manifest.rois when
    the bytes counted per ROI exceed `max_image_bytes`."""
    files: dict[str, bytes] = {}
    for index, entry in enumerate(entries):
        for side in ("left", "right"):
            if entry[side] not in files:
                files[entry[side]] = read_image(entry[side], f"manifest.rois[{index}].{side}")
    carried = sum(len(files[entry[side]]) for entry in entries for side in ("left", "right"))
    if max_image_bytes is not None and carried > max_image_bytes:
        raise InvalidInputError(
            "manifest.rois",
            f"the ROIs' images come to {carried} bytes counted per ROI (each ROI carries its own copy through "
            f"the build), more than the {max_image_bytes} allowed",
        )
    for spec, entry in zip(specs, entries):
        for image, side in zip(spec.images, ("left", "right")):
            image.image.content = files[entry[side]]


def _number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _float(value, field: str, message: str = "must be a number") -> float:
    if not _number(value):
        raise InvalidInputError(field, message)
    try:
        return float(value)
    except OverflowError:  # an integer of hundreds of digits
        raise InvalidInputError(field, f"{message}, and this one is too large for a double") from None


def _pair(value, field: str, message: str) -> tuple[float, float]:
    if not (isinstance(value, list) and len(value) == 2):
        raise InvalidInputError(field, message)
    return _float(value[0], field, message), _float(value[1], field, message)

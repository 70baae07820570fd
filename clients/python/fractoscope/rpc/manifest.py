"""Specimen manifests: JSON naming a specimen and its ROIs and their image files, as ROI messages.
Shared by the client (a manifest file, images relative to it) and the HTTP API (a manifest
uploaded with its images).

    {"specimen": "steel-42",
     "rois": [{"id": "overview", "images": ["o_m5.tif", "o_0.tif", "o_p5.tif"], "tilt_deg": [-5, 0, 5],
               "calibrate": true, "magnification": 500},
              {"id": "zoom", "left": "z_l.tif", "right": "z_r.tif", "magnification": 2000,
               "parent": "overview", "center_um": "auto", "tilt_deg": [-5, 5], "pixel_size_um": 0.05,
               "tilt_axis_deg": 90, "matching": {"propagate_at_full_resolution": true}}]}

An ROI is a stereo pair ("left", "right") or a tilt series of three or more images ("images",
reference first); "tilt_deg" gives one tilt per image. "calibrate": true (series only) estimates
the tilts from the images, the given or metadata tilts being the start (MatchingParameters'
calibrate_tilt). "matching" holds MatchingParameters fields (see the protobuf API) for that ROI's
images. The overview may name a "level" ("plane" or "substrate"): where height zero is
(RoiSpec.level).
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
    "images",
    "calibrate",
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


_ROI_IMAGE_FIELD = re.compile(r"rois\[(\d+)\]\.images\[(\d+)\](\.image|\.tilt_deg)?")
_PAIR_SIDES = ("left", "right")


def manifest_field(field: str, rois: Sequence[tiles_pb2.RoiSpec] = ()) -> str:
    """The manifest entry that a ReconstructSpecimen request's `field` comes from:
    rois[i].images[0].image is manifest.rois[i].left (manifest.rois[i].images[0] for a tilt
    series: an image index above 1, or an ROI of the request's `rois` with three or more images),
    rois[i].images[1].tilt_deg is manifest.rois[i].tilt_deg, rois[i].parameters.x is
    manifest.rois[i].matching.x."""
    image = _ROI_IMAGE_FIELD.fullmatch(field)
    if image:
        roi, view = int(image[1]), int(image[2])
        if image[3] == ".tilt_deg":
            return f"manifest.rois[{roi}].tilt_deg"
        series = view >= len(_PAIR_SIDES) or (roi < len(rois) and len(rois[roi].images) > len(_PAIR_SIDES))
        return f"manifest.rois[{roi}]." + (f"images[{view}]" if series else _PAIR_SIDES[view])
    return "manifest." + field.replace("].parameters.", "].matching.", 1)


def image_entry(field: str) -> tuple[int, int] | None:
    """(ROI index, image index, reference first): the manifest's image file that a
    ReconstructSpecimen request's `field` (rois[i].images[j] or its .image) is about; None for any
    other field."""
    image = _ROI_IMAGE_FIELD.fullmatch(field)
    return (int(image[1]), int(image[2])) if image and image[3] != ".tilt_deg" else None


def image_names(entry: dict) -> list[str]:
    """The image files a checked ROI entry names, reference first: its series, or left and right."""
    return list(entry["images"]) if "images" in entry else [entry[side] for side in _PAIR_SIDES]


def _roi(entry, index: int) -> tiles_pb2.RoiSpec:
    """An ROI entry's message, every key and number checked, its images named but not yet read."""
    where = f"manifest.rois[{index}]"
    if not isinstance(entry, dict):
        raise InvalidInputError(where, "must be an object")
    _refuse_repeated_key(entry, where)
    unknown = set(entry) - _KEYS
    if unknown:
        raise InvalidInputError(where, f"unknown keys {sorted(unknown)}; known: {sorted(_KEYS)}")
    if not isinstance(entry.get("id"), str):
        raise InvalidInputError(f"{where}.id", "is required (a string)")
    names = _image_files(entry, where)
    if not isinstance(entry.get("parent", ""), str):
        raise InvalidInputError(f"{where}.parent", "must be the id of another ROI (a string)")
    tilts = entry.get("tilt_deg")
    if tilts is not None:
        tilts = _numbers(tilts, len(names), f"{where}.tilt_deg", f"must be {len(names)} numbers, one per image")
    spec = tiles_pb2.RoiSpec(
        id=entry["id"],
        parent=entry.get("parent", ""),
        magnification=_float(entry.get("magnification", 0.0), f"{where}.magnification"),
    )
    for view, name in enumerate(names):
        image = spec.images.add()  # filled in place: nesting a built message would copy the image
        image.image.filename = name.replace("\\", "/").rsplit("/", 1)[-1]
        if tilts is not None:
            image.tilt_deg = tilts[view]
    for key in ("pixel_size_um", "tilt_axis_deg"):
        if key in entry:
            setattr(spec, key, _float(entry[key], f"{where}.{key}"))
    centre = entry.get("center_um", "auto")
    if centre != "auto":
        x_um, y_um = _numbers(centre, 2, f"{where}.center_um", 'must be [x, y] in µm or "auto"')
        spec.center_um.CopyFrom(common_pb2.PointUm(x_um=x_um, y_um=y_um))
    if "level" in entry:
        # Its value is checked where it is used (tiles.messages.roi_request), whose errors name it too.
        if not isinstance(entry["level"], str) or entry.get("parent"):
            raise InvalidInputError(f"{where}.level", 'must be "plane" or "substrate", and is for the overview only')
        spec.level = entry["level"]
    if "matching" in entry:
        _matching(entry["matching"], spec.parameters, f"{where}.matching")
    if entry.get("calibrate", False) is not False:
        if entry["calibrate"] is not True or len(names) < 3:
            raise InvalidInputError(
                f"{where}.calibrate",
                "must be true or false; true (calibrate the tilts) takes a series of 3 or more images",
            )
        spec.parameters.calibrate_tilt = True
    return spec


def _image_files(entry: dict, where: str) -> list[str]:
    """The image files an ROI entry names, reference first: "left" and "right", or "images" (a
    tilt series of three or more), checked."""
    if "images" in entry:
        names = entry["images"]
        if "left" in entry or "right" in entry:
            raise InvalidInputError(f"{where}.images", 'give either "left" and "right" (a pair) or "images" (a series)')
        if not (isinstance(names, list) and len(names) >= 3 and all(isinstance(name, str) for name in names)):
            raise InvalidInputError(
                f"{where}.images", "must list 3 or more image files, reference first (a pair: left and right)"
            )
    else:
        for side in _PAIR_SIDES:
            if not isinstance(entry.get(side), str):
                raise InvalidInputError(f"{where}.{side}", 'is required (a string), or "images" for a tilt series')
    return image_names(entry)


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
        for view, name in enumerate(image_names(entry)):
            if name not in files:
                files[name] = read_image(name, manifest_field(f"rois[{index}].images[{view}]", specs))
    carried = sum(len(files[name]) for entry in entries for name in image_names(entry))
    if max_image_bytes is not None and carried > max_image_bytes:
        raise InvalidInputError(
            "manifest.rois",
            f"the ROIs' images come to {carried} bytes counted per ROI (each ROI carries its own copy through "
            f"the build), more than the {max_image_bytes} allowed",
        )
    for spec, entry in zip(specs, entries):
        for image, name in zip(spec.images, image_names(entry)):
            image.image.content = files[name]


def _number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _float(value, field: str, message: str = "must be a number") -> float:
    if not _number(value):
        raise InvalidInputError(field, message)
    try:
        return float(value)
    except OverflowError:  # an integer of hundreds of digits
        raise InvalidInputError(field, f"{message}, and this one is too large for a double") from None


def _numbers(value, count: int, field: str, message: str) -> list[float]:
    """A list of `count` numbers, checked; InvalidInputError(field, message) otherwise."""
    if not (isinstance(value, list) and len(value) == count):
        raise InvalidInputError(field, message)
    return [_float(item, field, message) for item in value]

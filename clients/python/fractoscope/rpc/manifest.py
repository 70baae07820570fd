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
from collections.abc import Callable

from google.protobuf import json_format

from fractoscope.errors import InvalidInputError
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
    text: str | bytes, read_image: Callable[[str, str], bytes], *, source: str = "the manifest"
) -> tuple[str, list[tiles_pb2.RoiSpec]]:
    """(specimen id, ROI messages with the images' bytes) of a manifest's JSON text; `read_image(name,
    field)` returns the bytes of an image the manifest names (raising InvalidInputError naming
    `field` when it cannot). InvalidInputError names the bad entry; `source` names the manifest in
    messages."""
    try:
        manifest = json.loads(text)
    except (json.JSONDecodeError, UnicodeDecodeError, RecursionError) as error:
        raise InvalidInputError("manifest", f"{source} is not JSON: {error}") from None
    if not isinstance(manifest, dict) or not isinstance(manifest.get("specimen"), str):
        raise InvalidInputError("manifest.specimen", "the manifest must be an object with a specimen id")
    unknown = set(manifest) - _MANIFEST_KEYS
    if unknown:
        raise InvalidInputError("manifest", f"unknown keys {sorted(unknown)}; known: {sorted(_MANIFEST_KEYS)}")
    entries = manifest.get("rois")
    if not isinstance(entries, list) or not entries:
        raise InvalidInputError("manifest.rois", "must be a non-empty list")
    return manifest["specimen"], [_roi(entry, index, read_image) for index, entry in enumerate(entries)]


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


def _roi(entry, index: int, read_image: Callable[[str, str], bytes]) -> tiles_pb2.RoiSpec:
    where = f"manifest.rois[{index}]"
    if not isinstance(entry, dict):
        raise InvalidInputError(where, "must be an object")
    unknown = set(entry) - _KEYS
    if unknown:
        raise InvalidInputError(where, f"unknown keys {sorted(unknown)}; known: {sorted(_KEYS)}")
    for key in ("id", "left", "right"):
        if not isinstance(entry.get(key), str):
            raise InvalidInputError(f"{where}.{key}", "is required (a string)")
    if not isinstance(entry.get("parent", ""), str):
        raise InvalidInputError(f"{where}.parent", "must be the id of another ROI (a string)")
    tilts = entry.get("tilt_deg")
    if tilts is not None and not (isinstance(tilts, list) and len(tilts) == 2 and all(_number(t) for t in tilts)):
        raise InvalidInputError(f"{where}.tilt_deg", "must be two numbers [t1, t2]")
    spec = tiles_pb2.RoiSpec(
        id=entry["id"], parent=entry.get("parent", ""), magnification=_float(entry, "magnification", where, 0.0)
    )
    for side_index, side in enumerate(("left", "right")):
        image = spec.images.add()  # filled in place: nesting a built message would copy the image
        image.image.content, image.image.filename = (
            read_image(entry[side], f"{where}.{side}"),
            entry[side].replace("\\", "/").rsplit("/", 1)[-1],
        )
        if tilts is not None:
            image.tilt_deg = float(tilts[side_index])
    if "pixel_size_um" in entry:
        spec.pixel_size_um = _float(entry, "pixel_size_um", where)
    if "tilt_axis_deg" in entry:
        spec.tilt_axis_deg = _float(entry, "tilt_axis_deg", where)
    centre = entry.get("center_um", "auto")
    if centre != "auto":
        if not (isinstance(centre, list) and len(centre) == 2 and all(_number(v) for v in centre)):
            raise InvalidInputError(f"{where}.center_um", 'must be [x, y] in µm or "auto"')
        spec.center_um.CopyFrom(common_pb2.PointUm(x_um=float(centre[0]), y_um=float(centre[1])))
    if "level" in entry:
        # Its value is checked where it is used (tiles.messages.roi_request), whose errors name it too.
        if not isinstance(entry["level"], str) or entry.get("parent"):
            raise InvalidInputError(f"{where}.level", 'must be "plane" or "substrate", and is for the overview only')
        spec.level = entry["level"]
    if "matching" in entry:
        if not isinstance(entry["matching"], dict):
            raise InvalidInputError(f"{where}.matching", "must be an object of MatchingParameters fields")
        try:
            json_format.ParseDict(entry["matching"], spec.parameters)
        except json_format.ParseError as error:
            first_line = str(error).splitlines()[0]
            raise InvalidInputError(f"{where}.matching", f"not MatchingParameters: {first_line}") from None
    return spec


def _number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _float(entry: dict, key: str, where: str, default: float | None = None) -> float:
    value = entry.get(key, default)
    if not _number(value):
        raise InvalidInputError(f"{where}.{key}", "must be a number")
    return float(value)

"""Specimen manifest files: JSON naming a specimen and its ROIs (the format: rpc.manifest), the
images' paths relative to the file."""

from __future__ import annotations

from pathlib import Path

from fractoscope.errors import InvalidInputError
from fractoscope.rpc.manifest import parse_manifest
from fractoscope.v1 import tiles_pb2


def load_manifest(path: str | Path) -> tuple[str, list[tiles_pb2.RoiSpec]]:
    """(specimen id, ROI messages with the images' bytes); InvalidInputError names the bad entry."""
    path = Path(path)
    try:
        text = path.read_bytes()  # JSON's own decoding, whose errors parse_manifest names
    except OSError as error:
        raise InvalidInputError("manifest", f"cannot read {path}: {error.strerror}") from None

    def read_image(name: str, field: str) -> bytes:
        image_path = path.parent / name
        try:
            return image_path.read_bytes()
        except OSError as error:
            raise InvalidInputError(field, f"cannot read {image_path}: {error.strerror}") from None

    return parse_manifest(text, read_image, source=str(path))

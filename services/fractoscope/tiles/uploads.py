"""Uploads of the HTTP API: a manifest and its images, kept until a build takes them."""

from __future__ import annotations

import re
import shutil
import uuid
from http import HTTPStatus
from pathlib import Path

from aiohttp import web

from fractoscope.errors import InvalidInputError, NotFoundError
from fractoscope.rpc.manifest import manifest_field, parse_manifest
from fractoscope.specimen.store import validate_id
from fractoscope.tiles.http_json import ApiError, off_loop
from fractoscope.tiles.http_requests import form_parts, multipart_reader, read_chunk
from fractoscope.tiles.messages import (
    checked_rois,
)
from fractoscope.v1 import tiles_pb2

_FILE_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,127}")


DEFAULT_MAX_UPLOAD_BYTES = 512 * 1024 * 1024


class Uploads:
    """Uploaded manifests and their images under `root/{upload_id}/`, each written in a staging
    folder and renamed into place once complete and valid: never half of one."""

    def __init__(self, root: Path, max_bytes: int):
        self.root = Path(root)
        self.max_bytes = max_bytes
        self.root.mkdir(parents=True, exist_ok=True)
        for leftover in self.root.glob(".staging-*"):
            shutil.rmtree(leftover, ignore_errors=True)

    async def receive(self, request: web.Request) -> tuple[str, str, list[tiles_pb2.RoiSpec]]:
        """Stores a multipart upload (a `manifest` part, `images` parts with the file names the
        manifest gives, optionally `request_id`); returns its id and the manifest's specimen id
        and ROIs."""
        reader = await multipart_reader(request, limit_bytes=self.max_bytes)
        upload_id = uuid.uuid4().hex
        staging = self.root / f".staging-{upload_id}"
        staging.mkdir()
        try:
            await self._receive_parts(reader, staging)
            specimen_id, rois = await off_loop(self._parse, staging)
            staging.rename(self.root / upload_id)
        finally:
            shutil.rmtree(staging, ignore_errors=True)
        return upload_id, specimen_id, rois

    async def _receive_parts(self, reader, staging: Path) -> None:
        total, fields = 0, {}
        async for part in form_parts(reader):
            name = part.name or ""
            if name in ("manifest", "request_id"):
                target, label = staging / f"{name}.field", name
            elif name == "images":
                if not _FILE_NAME.fullmatch(part.filename or ""):
                    raise InvalidInputError(
                        f"images[{part.filename!r}]",
                        "file names are 1 to 128 of A-Z a-z 0-9 . _ -, not starting with . _ -",
                    )
                target, label = staging / "images" / part.filename, f"images[{part.filename!r}]"
                target.parent.mkdir(exist_ok=True)
            else:
                raise InvalidInputError(name or "body", "is not a part of an upload (manifest, request_id, images)")
            if target.exists():
                raise InvalidInputError(label, "is given more than once")
            with open(target, "wb") as out:
                while chunk := await read_chunk(part):
                    total += len(chunk)
                    if total > self.max_bytes:
                        raise ApiError(
                            HTTPStatus.REQUEST_ENTITY_TOO_LARGE, f"the upload exceeds {self.max_bytes} bytes", label
                        )
                    out.write(chunk)
            fields[name] = True
        if "manifest" not in fields:
            raise InvalidInputError("manifest", "is required: the specimen manifest (JSON)")

    def _parse(self, directory: Path) -> tuple[str, list[tiles_pb2.RoiSpec]]:
        def read_image(name: str, field_name: str) -> bytes:
            path = directory / "images" / name
            if not _FILE_NAME.fullmatch(name) or not path.is_file():
                raise InvalidInputError(
                    field_name, f"{name!r} was not uploaded (send each image as a file part named as in the manifest)"
                )
            return path.read_bytes()

        specimen_id, rois = parse_manifest(
            (directory / "manifest.field").read_bytes(), read_image, source="the uploaded manifest"
        )
        validate_id(specimen_id, field="manifest.specimen")
        try:  # what the build would refuse, refused before a job is accepted
            checked_rois(rois)
        except InvalidInputError as error:  # named as the manifest names it
            raise InvalidInputError(manifest_field(error.field), error.message) from None
        return specimen_id, rois

    def load(self, upload_id: str) -> tuple[str, list[tiles_pb2.RoiSpec]]:
        if not re.fullmatch(r"[0-9a-f]{32}", upload_id or ""):
            raise InvalidInputError("upload_id", "is not an upload id (32 hexadecimal digits)")
        directory = self.root / upload_id
        if not directory.is_dir():
            raise NotFoundError(f"no upload {upload_id!r}", field="upload_id")
        return self._parse(directory)

    def field(self, upload_id: str, name: str) -> str:
        path = self.root / upload_id / f"{name}.field"
        return path.read_text(errors="replace")[:128] if path.is_file() else ""

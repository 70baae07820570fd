"""Uploads of the HTTP API: a manifest and its images, checked at receipt as the build will check
them, kept until a build takes them, they are deleted or they expire.

With object storage (replicas sharing a bucket), each upload is also copied to
`uploads/{upload_id}/` there, its `complete` marker written last, so that a build submitted to any
replica finds it: a replica copies it to its own folder when first asked for it."""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import time
import uuid
from collections.abc import Iterator
from http import HTTPStatus
from pathlib import Path
from typing import NamedTuple

from aiohttp import web

from fractoscope.errors import InvalidInputError, NotFoundError
from fractoscope.http.build_jobs import Analyses
from fractoscope.http.inputs import form_parts, multipart_reader, read_chunk
from fractoscope.http.responses import ApiError, off_loop
from fractoscope.matching import messages as rpc_matching
from fractoscope.rpc.limits import MAX_REQUEST_ID_CHARS, MAX_ROIS
from fractoscope.rpc.manifest import manifest_field, parse_manifest
from fractoscope.runtime import budget
from fractoscope.runtime.budget import Cost
from fractoscope.sem.image import read_sem_image
from fractoscope.specimen.model import validate_id
from fractoscope.stereo.inputs import resolve_calibration
from fractoscope.store.objects import S3Objects
from fractoscope.tiles.messages import check_child_centres, checked_rois, in_roi
from fractoscope.v1 import tiles_pb2

_FILE_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,127}")
_UPLOAD_ID = re.compile(r"[0-9a-f]{32}")
# The object written last when an upload is copied to object storage: without it, it is incomplete.
_COMPLETE = "complete"

DEFAULT_MAX_UPLOAD_BYTES = 512 * 1024 * 1024
# Parts of one upload: a manifest, a request id and the images of MAX_ROIS ROIs, a tilt series of
# 15 views each (a part beyond is refused as it comes, before it costs a file).
MAX_UPLOAD_PARTS = 2 + MAX_ROIS * 15
# Long enough to submit a build the next day; short enough that abandoned uploads do not fill the disk.
DEFAULT_MAX_AGE_S = 24 * 3600.0


class Uploads:
    """Uploaded manifests and their images under `root/{upload_id}/`, each written in a staging
    folder and renamed into place once complete and valid: never half of one. Uploads older than
    `max_age_s` (default FRACTO_UPLOAD_MAX_AGE_S, else DEFAULT_MAX_AGE_S) are removed at start and
    whenever an upload is received; until then they are not found. With `objects`, uploads are
    shared through object storage (see the module docstring). Receiving one needs `analyses`,
    under whose budget its images are decoded (and its build's estimate checked first)."""

    def __init__(
        self,
        root: Path,
        max_bytes: int,
        *,
        analyses: Analyses | None = None,
        max_age_s: float | None = None,
        objects: S3Objects | None = None,
    ):
        self.root = Path(root)
        self.max_bytes = max_bytes
        self.analyses = analyses
        self.objects = objects
        if max_age_s is None:
            max_age_s = float(os.environ.get("FRACTO_UPLOAD_MAX_AGE_S", DEFAULT_MAX_AGE_S))
        self.max_age_s = max_age_s
        self.root.mkdir(parents=True, exist_ok=True)
        for leftover in self.root.glob(".staging-*"):
            shutil.rmtree(leftover, ignore_errors=True)
        self.sweep()

    def sweep(self) -> None:
        """Removes the uploads older than max_age_s, here and in object storage."""
        for directory in self.root.iterdir():
            if _UPLOAD_ID.fullmatch(directory.name) and self._expired(directory):
                shutil.rmtree(directory, ignore_errors=True)
        if self.objects is not None:
            newest: dict[str, float] = {}
            for item in self.objects.list("uploads/"):
                upload_id = item.key.split("/")[1]
                newest[upload_id] = max(newest.get(upload_id, 0.0), item.modified_s)
            for upload_id, modified_s in newest.items():
                if modified_s < time.time() - self.max_age_s:
                    self._unshare(upload_id)

    def _expired(self, directory: Path) -> bool:
        """Whether an upload is older than max_age_s: its folder last changed when it was stored."""
        try:
            return directory.stat().st_mtime < time.time() - self.max_age_s
        except FileNotFoundError:  # removed meanwhile: gone is as good as expired
            return True

    async def receive(self, request: web.Request) -> tuple[str, str, list[tiles_pb2.RoiSpec]]:
        """Stores a multipart upload (a `manifest` part, `images` parts with the file names the
        manifest gives, optionally `request_id`); returns its id and the manifest's specimen id
        and ROIs."""
        reader = await multipart_reader(request, limit_bytes=self.max_bytes)
        await off_loop(self.sweep)
        upload_id = uuid.uuid4().hex
        with self._staging() as staging:
            await self._receive_parts(reader, staging)
            specimen_id, rois, shapes = await off_loop(self._parse, staging)  # from the images' headers
            # The images are decoded under the budget, as the build would take them.
            cost = Cost(f"the images of {len(rois)} ROIs", budget.decode_bytes(shapes))
            await self.analyses.run(request, cost, self._check, staging, rois, shapes)
            staging.rename(self.root / upload_id)
        if self.objects is not None:
            await off_loop(self._share, upload_id)
        return upload_id, specimen_id, rois

    def _share(self, upload_id: str) -> None:
        """Copies a stored upload to object storage, its `complete` marker last."""
        directory = self.root / upload_id
        for path in sorted(path for path in directory.rglob("*") if path.is_file()):
            self.objects.put_file(f"uploads/{upload_id}/{path.relative_to(directory).as_posix()}", path)
        self.objects.put(f"uploads/{upload_id}/{_COMPLETE}", b"")

    def _synchronize(self, upload_id: str) -> None:
        """Makes root's copy of an upload agree with object storage: removed when it was deleted
        there (through another replica), copied from there when missing here (through a staging
        folder, renamed into place) if it is complete and unexpired."""
        prefix = f"uploads/{upload_id}/"
        listed = {item.key[len(prefix) :]: item.modified_s for item in self.objects.list(prefix)}
        if _COMPLETE not in listed:
            self._remove_here(upload_id)
            return
        if (self.root / upload_id).is_dir() or listed[_COMPLETE] < time.time() - self.max_age_s:
            return
        with self._staging() as staging:
            for relative in listed.keys() - {_COMPLETE}:
                if not all(_FILE_NAME.fullmatch(part) for part in relative.split("/")):
                    continue  # not a file an upload writes
                target = staging / relative
                target.parent.mkdir(exist_ok=True)
                self.objects.get_file(prefix + relative, target)
            os.utime(staging, (listed[_COMPLETE], listed[_COMPLETE]))  # its age is the upload's
            with contextlib.suppress(OSError):  # fetched by another thread meanwhile
                staging.rename(self.root / upload_id)

    @contextlib.contextmanager
    def _staging(self) -> Iterator[Path]:
        """A new staging folder under root, removed after the block unless the block renamed it
        into place (one a killed process left is removed at start)."""
        staging = self.root / f".staging-{uuid.uuid4().hex}"
        staging.mkdir()
        try:
            yield staging
        finally:
            shutil.rmtree(staging, ignore_errors=True)

    def _unshare(self, upload_id: str) -> bool:
        """Removes an upload from object storage, its marker first; whether it was there."""
        marker = f"uploads/{upload_id}/{_COMPLETE}"
        keys = [item.key for item in self.objects.list(f"uploads/{upload_id}/")]
        if marker in keys:
            self.objects.delete(marker)
        self.objects.delete_many([key for key in keys if key != marker])
        return bool(keys)

    async def _receive_parts(self, reader, staging: Path) -> None:
        total, fields = 0, {}
        async for part in form_parts(reader, max_parts=MAX_UPLOAD_PARTS):
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
            if name == "request_id":
                target.write_text(await _request_id(part), encoding="utf-8")
                continue
            with open(target, "wb") as out:
                while chunk := await read_chunk(part):
                    total += len(chunk)
                    if total > self.max_bytes:
                        raise ApiError(
                            HTTPStatus.REQUEST_ENTITY_TOO_LARGE, f"the upload exceeds {self.max_bytes} bytes", label
                        )
                    await off_loop(out.write, chunk)  # a slow disk must not hold every connection
            fields[name] = True
        if "manifest" not in fields:
            raise InvalidInputError("manifest", "is required: the specimen manifest (JSON)")

    def _check(self, directory: Path, rois: list[tiles_pb2.RoiSpec], shapes: list[tuple[int, int]]) -> None:
        """A received upload (parsed by `_parse`) checked whole: its images as the build will check
        them, and no image part the manifest does not name."""
        named = {item.image.filename for roi in rois for item in roi.images}
        for name in sorted(path.name for path in (directory / "images").iterdir()):
            if name not in named:
                raise InvalidInputError(f"images[{name!r}]", "is not an image the manifest names")
        with _as_manifest_entries(rois):
            _check_images(rois, shapes)

    def _parse(self, directory: Path) -> tuple[str, list[tiles_pb2.RoiSpec], list[tuple[int, int]]]:
        """The specimen id, the ROIs and their images' (rows, cols) of a stored manifest, checked
        from the images' headers, and the build's estimated memory against the budget's limit of
        one request (TooLargeError, as ReconstructSpecimen refuses it), before any is decoded."""

        def read_image(name: str, field_name: str) -> bytes:
            path = directory / "images" / name
            if not _FILE_NAME.fullmatch(name) or not path.is_file():
                raise InvalidInputError(
                    field_name, f"{name!r} was not uploaded (send each image as a file part named as in the manifest)"
                )
            return path.read_bytes()

        specimen_id, rois = parse_manifest(
            (directory / "manifest.field").read_bytes(),
            read_image,
            source="the uploaded manifest",
            max_image_bytes=self.max_bytes,  # the build sends them all in one request
        )
        validate_id(specimen_id, field="manifest.specimen")
        with _as_manifest_entries(rois):  # what the build would refuse, refused before a job is accepted
            _, height_requests, shapes = checked_rois(rois)
            estimate = budget.specimen_bytes(
                shapes, matched_here=[rpc_matching.peak_bytes(request)[0] for request in height_requests]
            )
        rows, cols = max(shapes, key=lambda shape: shape[0] * shape[1])
        if self.analyses is not None:
            self.analyses.budget.check(
                estimate, f"specimen {specimen_id!r} ({len(rois)} ROIs, the largest of {cols} x {rows} pixels)"
            )
        return specimen_id, rois, shapes

    def load(self, upload_id: str) -> tuple[str, list[tiles_pb2.RoiSpec]]:
        specimen_id, rois, _ = self._parse(self._directory(upload_id))
        return specimen_id, rois

    def delete(self, upload_id: str) -> None:
        """Removes an upload, here and in object storage (NotFoundError naming upload_id when
        there is none)."""
        _check_upload_id(upload_id)
        shared = self.objects is not None and self._unshare(upload_id)
        if not self._remove_here(upload_id) and not shared:  # received by another replica, deleted or expired
            raise NotFoundError(f"no upload {upload_id!r}", field="upload_id")

    def _remove_here(self, upload_id: str) -> bool:
        """Removes root's copy of an upload; whether there was one. Renamed first, so that a build
        loading it meanwhile finds all of it or nothing; a leftover of a failed removal is a
        staging folder, removed at start."""
        doomed = self.root / f".staging-deleted-{uuid.uuid4().hex}"
        try:
            (self.root / upload_id).rename(doomed)
        except FileNotFoundError:
            return False
        shutil.rmtree(doomed, ignore_errors=True)
        return True

    def _directory(self, upload_id: str) -> Path:
        _check_upload_id(upload_id)
        directory = self.root / upload_id
        if self.objects is not None:
            self._synchronize(upload_id)
        if not directory.is_dir() or self._expired(directory):
            raise NotFoundError(f"no upload {upload_id!r}", field="upload_id")
        return directory

    def field(self, upload_id: str, name: str) -> str:
        path = self.root / upload_id / f"{name}.field"
        return path.read_text(encoding="utf-8") if path.is_file() else ""


def _check_upload_id(upload_id: str) -> None:
    if not _UPLOAD_ID.fullmatch(upload_id or ""):
        raise InvalidInputError("upload_id", "is not an upload id (32 hexadecimal digits)")


async def _request_id(part) -> str:
    """The `request_id` part's text, held to what gRPC takes: UTF-8 of at most MAX_REQUEST_ID_CHARS."""
    content = bytearray()
    while (chunk := await read_chunk(part)) and len(content) <= 4 * MAX_REQUEST_ID_CHARS:
        content += chunk  # read no further than any such text can take (UTF-8: 4 bytes a character at most)
    try:
        text = content.decode("utf-8")
    except UnicodeDecodeError:
        text = None
    if text is None or len(text) > MAX_REQUEST_ID_CHARS:
        raise InvalidInputError("request_id", f"must be UTF-8 text of at most {MAX_REQUEST_ID_CHARS} characters")
    return text


@contextlib.contextmanager
def _as_manifest_entries(rois: list[tiles_pb2.RoiSpec]):
    """Errors about the fields of a ReconstructSpecimen request of `rois`, named as the manifest's entries."""
    try:
        yield
    except InvalidInputError as error:
        raise InvalidInputError(manifest_field(error.field, rois), error.message) from None


class _FileCalibration(NamedTuple):
    """What the build reads from an image file's metadata (its pixels are not kept)."""

    tilt_deg: float | None
    pixel_size_um: float | None


def _check_images(rois: list[tiles_pb2.RoiSpec], shapes: list[tuple[int, int]]) -> None:
    """Decodes each image once, so that a file the build could not read is refused now, and checks
    what the build takes from them as the matching pipeline resolves it (each ROI's tilts and pixel
    size, given or from its files' metadata: inputs.resolve_calibration), then where given centres
    put the ROIs. Errors name the request's fields."""
    files: dict[str, _FileCalibration] = {}
    for index, roi in enumerate(rois):
        for side, item in enumerate(roi.images):
            if item.image.filename not in files:
                image = read_sem_image(item.image.content, field=f"rois[{index}].images[{side}].image")
                files[item.image.filename] = _FileCalibration(image.tilt_deg, image.pixel_size_um)
    pixel_sizes_um = []
    for index, roi in enumerate(rois):
        tilts = (
            [item.tilt_deg for item in roi.images] if all(item.HasField("tilt_deg") for item in roi.images) else None
        )
        with in_roi(index):
            _, pixel_size_um, _ = resolve_calibration(
                [files[item.image.filename] for item in roi.images],
                tilts,
                roi.pixel_size_um if roi.HasField("pixel_size_um") else None,
            )
        pixel_sizes_um.append(pixel_size_um)
    check_child_centres(rois, shapes, pixel_sizes_um)

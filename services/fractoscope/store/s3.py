"""Specimens in object storage, published crash-safe, shared by any number of tile replicas.

Keys under the store's prefix:
- `builds/{id}/{build}/{sha256}`: a build's files, immutable and content-addressed;
- `builds/{id}/{build}/manifest.json`: {"files": {path in the specimen: sha256}};
- `pointers/{id}.json`: {"build": build id}, the one object a build replaces to publish, by a
  conditional write (If-Match its ETag as read, If-None-Match: * for a first build);
- `leases/{id}.json`: the lease of the replica building it (store.leases).

Readers follow the pointer (looked at again after `pointer_ttl_s`), so they see the old build or
the new one whole. A killed build leaves only objects no pointer names; `sweep` removes those
older than `grace_s`, at start and after each publish of that specimen.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import threading
import time
import uuid
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from fractoscope.errors import NotFoundError
from fractoscope.specimen.model import Specimen, validate_id
from fractoscope.store.base import StoredSpecimens
from fractoscope.store.folder import SpecimenStore
from fractoscope.store.leases import DEFAULT_LEASE_TTL_S, Lease, held
from fractoscope.store.objects import ObjectMissing, PreconditionFailed, S3Objects, open_objects
from fractoscope.store.scratch import remove_abandoned_scratch, scratch_folder

DEFAULT_GRACE_S = 3600.0
DEFAULT_POINTER_TTL_S = 1.0
_UPLOAD_THREADS = 8


class ObjectSpecimenStore(StoredSpecimens):
    """The specimens in `objects`, each replica's loaded ones cached in memory (bounded by the
    specimens it serves); exports', reports' and builds' scratch folders under `scratch_root`
    (local disk: a pod's emptyDir)."""

    def __init__(
        self,
        objects: S3Objects,
        scratch_root: Path,
        *,
        grace_s: float = DEFAULT_GRACE_S,
        pointer_ttl_s: float = DEFAULT_POINTER_TTL_S,
        lease_ttl_s: float = DEFAULT_LEASE_TTL_S,
    ):
        self.objects = objects
        self.scratch_root = Path(scratch_root)
        self.grace_s, self.pointer_ttl_s, self.lease_ttl_s = grace_s, pointer_ttl_s, lease_ttl_s
        self._cache: dict[str, tuple[float, str, Specimen]] = {}  # id: (checked, pointer ETag, specimen)
        self._lock = threading.Lock()
        remove_abandoned_scratch(self.scratch_root)

    def recover(self) -> tuple[list[str], int]:
        """Nothing to restore (a publish is one write); removes what killed builds left."""
        return [], self.sweep()

    def ids(self) -> list[str]:
        return sorted(
            listed.key[len("pointers/") : -len(".json")]
            for listed in self.objects.list("pointers/")
            if listed.key.endswith(".json")
        )

    def load(self, specimen_id: str, *, fresh: bool = False) -> Specimen:
        """The specimen as published: its pointer read again after pointer_ttl_s, or now when `fresh`."""
        validate_id(specimen_id, field="specimen_id")
        now = time.monotonic()
        with self._lock:
            cached = self._cache.get(specimen_id)
        if cached and now - cached[0] < self.pointer_ttl_s and not fresh:
            return cached[2]
        try:
            pointer = self.objects.get(_pointer_key(specimen_id))
        except ObjectMissing:
            with self._lock:
                self._cache.pop(specimen_id, None)
            raise NotFoundError(f"no specimen {specimen_id!r}", field="specimen_id") from None
        if cached and cached[1] == pointer.etag:
            specimen = cached[2]
        else:
            specimen = self._specimen(specimen_id, json.loads(pointer.data)["build"])
        with self._lock:
            self._cache[specimen_id] = (now, pointer.etag, specimen)
        return specimen

    def _specimen(self, specimen_id: str, build: str) -> Specimen:
        """A published build, its files read from the objects its manifest names."""
        prefix = f"builds/{specimen_id}/{build}/"
        files = json.loads(self.objects.get(prefix + "manifest.json").data)["files"]

        def read(relative: str) -> bytes:
            if relative not in files:
                raise FileNotFoundError(relative)
            return self.objects.get(prefix + files[relative]).data

        return Specimen(read, json.loads(read("specimen.json")), version=build)

    def building(self, specimen_id: str) -> contextlib.AbstractContextManager[None]:
        """The specimen's build lease, held for the block (ResourceExhaustedError while another
        replica builds it)."""
        return held(
            Lease(self.objects, f"leases/{specimen_id}.json", what=f"specimen {specimen_id!r}", ttl_s=self.lease_ttl_s)
        )

    @contextlib.contextmanager
    def writing(self, specimen_id: str) -> Iterator[Path]:
        """A local folder to write a specimen into; on success its files become the objects of a
        new build, which is then published. On failure nothing is published."""
        build = f"{time.time_ns():x}-{uuid.uuid4().hex[:12]}"
        with scratch_folder(self.scratch_root, "build") as staging:
            yield staging
            prefix = f"builds/{specimen_id}/{build}/"
            paths = sorted(path for path in staging.rglob("*") if path.is_file())
            with ThreadPoolExecutor(_UPLOAD_THREADS, thread_name_prefix="fractoscope-upload") as pool:
                digests = list(pool.map(lambda path: self._put_content(prefix, path), paths))
            files = {path.relative_to(staging).as_posix(): digest for path, digest in zip(paths, digests, strict=True)}
            self.objects.put(prefix + "manifest.json", json.dumps({"files": files}).encode())
        self._publish(specimen_id, build)
        self.sweep(specimen_id)

    def _put_content(self, prefix: str, path: Path) -> str:
        content = path.read_bytes()
        digest = hashlib.sha256(content).hexdigest()
        self.objects.put(prefix + digest, content)
        return digest

    def _publish(self, specimen_id: str, build: str) -> None:
        """Points `specimen_id` at `build` by a conditional write on the pointer as it was read,
        again when another publish came in between (the later build wins, whole)."""
        record = json.dumps({"build": build}).encode()
        while True:
            try:
                etag = self.objects.get(_pointer_key(specimen_id)).etag
            except ObjectMissing:
                etag = None
            try:
                self.objects.put(_pointer_key(specimen_id), record, if_match=etag, if_absent=etag is None)
                return
            except PreconditionFailed:
                continue

    def delete(self, specimen_id: str) -> None:
        """Unpublishes a specimen at once (its objects go at the next sweep after the grace
        period); NotFoundError naming `specimen_id` when there is none."""
        validate_id(specimen_id, field="specimen_id")
        try:
            self.objects.get(_pointer_key(specimen_id))
        except ObjectMissing:
            raise NotFoundError(f"no specimen {specimen_id!r}", field="specimen_id") from None
        self.objects.delete(_pointer_key(specimen_id))
        with self._lock:
            self._cache.pop(specimen_id, None)

    def sweep(self, specimen_id: str | None = None, *, now_s: float | None = None) -> int:
        """Removes the objects of builds that no pointer names (killed, replaced or deleted ones)
        last written more than grace_s ago, of one specimen or of all; returns how many."""
        now_s = time.time() if now_s is None else now_s
        published = {}
        doomed = []
        for listed in self.objects.list(f"builds/{specimen_id}/" if specimen_id else "builds/"):
            owner, build = listed.key.split("/")[1:3]
            if owner not in published:
                try:
                    published[owner] = json.loads(self.objects.get(_pointer_key(owner)).data)["build"]
                except ObjectMissing:
                    published[owner] = None
            if build != published[owner] and listed.modified_s < now_s - self.grace_s:
                doomed.append(listed.key)
        self.objects.delete_many(doomed)
        return len(doomed)


def _pointer_key(specimen_id: str) -> str:
    return f"pointers/{specimen_id}.json"


def open_specimen_store(url: str | None, data_dir: Path) -> StoredSpecimens:
    """The store `--store` names: `s3://bucket/prefix` (object storage, scratch folders under
    `data_dir`/tmp), or, when empty, the folder store under `data_dir`."""
    if not url:
        return SpecimenStore(data_dir)
    return ObjectSpecimenStore(open_objects(url), Path(data_dir) / "tmp")

"""The specimen store's interface: what the tile service, its HTTP endpoint, builds, exports and
reports ask of a store, whether specimens live in a folder (store.folder) or in object storage
(store.s3)."""

from __future__ import annotations

import abc
import contextlib
from pathlib import Path

from fractoscope.errors import AlreadyExistsError, NotFoundError
from fractoscope.specimen.model import Specimen
from fractoscope.store.objects import S3Objects


class StoredSpecimens(abc.ABC):
    """A store of specimens by id, and what every store does alike over its `load`. `objects` is
    the object storage that replicas share (None: this process alone owns the store);
    `scratch_root` the folder of exports', reports' and builds' scratch folders (store.scratch)."""

    objects: S3Objects | None = None
    scratch_root: Path

    @abc.abstractmethod
    def load(self, specimen_id: str, *, fresh: bool = False) -> Specimen:
        """The stored specimen, with `fresh` as published now rather than as a shared store last
        saw it; NotFoundError naming `specimen_id` when there is none."""

    @abc.abstractmethod
    def ids(self) -> list[str]:
        """The stored specimens' ids, sorted."""

    @abc.abstractmethod
    def writing(self, specimen_id: str) -> contextlib.AbstractContextManager[Path]:
        """A folder to write a specimen into (specimen.model's writers); on success it replaces the
        stored one whole, on failure the stored one stays as it was."""

    @abc.abstractmethod
    def delete(self, specimen_id: str) -> None:
        """Removes a stored specimen at once; NotFoundError naming `specimen_id` when there is none."""

    @abc.abstractmethod
    def recover(self) -> tuple[list[str], int]:
        """Undoes what writes of a killed process left, when the one writer starts; returns the
        restored ids and the number of leftovers removed."""

    def building(self, specimen_id: str) -> contextlib.AbstractContextManager[None]:
        """Held for the whole of one build of `specimen_id`: a process that owns its store builds
        alone, its job runner keeping builds of one request apart."""
        return contextlib.nullcontext()

    def built_by(self, specimen_id: str, request_id: str, digest: str) -> Specimen | None:
        """The stored specimen that a request with `request_id` and content `digest` (a digest of
        the request without its id) built, if any; AlreadyExistsError naming request_id when that
        id built it from other content. A request without an id built nothing."""
        if not request_id:
            return None
        try:
            existing = self.load(specimen_id)
        except NotFoundError:
            return None
        if existing.request_id != request_id:
            return None
        # A specimen built before digests were kept has none: its content cannot be compared.
        if existing.request_digest and existing.request_digest != digest:
            raise AlreadyExistsError(
                f"request_id {request_id!r} built specimen {specimen_id!r} from other content; give this request a "
                "new request_id",
                field="request_id",
            )
        return existing

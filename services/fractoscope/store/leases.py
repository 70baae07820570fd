"""Leases in object storage: one holder at a time, taken and renewed by conditional writes, so
that replicas sharing nothing but a bucket never build one specimen twice at once, and a dead
holder's lease runs out after `ttl_s`."""

from __future__ import annotations

import contextlib
import json
import threading
import time
import uuid
from collections.abc import Iterator

from fractoscope.errors import ResourceExhaustedError
from fractoscope.store.objects import ObjectMissing, PreconditionFailed, S3Objects

DEFAULT_LEASE_TTL_S = 30.0


class LeaseLost(Exception):
    """Another holder took the lease (this one had expired: a renewal came too late)."""


class Lease:
    """The lease object at `key`, held by `holder` while taken: {"holder", "expires_s" (Unix s)}."""

    def __init__(self, objects: S3Objects, key: str, *, what: str, ttl_s: float = DEFAULT_LEASE_TTL_S):
        self._objects, self.key, self._what, self.ttl_s = objects, key, what, ttl_s
        self.holder = uuid.uuid4().hex
        self._etag: str | None = None

    def take(self) -> None:
        """Takes the lease if it is free or expired; ResourceExhaustedError (retry after its
        remaining time) while another holds it."""
        try:
            current = self._objects.get(self.key)
        except ObjectMissing:
            current = None
        if current is not None:
            held = json.loads(current.data)
            remaining_s = held["expires_s"] - time.time()
            if held["holder"] != self.holder and remaining_s > 0:
                raise ResourceExhaustedError(
                    f"{self._what} is being built by another replica; retry in about {remaining_s:.0f} s",
                    retry_after_s=max(remaining_s, 1.0),
                )
        try:
            self._write(if_match=current.etag if current else None)
        except PreconditionFailed:
            raise ResourceExhaustedError(
                f"{self._what} is being built by another replica; retry in about {self.ttl_s:.0f} s",
                retry_after_s=self.ttl_s,
            ) from None

    def renew(self) -> None:
        """Extends the lease by ttl_s; LeaseLost when another holder took it meanwhile."""
        try:
            self._write(if_match=self._etag)
        except PreconditionFailed:
            raise LeaseLost(f"the lease {self.key!r} was taken by another holder") from None

    def release(self) -> None:
        """Gives the lease up, unless another holder has it by now."""
        with contextlib.suppress(ObjectMissing):
            if json.loads(self._objects.get(self.key).data)["holder"] == self.holder:
                self._objects.delete(self.key)

    def _write(self, *, if_match: str | None) -> None:
        record = json.dumps({"holder": self.holder, "expires_s": time.time() + self.ttl_s}).encode()
        self._etag = self._objects.put(self.key, record, if_match=if_match, if_absent=if_match is None)


@contextlib.contextmanager
def held(lease: Lease) -> Iterator[None]:
    """The lease taken for the block, renewed every third of its time on a thread of its own."""
    lease.take()
    stopped = threading.Event()

    def renew() -> None:
        while not stopped.wait(lease.ttl_s / 3):
            with contextlib.suppress(Exception):  # a missed renewal is retried; the next may still come in time
                lease.renew()

    renewer = threading.Thread(target=renew, name="fractoscope-lease", daemon=True)
    renewer.start()
    try:
        yield
    finally:
        stopped.set()
        renewer.join()
        lease.release()

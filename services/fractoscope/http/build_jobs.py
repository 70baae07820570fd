"""Work the HTTP API runs for its callers: reconstructions (ReconstructSpecimen calls on this
server's own gRPC endpoint, followed as jobs) and analyses on a bounded pool.

With a folder store, each job's state is also written to `DATA/jobs/{job_id}.json` as it changes,
so that a job the server was running when it stopped (a kill, a restart) is reported failed
(UNAVAILABLE) after it, as the object store's replicas report one of a stopped replica.

With object storage (a store shared by replicas), each job's state is also written to
`jobs/{job_id}.json` there as it changes, and at least every JOB_LOST_AFTER_S / 6 while it waits or
runs, so any replica answers for a job another one runs; one whose record went unwritten for
JOB_LOST_AFTER_S is reported failed (UNAVAILABLE): the replica that ran it stopped."""

from __future__ import annotations

import asyncio
import json
import logging
import os
import re
import threading
import time
import uuid
from collections import OrderedDict
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from http import HTTPStatus
from pathlib import Path

from aiohttp import web
from google.protobuf import json_format

from fractoscope.errors import FractoscopeError, InvalidInputError, NotFoundError
from fractoscope.http.responses import ApiError
from fractoscope.rpc.channel import open_channel
from fractoscope.rpc.status import ClientError, raised_as_client_errors
from fractoscope.runtime.budget import Budget, Cost
from fractoscope.store.objects import Listed, ObjectMissing, S3Objects, Stored
from fractoscope.store.scratch import process_identity
from fractoscope.v1 import tiles_pb2, tiles_pb2_grpc

# How often a running job's progress is written to object storage at most, s.
_PROGRESS_WRITE_S = 1.0
# How long another replica's unfinished job may go without its record being rewritten before it
# is reported failed, s (its replica rewrites it six times as often).
JOB_LOST_AFTER_S = 60.0
_UNFINISHED = ("queued", "running")
logger = logging.getLogger(__name__)


@dataclass
class HttpBuildJob:
    """A reconstruction submitted over HTTP and what became of it."""

    id: str
    specimen_id: str
    request_id: str
    upload_id: str
    state: str = "queued"  # queued, running, succeeded, failed
    fraction: float = 0.0
    message: str = ""
    created_s: float = field(default_factory=time.time)
    finished_s: float | None = None
    specimen: dict | None = None
    error: dict | None = None
    updated_s: float = field(default_factory=time.time)  # when its record was last written
    process: str | None = None  # the identity of the process that wrote its record (store.scratch)

    def as_dict(self) -> dict:
        return {
            "job_id": self.id,
            "specimen_id": self.specimen_id,
            "request_id": self.request_id,
            "upload_id": self.upload_id,
            "state": self.state,
            "progress": {"fraction": self.fraction, "message": self.message},
            "created": _iso(self.created_s),
            "finished": _iso(self.finished_s) if self.finished_s else None,
            "specimen": self.specimen,
            "error": self.error,
        }

    def record(self) -> bytes:
        """The job as written to object storage now (as_dict with its times in seconds)."""
        self.updated_s = time.time()
        times = {"created_s": self.created_s, "finished_s": self.finished_s, "updated_s": self.updated_s}
        return json.dumps({**self.as_dict(), **times, "process": process_identity(os.getpid())}).encode()

    @classmethod
    def from_record(cls, data: bytes) -> HttpBuildJob:
        record = json.loads(data)
        return cls(
            record["job_id"],
            record["specimen_id"],
            record["request_id"],
            record["upload_id"],
            state=record["state"],
            fraction=record["progress"]["fraction"],
            message=record["progress"]["message"],
            created_s=record["created_s"],
            finished_s=record["finished_s"],
            specimen=record["specimen"],
            error=record["error"],
            updated_s=record.get("updated_s", record["created_s"]),
            process=record.get("process"),
        )

    def lost(self, *, after_s: float, local: bool = False) -> HttpBuildJob:
        """This job as read from a record another process wrote: failed (UNAVAILABLE) when it is
        unfinished and the record went unwritten for `after_s` (another replica's), or, with
        `local` (a record of this host's), its process no longer runs."""
        if self.state not in _UNFINISHED:
            return self
        silent_s = time.time() - self.updated_s
        if local and not _running(self.process):
            self._failed("the server stopped while it ran this job (it was restarted or killed); submit it again")
        elif not local and silent_s > after_s:
            self._failed(f"the replica running this job stopped ({silent_s:.0f} s without word); submit it again")
        return self

    def _failed(self, message: str) -> None:
        self.state, self.finished_s = "failed", self.updated_s
        self.error = {"error": message, "field": None, "code": "UNAVAILABLE"}


def _running(identity: str | None) -> bool:
    """Whether the process of an identity (store.scratch.process_identity) still runs."""
    return identity is not None and process_identity(int(identity.partition(".")[0])) == identity


class FolderRecords:
    """Job records in a local folder (a folder store's data directory), read and written as
    S3Objects' are (`put`, `get`, `list`; ObjectMissing when there is none), each written whole
    by a rename."""

    local = True

    def __init__(self, root: Path):
        self.root = Path(root)

    def put(self, key: str, data: bytes) -> None:
        path = self.root / key
        path.parent.mkdir(parents=True, exist_ok=True)
        staged = path.with_name(f".{path.name}.{uuid.uuid4().hex}")
        staged.write_bytes(data)
        staged.replace(path)

    def get(self, key: str) -> Stored:
        try:
            return Stored((self.root / key).read_bytes(), "")
        except FileNotFoundError:
            raise ObjectMissing(f"no record {key!r}") from None

    def list(self, prefix: str) -> Iterator[Listed]:
        folder = self.root / prefix
        for path in sorted(folder.glob("*.json")) if folder.is_dir() else ():
            yield Listed(f"{prefix}{path.name}", path.stat().st_mtime)


class Analyses:
    """The API's analyses (roughness, profiles, height statistics, exports, reports, the checks of
    uploads) on threads of their own, one for every request the `budget` admits at once (its CPU
    slots and its queue), so that lookups, jobs and the viewer's tiles never wait behind them
    (twelve roughness queries at once once held a specimen lookup for 77 s). Each is admitted
    by the budget first, which refuses at once what cannot fit (413, 429: it is shared with gRPC),
    and stopped when its caller has gone (the request's connection closed). Used from the event
    loop's thread only."""

    def __init__(self, budget: Budget):
        self.budget = budget
        self._pool = ThreadPoolExecutor(
            max_workers=budget.cpu_slots + budget.queue_limit, thread_name_prefix="fractoscope-http-analysis"
        )

    async def run(self, request: web.Request, cost: Cost, function, *args):
        """`function(*args)` admitted as `cost` on the analysis threads, stopped if `request`'s
        client goes away; ResourceExhaustedError (TooLargeError) at once when it does not fit."""
        ticket = self.budget.admit(cost)

        def admitted():
            with ticket.running(stopped=lambda: _gone(request)):
                return function(*args)

        try:
            return await asyncio.get_running_loop().run_in_executor(self._pool, admitted)
        finally:
            ticket.release()  # a no-op once it ran

    def close(self) -> None:
        """Waiting analyses never start; returns once running ones end."""
        self._pool.shutdown(wait=True, cancel_futures=True)


def _gone(request: web.Request) -> bool:
    """Whether the client of a request has closed its connection (read from any thread)."""
    transport = request.transport
    return transport is None or transport.is_closing()


class BuildJobs:
    """Builds submitted over HTTP, each a ReconstructSpecimen call on `address` (this server's gRPC
    endpoint) with the submitter's token, at most `workers` at once and `queue_limit` waiting
    (more get 429); the last `keep` jobs stay queryable here, and in `objects` (object storage,
    or FolderRecords) all of them: in object storage for every replica, another replica's
    unfinished job reported failed once its record went unwritten for `lost_after_s`; in a folder
    for later processes, which report an unfinished job of a process gone as failed."""

    def __init__(
        self,
        address: str | None,
        *,
        workers: int,
        queue_limit: int,
        keep: int = 1000,
        timeout_s: float = 3600.0,
        objects: S3Objects | FolderRecords | None = None,
        lost_after_s: float = JOB_LOST_AFTER_S,
    ):
        self.address = address
        self.objects = objects
        self.queue_limit = queue_limit
        self.timeout_s = timeout_s
        self._pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="fractoscope-http-build")
        self._jobs: OrderedDict[str, HttpBuildJob] = OrderedDict()
        self._finished: OrderedDict[str, HttpBuildJob] = OrderedDict()  # other replicas' (_stored)
        self._keep = keep
        self._lock = threading.Lock()
        self._calls: set = set()  # the ReconstructSpecimen calls under way, cancelled by close()
        self.lost_after_s = lost_after_s
        self._closed = threading.Event()
        if objects is not None and not getattr(objects, "local", False):
            threading.Thread(target=self._keep_records_fresh, name="fractoscope-job-records", daemon=True).start()

    @property
    def enabled(self) -> bool:
        return self.address is not None

    def submit(self, specimen_id: str, rois, *, request_id: str, token: str | None, upload_id: str) -> HttpBuildJob:
        with self._lock:
            waiting = sum(job.state == "queued" for job in self._jobs.values())
            if waiting >= self.queue_limit:
                raise ApiError(
                    HTTPStatus.TOO_MANY_REQUESTS,
                    f"{waiting} builds are waiting; retry later",
                    None,
                    **{"Retry-After": "30"},
                )
            job = HttpBuildJob(uuid.uuid4().hex, specimen_id, request_id, upload_id)
            self._jobs[job.id] = job
            while len(self._jobs) > self._keep:
                self._jobs.popitem(last=False)
        self._write(job)
        self._pool.submit(self._run, job, rois, token)
        return job

    def _write(self, job: HttpBuildJob) -> None:
        """The job's state to its record (when it has one), for the other replicas or the next
        process. A store out of reach costs only their view of it: the job goes on, and an
        unfinished one's record is written again within lost_after_s / 6 (_keep_records_fresh)."""
        if self.objects is None:
            return
        try:
            self.objects.put(f"jobs/{job.id}.json", job.record())
        except (FractoscopeError, OSError) as error:  # OSError: a folder's disk full
            logger.warning("job %s: its record could not be written: %s", job.id, error)

    def _stored(self, job_id: str) -> HttpBuildJob | None:
        """Another replica's job as its record in object storage tells it (see HttpBuildJob.lost),
        None when there is none. Finished records never change: each is read once and kept (the
        last `keep` of them)."""
        with self._lock:
            job = self._finished.get(job_id)
        if job is not None:
            return job
        try:
            job = HttpBuildJob.from_record(self.objects.get(f"jobs/{job_id}.json").data)
        except ObjectMissing:
            return None
        if job.state not in _UNFINISHED:
            with self._lock:
                self._finished[job_id] = job
                while len(self._finished) > self._keep:
                    self._finished.popitem(last=False)
        return job.lost(after_s=self.lost_after_s, local=getattr(self.objects, "local", False))

    def listed(self) -> list[HttpBuildJob]:
        """Every job known here and, with object storage, every replica's, oldest first."""
        with self._lock:
            jobs = dict(self._jobs)
        if self.objects is not None:
            for listed in self.objects.list("jobs/"):
                job_id = listed.key[len("jobs/") : -len(".json")]
                if job_id not in jobs and (job := self._stored(job_id)) is not None:
                    jobs[job_id] = job
        return sorted(jobs.values(), key=lambda job: job.created_s)

    def get(self, job_id: str) -> HttpBuildJob:
        if not re.fullmatch(r"[0-9a-f]{32}", job_id):
            raise InvalidInputError("job_id", "is not a job id (32 hexadecimal digits)")
        with self._lock:
            job = self._jobs.get(job_id)
        if job is None and self.objects is not None:  # another replica's
            job = self._stored(job_id)
        if job is None:
            raise NotFoundError(f"no job {job_id!r}", field="job_id")
        return job

    def close(self) -> None:
        """Queued jobs never start; running ones are cancelled; returns once their threads end."""
        self._closed.set()
        self._pool.shutdown(wait=False, cancel_futures=True)
        with self._lock:
            calls = list(self._calls)
        for call in calls:
            call.cancel()
        self._pool.shutdown(wait=True)

    def _keep_records_fresh(self) -> None:
        """Rewrites this replica's unfinished jobs' records, so that other replicas know it lives."""
        while not self._closed.wait(self.lost_after_s / 6):
            with self._lock:
                unfinished = [job for job in self._jobs.values() if job.state in _UNFINISHED]
            for job in unfinished:
                self._write(job)

    def _run(self, job: HttpBuildJob, rois, token: str | None) -> None:
        job.state = "running"
        self._write(job)
        written_s = time.monotonic()
        request = tiles_pb2.ReconstructSpecimenRequest(
            specimen_id=job.specimen_id, rois=rois, request_id=job.request_id
        )
        call = None
        try:
            with open_channel(self.address, token=token) as channel, raised_as_client_errors():
                call = tiles_pb2_grpc.TileServiceStub(channel).ReconstructSpecimen(request, timeout=self.timeout_s)
                with self._lock:
                    self._calls.add(call)
                for response in call:
                    if response.HasField("progress"):
                        job.fraction, job.message = response.progress.fraction, response.progress.message
                        if time.monotonic() - written_s > _PROGRESS_WRITE_S:
                            self._write(job)
                            written_s = time.monotonic()
                    else:
                        job.specimen = json_format.MessageToDict(
                            response.specimen,
                            preserving_proto_field_name=True,
                            always_print_fields_with_no_presence=True,
                        )
            job.state, job.fraction = ("succeeded", 1.0) if job.specimen is not None else ("failed", job.fraction)
            if job.specimen is None:
                job.error = {"error": "the build ended without a specimen", "field": None, "code": "INTERNAL"}
        except ClientError as error:
            job.state = "failed"
            job.error = {"error": str(error), "field": error.field, "code": error.code.name}
        finally:
            job.finished_s = time.time()
            with self._lock:
                self._calls.discard(call)
            self._write(job)


def _iso(seconds: float) -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(seconds))

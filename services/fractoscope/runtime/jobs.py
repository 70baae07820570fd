"""Long calls (specimen builds, height maps, meshes, strips) as jobs: each kind runs on a bounded
pool of worker threads of its own with a bounded queue, never on the threads that answer calls.

A call follows its job: it streams the job's progress and ends with its result. Calls with the
same key (a request id) follow one job. A full queue answers RESOURCE_EXHAUSTED with a retry hint.
When every call following a job has gone (cancelled, or past its deadline), the job is cancelled:
a queued job never starts, a running one stops at its next progress report (cooperatively; the
work's own outgoing calls are cancelled through `Job.on_cancel`).
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Callable, Hashable, Iterator
from typing import Any

import grpc

from fractoscope.errors import CancelledError, ResourceExhaustedError
from fractoscope.v1 import common_pb2

_FINISHED, _GONE = object(), object()
# The retry hint before any job has finished, s.
_FIRST_GUESS_S = 10.0


class Job:
    """One piece of work and the calls following it. The work gets the job: `progress` is its
    progress callback (raising CancelledError once the job is cancelled), `on_cancel` registers
    what else to stop, `time_remaining_s` bounds the deadlines of the calls it makes."""

    def __init__(self, key: Hashable | None, work: Callable[[Job], Any], lock: threading.Lock):
        self.key = key
        self._work = work
        self._lock = lock  # the runner's, which guards every job's followers
        self._followers: list[_Follower] = []
        self._cancelled = threading.Event()
        self._on_cancel: list[Callable[[], Any]] = []
        self._last: common_pb2.Progress | None = None
        self._outcome: tuple[bool, Any] | None = None  # (succeeded, result or exception)
        self._started = False

    def progress(self, fraction: float, message: str) -> None:
        """Reports progress to every follower; raises CancelledError once the job is cancelled."""
        if self._cancelled.is_set():
            raise CancelledError("every caller of this job went away")
        event = common_pb2.Progress(stage=message.split(" ", 1)[0], fraction=float(fraction), message=message)
        with self._lock:
            self._last = event
            followers = list(self._followers)
        for follower in followers:
            follower.events.put(event)

    def on_cancel(self, callback: Callable[[], Any]) -> None:
        """Calls `callback` when the job is cancelled (at once if it already is)."""
        with self._lock:
            if not self._cancelled.is_set():
                self._on_cancel.append(callback)
                return
        callback()

    def time_remaining_s(self, *, at_most_s: float) -> float:
        """Seconds until the last follower's deadline, at most `at_most_s`."""
        with self._lock:
            deadline = max((follower.deadline for follower in self._followers), default=time.monotonic())
        return min(max(deadline - time.monotonic(), 0.0), at_most_s)

    @property
    def cancelled(self) -> bool:
        return self._cancelled.is_set()

    def _run(self) -> None:
        try:
            outcome = (True, self._work(self))
        except BaseException as error:  # handed to the followers, which re-raise it
            outcome = (False, error)
        with self._lock:
            self._outcome = outcome
            followers, self._followers = self._followers, []
        for follower in followers:
            follower.events.put(_FINISHED)

    def _attach(self, follower: _Follower) -> None:
        """Under the runner's lock."""
        if self._outcome is not None:  # finished just now, before its runner let go of it
            follower.events.put(_FINISHED)
            return
        self._followers.append(follower)
        if self._last is not None:
            follower.events.put(self._last)

    def _detach(self, follower: _Follower) -> bool:
        """Under the runner's lock; True when that was the last follower of an unfinished job,
        which is then cancelled (see `_stop`)."""
        if follower in self._followers:
            self._followers.remove(follower)
        if self._followers or self._outcome is not None:
            return False
        self._cancelled.set()
        return True

    def _stop(self) -> None:
        """Outside the lock, after `_detach` returned True: stops what the work registered."""
        with self._lock:
            callbacks, self._on_cancel = self._on_cancel, []
        for callback in callbacks:
            callback()


class _Follower:
    def __init__(self, deadline: float):
        self.deadline = deadline
        self.events: queue.SimpleQueue = queue.SimpleQueue()


class JobRunner:
    """Runs jobs of one kind (`name`, as messages call them) on `workers` daemon threads of its
    own, at most `queue_limit` waiting; at most `max_followers` calls follow them at once (calls
    that join a running job count too)."""

    def __init__(self, name: str, *, workers: int, queue_limit: int):
        if workers < 1 or queue_limit < 0:
            raise ValueError(f"{name}: workers must be >= 1 and queue_limit >= 0, got {workers} and {queue_limit}")
        self.name = name
        self.workers = workers
        self.queue_limit = queue_limit
        self.max_followers = 4 * (workers + queue_limit)  # room for calls that join a job
        self._queue: queue.SimpleQueue[Job] = queue.SimpleQueue()
        self._lock = threading.Lock()
        self._keyed: dict[Hashable, Job] = {}
        self._waiting = 0
        self._followers = 0
        self._mean_s = _FIRST_GUESS_S
        for index in range(workers):
            threading.Thread(target=self._serve, name=f"fractoscope-{name}-{index}", daemon=True).start()

    def follow(
        self, context: grpc.ServicerContext, work: Callable[[Job], Any], *, key: Hashable | None = None
    ) -> Iterator[Any]:
        """Runs `work(job)` as a job, or joins the running job of `key`, at once; raises
        ResourceExhaustedError when the queue or the followers are full. The iterator it returns
        (iterate it to its end) yields a Progress message for each report and finally the work's
        result, or raises what the work raised; it ends early when the call does."""
        follower = _Follower(time.monotonic() + context.time_remaining())
        job = self._attach(follower, work, key)
        return self._events(context, follower, job)

    def _events(self, context: grpc.ServicerContext, follower: _Follower, job: Job) -> Iterator[Any]:
        try:
            if not context.add_callback(lambda: follower.events.put(_GONE)):
                return  # the call ended already
            while (event := follower.events.get()) is not _FINISHED:
                if event is _GONE:
                    return  # nobody listens any more; the finally below lets go of the job
                yield event
            succeeded, value = job._outcome
            if not succeeded:
                raise value
            yield value
        finally:
            self._detach(follower, job)

    def result(self, context: grpc.ServicerContext, work: Callable[[Job], Any], *, key: Hashable | None = None) -> Any:
        """`follow` for unary calls: the work's result, progress left out."""
        outcome = None
        for outcome in self.follow(context, work, key=key):  # noqa: B007 - the last one is the result
            pass
        if outcome is None or isinstance(outcome, common_pb2.Progress):
            raise CancelledError("the call ended before its job")
        return outcome

    def _attach(self, follower: _Follower, work, key) -> Job:
        with self._lock:
            if self._followers >= self.max_followers:
                raise ResourceExhaustedError(
                    f"{self._followers} calls already wait on this server's {self.name}; retry later",
                    retry_after_s=self._retry_after_s(),
                )
            job = self._keyed.get(key) if key is not None else None
            if job is None or job.cancelled:
                if self._waiting >= self.queue_limit:
                    raise ResourceExhaustedError(
                        f"the server's queue of {self.name} is full ({self.workers} running, {self._waiting} "
                        f"waiting); retry in about {self._retry_after_s():.0f} s",
                        retry_after_s=self._retry_after_s(),
                    )
                job = Job(key, work, self._lock)
                self._waiting += 1
                if key is not None:
                    self._keyed[key] = job
                self._queue.put(job)
            job._attach(follower)
            self._followers += 1
            return job

    def _detach(self, follower: _Follower, job: Job) -> None:
        with self._lock:
            self._followers -= 1
            cancelled = job._detach(follower)
            if cancelled and not job._started:  # its place in the queue is free at once
                self._waiting -= 1
                self._forget(job)
        if cancelled:
            job._stop()

    def _serve(self) -> None:
        while True:
            job = self._queue.get()
            with self._lock:
                if job.cancelled and not job._started:
                    continue  # counted out when it was cancelled
                self._waiting -= 1
                job._started = True
            started = time.monotonic()
            job._run()
            with self._lock:
                self._forget(job)
                self._mean_s = 0.8 * self._mean_s + 0.2 * (time.monotonic() - started)

    def _forget(self, job: Job) -> None:
        """Under the lock: later calls with its key start a new job."""
        if job.key is not None and self._keyed.get(job.key) is job:
            del self._keyed[job.key]

    def _retry_after_s(self) -> float:
        """When a place in the queue is likely to free up: a typical job's time over the workers."""
        return min(max(self._mean_s / self.workers, 1.0), 600.0)

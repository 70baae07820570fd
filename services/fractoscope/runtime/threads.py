"""Which threads answer which calls: health checks on a pool of their own, calls that follow jobs
(see jobs) on theirs, analyses (admitted by the budget, see budget) on theirs, everything else
on the server's workers. However many builds wait, however many analyses run and however busy
the tiles are, a health check and a tile find a free thread."""

from __future__ import annotations

from collections.abc import Iterable
from concurrent.futures import ThreadPoolExecutor

import grpc

HEALTH_PREFIX = "/grpc.health.v1.Health/"
_HEALTH_THREADS = 2


class ThreadPoolRouting(grpc.ServerInterceptor):
    """Routes health checks to their own threads, the methods in `job_methods` to
    `job_call_threads` threads (enough for every call the job runners admit, plus some to refuse
    the rest quickly) and those in `analysis_methods` to `analysis_threads` (likewise for what
    the budget admits). gRPC Python runs a method on the pool its behavior names in
    `experimental_thread_pool`, else on the server's."""

    def __init__(
        self,
        job_methods: Iterable[str],
        *,
        job_call_threads: int,
        analysis_methods: Iterable[str] = (),
        analysis_threads: int = 1,
    ):
        health = ThreadPoolExecutor(max_workers=_HEALTH_THREADS, thread_name_prefix="fractoscope-health")
        job_calls = ThreadPoolExecutor(max_workers=job_call_threads, thread_name_prefix="fractoscope-job-call")
        analyses = ThreadPoolExecutor(max_workers=analysis_threads, thread_name_prefix="fractoscope-analysis")
        self._pools = {method: job_calls for method in job_methods} | {method: analyses for method in analysis_methods}
        self._health = health
        self._routed: dict[str, grpc.RpcMethodHandler] = {}

    def intercept_service(self, continuation, handler_call_details):
        method = handler_call_details.method
        pool = self._health if method.startswith(HEALTH_PREFIX) else self._pools.get(method)
        if pool is None:
            return continuation(handler_call_details)
        routed = self._routed.get(method)
        if routed is None:
            handler = continuation(handler_call_details)
            if handler is None:
                return None
            routed = self._routed[method] = _on_pool(handler, pool)
        return routed


def _on_pool(handler: grpc.RpcMethodHandler, pool: ThreadPoolExecutor) -> grpc.RpcMethodHandler:
    """The same handler, its behavior run on `pool`."""
    name = {
        (False, False): "unary_unary",
        (False, True): "unary_stream",
        (True, False): "stream_unary",
        (True, True): "stream_stream",
    }[(handler.request_streaming, handler.response_streaming)]
    behavior = getattr(handler, name)

    def routed(*args):
        return behavior(*args)

    routed.experimental_thread_pool = pool
    return handler._replace(**{name: routed})

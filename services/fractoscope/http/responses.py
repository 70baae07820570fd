"""The HTTP API's answers: JSON bodies and errors ({"error": message, "field": the input at fault
or null}, with the status errors.OUTCOMES gives a failure), and files streamed out in chunks."""

from __future__ import annotations

import asyncio
import errno
import math
from collections.abc import Callable
from http import HTTPStatus
from pathlib import Path

from aiohttp import web

from fractoscope import strict_json
from fractoscope.errors import FractoscopeError, outcome_of
from fractoscope.store.scratch import scratch_folder

JSON_TYPE = "application/json"


CORS_HEADERS = {
    "Access-Control-Allow-Origin": "*",
    "Access-Control-Expose-Headers": "ETag, Content-Encoding, Content-Disposition, Location",
}


CHUNK_BYTES = 1 << 20


class ApiError(Exception):
    """An answer other than success: its status, message, the field at fault and extra headers."""

    def __init__(self, status: HTTPStatus, message: str, field: str | None = None, **headers: str):
        super().__init__(message)
        self.status, self.message, self.field, self.headers = status, message, field, headers


async def off_loop(function, *args):
    return await asyncio.get_running_loop().run_in_executor(None, function, *args)


def failure_response(error: FractoscopeError) -> web.Response:
    """A failure as the HTTP status errors.OUTCOMES gives it, naming the field at fault."""
    retry_after_s = getattr(error, "retry_after_s", None)
    headers = {"Retry-After": str(math.ceil(retry_after_s))} if retry_after_s is not None else {}
    return json_error(HTTPStatus(outcome_of(error).http_status), str(error), getattr(error, "field", None), **headers)


def unexpected_response(error: Exception) -> web.Response:
    """An exception not raised on purpose, named by its class only (its message is for the log):
    507 when the disk or the quota is full, else 500."""
    if isinstance(error, OSError) and error.errno in (errno.ENOSPC, errno.EDQUOT):
        return json_error(HTTPStatus.INSUFFICIENT_STORAGE, "the server's disk is full; retry later", None)
    return json_error(HTTPStatus.INTERNAL_SERVER_ERROR, f"internal error ({type(error).__name__})", None)


def no_content() -> web.Response:
    return web.Response(status=HTTPStatus.NO_CONTENT, headers={**CORS_HEADERS, "Cache-Control": "no-store"})


def json_response(value, *, status: HTTPStatus = HTTPStatus.OK, **headers: str) -> web.Response:
    body = strict_json.dumps(value).encode()
    return web.Response(
        status=status,
        body=body,
        headers={**CORS_HEADERS, "Content-Type": JSON_TYPE, "Cache-Control": "no-store", **headers},
    )


def json_error(status: HTTPStatus, message: str, field: str | None, **headers: str) -> web.Response:
    """An error in the API's format: {"error": message, "field": the request field it names or null}."""
    return json_response({"error": message, "field": field}, status=status, **headers)


async def file_response(
    request: web.Request, run, write: Callable[[Path], tuple[Path, str]], *, scratch_root: Path
) -> web.StreamResponse:
    """A file written by `write(directory)` (on threads by `await run(function, *args)`, into a
    scratch folder under `scratch_root`: a store's scratch_root, whose leftovers of killed
    processes a store's start removes) and streamed out in chunks, so memory stays bounded; the
    folder goes once it is sent."""
    with scratch_folder(scratch_root, "fractoscope-http") as directory:
        path, media_type = await run(write, directory)
        response = web.StreamResponse(
            headers={
                **CORS_HEADERS,
                "Content-Type": media_type,
                "Content-Length": str(path.stat().st_size),
                "Cache-Control": "no-store",
                "Content-Disposition": f'attachment; filename="{path.name}"',
            }
        )
        await response.prepare(request)
        if request.method != "HEAD":
            with open(path, "rb") as source:  # read off the event loop: a file of gigabytes may come from a slow disk
                while chunk := await off_loop(source.read, CHUNK_BYTES):
                    await response.write(chunk)
        await response.write_eof()
        return response

"""The HTTP API's answers: JSON bodies and errors ({"error": message, "field": the input at fault
or null}, with the status errors.OUTCOMES gives a failure), and files streamed out in chunks."""

from __future__ import annotations

import asyncio
import math
import shutil
import tempfile
from collections.abc import Callable
from http import HTTPStatus
from pathlib import Path

from aiohttp import web

from fractoscope import strict_json
from fractoscope.errors import FractoscopeError, outcome_of

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


async def file_response(request: web.Request, run, write: Callable[[Path], tuple[Path, str]]) -> web.StreamResponse:
    """A file written by `write(directory)` (on threads by `await run(function, *args)`, into a
    temporary folder) and streamed out in chunks, so memory stays bounded; the folder goes once it
    is sent."""
    directory = Path(tempfile.mkdtemp(prefix="fractoscope-http-"))
    try:
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
            with open(path, "rb") as source:
                while chunk := source.read(CHUNK_BYTES):
                    await response.write(chunk)
        await response.write_eof()
        return response
    finally:
        shutil.rmtree(directory, ignore_errors=True)

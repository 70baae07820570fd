"""The HTTP API's inputs: query parameters, JSON bodies and multipart forms, each checked before
use, with errors that name the parameter, field or part at fault."""

from __future__ import annotations

import io
import json
import lzma
import math
import zipfile
import zlib
from http import HTTPStatus

import numpy as np
from aiohttp import BodyPartReader, web
from aiohttp.http_exceptions import HttpProcessingError
from numpy.lib import format as npy_format

from fractoscope.errors import InvalidInputError
from fractoscope.http.responses import CHUNK_BYTES, ApiError
from fractoscope.rpc import wire
from fractoscope.sem import image as sem_image
from fractoscope.specimen import queries
from fractoscope.tiles import messages
from fractoscope.v1 import tiles_pb2


def query_parameters(request: web.Request, known: set[str]) -> dict[str, str]:
    """The query's parameters (`token` aside), each given once and known."""
    values = {}
    for name in request.query.keys():
        if name == "token":
            continue
        if name not in known:
            raise InvalidInputError(
                name or "query",
                f"{'an unnamed parameter ' if not name else ''}is not a parameter "
                f"here{'; known: ' + ', '.join(sorted(known)) if known else ''}",
            )
        given = request.query.getall(name)
        if len(given) > 1:
            raise InvalidInputError(name, "is given more than once")
        values[name] = given[0]
    return values


def numbers(values: dict, name: str, count: int) -> list[float]:
    """`name=a,b,...` as `count` finite numbers."""
    if name not in values:
        raise InvalidInputError(name, "is required")
    try:
        numbers = [float(v) for v in values[name].split(",")]
    except (ValueError, AttributeError):
        numbers = []
    if len(numbers) != count or not all(math.isfinite(v) for v in numbers):
        raise InvalidInputError(name, f"must be {count} comma-separated finite numbers")
    return numbers


def number(values: dict, name: str, *, default: float | None = None, minimum: float | None = None) -> float | None:
    if name not in values:
        if default is None:
            raise InvalidInputError(name, "is required")
        return default
    value = numbers(values, name, 1)[0]
    if minimum is not None and value < minimum:
        raise InvalidInputError(name, f"must be at least {minimum:g}")
    return value


def choice(values: dict, name: str, choices: tuple[str, ...], *, default: str | None = None) -> str:
    value = values.get(name, default)
    if value not in choices:
        raise InvalidInputError(
            name, f"must be one of {', '.join(choices)}" if name in values or default is None else "is required"
        )
    return value


def flag(values: dict, name: str) -> bool:
    return choice(values, name, ("true", "false"), default="false") == "true"


# The surface texture chain's query parameters, SurfaceChain's fields; profiles take the first three.
PROFILE_CHAIN_PARAMETERS = messages.PROFILE_CHAIN_FIELDS
CHAIN_PARAMETERS = wire.CHAIN_FIELDS


def chain_request(values: dict) -> queries.ChainRequest:
    """The chain's settings among the query's parameters, decoded into the SurfaceChain of the
    gRPC requests and checked as those are (absent ones stay at their defaults)."""
    chain = tiles_pb2.SurfaceChain()
    for name in (name for name in CHAIN_PARAMETERS if name in values):
        field = chain.DESCRIPTOR.fields_by_name[name]
        if name == "form":
            chain.form = wire.FORMS[choice(values, "form", tuple(wire.FORMS))]
        elif name == "levelling_region":
            chain.levelling_region.CopyFrom(wire.region_message(numbers(values, name, 4)))
        elif field.type == field.TYPE_BOOL:
            setattr(chain, name, flag(values, name))
        else:
            setattr(chain, name, numbers(values, name, 1)[0])
    return messages.chain_request(chain, field="")


def area_of(values: dict) -> dict:
    """roi= or region= (not both); neither: the overview."""
    if "roi" in values and "region" in values:
        raise InvalidInputError("region", "give roi or region, not both")
    region = queries.checked_region(numbers(values, "region", 4)) if "region" in values else None
    return {"roi": values.get("roi"), "region_um": region}


def export_options(values: dict) -> dict:
    """The export's settings among the parameters, decoded into the ExportRequest of the gRPC API
    and read as its settings are (`messages.export_options`)."""
    pixel_size_um = number(values, "pixel_size_um", default=0.0, minimum=0.0)
    request = tiles_pb2.ExportRequest(
        format=wire.EXPORT_FORMATS[choice(values, "format", tuple(wire.EXPORT_FORMATS))],
        pixel_size_um=pixel_size_um,
        solid=flag(values, "solid"),
        units=wire.LENGTH_UNITS[choice(values, "units", tuple(wire.LENGTH_UNITS), default="um")],
    )
    return messages.export_options(request)


async def json_body(request: web.Request, *, limit_bytes: int) -> dict:
    raw = await request.content.read(limit_bytes + 1)
    if len(raw) > limit_bytes:
        raise ApiError(HTTPStatus.REQUEST_ENTITY_TOO_LARGE, f"a JSON body of at most {limit_bytes} bytes", "body")
    try:
        body = json.loads(raw)
    except (ValueError, RecursionError) as error:  # ValueError: bad JSON, bad UTF-8, integers of > 4300 digits
        raise InvalidInputError("body", f"is not JSON: {error}") from None
    if not isinstance(body, dict):
        raise InvalidInputError("body", "must be a JSON object")
    return body


async def small_form(request: web.Request, *, files: set[str], fields: set[str], limit_bytes: int) -> dict:
    """A multipart form held in memory: the `fields` as str, the `files` parts as bytes."""
    form, total = {}, 0
    parts = form_parts(await multipart_reader(request, limit_bytes=limit_bytes), max_parts=len(files | fields) + 1)
    async for part in parts:
        name = part.name or ""
        if name not in files | fields:
            raise InvalidInputError(name or "body", f"is not a part of this form ({', '.join(sorted(files | fields))})")
        if name in form:
            raise InvalidInputError(name, "is given more than once")
        content = bytearray()
        while chunk := await read_chunk(part):
            total += len(chunk)
            if total > limit_bytes:
                raise ApiError(HTTPStatus.REQUEST_ENTITY_TOO_LARGE, f"the request exceeds {limit_bytes} bytes", name)
            content += chunk
        if name in files:
            form[name] = bytes(content)
        else:
            try:
                form[name] = content.decode("utf-8")
            except UnicodeDecodeError:
                raise InvalidInputError(name, "must be UTF-8 text") from None
    return form


async def form_parts(reader, *, max_parts: int):
    """The parts of a multipart body, at most `max_parts` of them (413 for more: each costs a
    file or a buffer, and parsing them all would hold the event loop); a malformed one, or a
    nested multipart body (multipart/mixed), is the caller's error, not ours."""
    count = 0
    while True:
        try:
            part = await reader.next()
        except (HttpProcessingError, ValueError, AssertionError, LookupError) as error:
            raise InvalidInputError("body", f"is not valid multipart/form-data: {first_line(error)}") from None
        if part is None:
            return
        if not isinstance(part, BodyPartReader):
            raise InvalidInputError(
                "body",
                f"part {count + 1} is itself multipart ({part.headers.get('Content-Type')}); "
                "send each file as a part of its own",
            )
        count += 1
        if count > max_parts:
            raise ApiError(
                HTTPStatus.REQUEST_ENTITY_TOO_LARGE,
                f"the body has more than {max_parts} parts",
                "body",
                Connection="close",
            )
        yield part


async def read_chunk(part) -> bytes:
    try:
        return await part.read_chunk(CHUNK_BYTES)
    except (HttpProcessingError, ValueError, AssertionError, LookupError) as error:
        raise InvalidInputError(part.name or "body", f"is not valid multipart/form-data: {first_line(error)}") from None


def first_line(error: Exception) -> str:
    return (str(error).strip().splitlines() or [type(error).__name__])[0][:200]


# What a multipart body may carry besides its parts' contents: boundaries and part headers.
_MULTIPART_FRAMING_BYTES = 1024 * 1024


async def multipart_reader(request: web.Request, *, limit_bytes: int):
    """The reader of a multipart body whose parts may hold `limit_bytes` in all: a Content-Length
    beyond that is refused (413) before anything is read."""
    if request.content_type != "multipart/form-data":
        raise ApiError(HTTPStatus.UNSUPPORTED_MEDIA_TYPE, "send multipart/form-data", "content-type")
    if (request.content_length or 0) > limit_bytes + _MULTIPART_FRAMING_BYTES:
        raise ApiError(
            HTTPStatus.REQUEST_ENTITY_TOO_LARGE,
            f"a body of {request.content_length} bytes exceeds the {limit_bytes} allowed",
            "body",
            Connection="close",
        )  # the body is not read
    try:
        return await request.multipart()
    except (ValueError, AssertionError, KeyError) as error:
        raise InvalidInputError("body", f"is not multipart/form-data: {error}") from None


# What reading a damaged or foreign zip archive or .npy array may raise.
_UNREADABLE_NPZ = (
    OSError,
    ValueError,
    KeyError,
    TypeError,
    EOFError,
    RuntimeError,  # an encrypted member
    NotImplementedError,  # a compression method zipfile lacks
    zipfile.BadZipFile,
    zlib.error,
    lzma.LZMAError,
)
# The arrays of a height map's npz that are read (the others, such as its record, are not).
_HEIGHT_MAP_ARRAYS = ("z_um", "sigma_um", "pixel_size_um")
_NPY_HEADER_READERS = {(1, 0): npy_format.read_array_header_1_0, (2, 0): npy_format.read_array_header_2_0}


# What an uploaded map's arrays take once decoded, per point: z_um and sigma_um as float64 at most.
NPZ_BYTES_PER_POINT = 16


def npz_shape(content: bytes | None) -> tuple[int, int]:
    """The (rows, cols) of an uploaded npz's z_um, from the .npy headers alone (see
    _check_npz_headers), for estimates before anything is decoded."""
    if not content:
        raise InvalidInputError("height_map", "is required: an .npz with z_um (as fracto height writes it)")
    if not content.startswith(b"PK"):  # npz files are zip archives; np.load would try a pickle
        raise InvalidInputError(
            "height_map", "is not an npz file (a zip archive with z_um, as fracto height writes it)"
        )
    shape = _check_npz_headers(content)
    return (shape[0] if shape else 1), math.prod(shape[1:])


def npz_height_map(content: bytes | None) -> tuple[np.ndarray, np.ndarray | None, float | None]:
    """z_um (and sigma_um, pixel_size_um if stored) of an uploaded npz, as `fracto height` writes it;
    its arrays are checked from their headers before any is read (see npz_shape)."""
    npz_shape(content)
    try:
        with np.load(io.BytesIO(content), allow_pickle=False) as arrays:
            z_um = np.asarray(arrays["z_um"])
            sigma_um = np.asarray(arrays["sigma_um"]) if "sigma_um" in arrays.files else None
            stored = float(arrays["pixel_size_um"]) if "pixel_size_um" in arrays.files else None
    except _UNREADABLE_NPZ as error:
        raise InvalidInputError("height_map", f"is not an npz with z_um: {first_line(error)}") from None
    return z_um, sigma_um, stored


def _check_npz_headers(content: bytes) -> tuple[int, ...]:
    """Refuses, from the .npy headers alone, an npz that np.load would allocate too much for (an
    array of more values than an image may have pixels, sem.image.MAX_IMAGE_PIXELS: 413; a header
    may declare any shape in a few bytes) or that is not a height map (400); z_um's shape."""
    limit = sem_image.MAX_IMAGE_PIXELS
    headers = _npy_headers(content)
    for name, shape, dtype in headers:
        if math.prod(shape) > limit:
            raise ApiError(
                HTTPStatus.REQUEST_ENTITY_TOO_LARGE,
                f"height_map's {name} array is {'x'.join(map(str, shape[::-1]))} (width x height), more than the "
                f"{limit} pixels an image may have (FRACTO_MAX_IMAGE_PIXELS)",
                "height_map",
            )
        if name in _HEIGHT_MAP_ARRAYS and dtype.kind not in "fiu":
            raise InvalidInputError("height_map", f"its {name} array holds {dtype}, not real numbers")
    shapes = {name: shape for name, shape, _ in headers}
    if "z_um" not in shapes:
        raise InvalidInputError("height_map", "holds no z_um array (as fracto height writes it)")
    return tuple(shapes["z_um"])


def _npy_headers(content: bytes) -> list[tuple[str, tuple[int, ...], np.dtype]]:
    """Each member of a zip archive as (name without .npy, shape, dtype), read from its .npy header only."""
    headers = []
    try:
        with zipfile.ZipFile(io.BytesIO(content)) as archive:
            for info in archive.infolist():
                with archive.open(info) as member:
                    version = npy_format.read_magic(member)
                    if version not in _NPY_HEADER_READERS:
                        raise ValueError(f"{info.filename} is a .npy file of version {version}, not 1.0 or 2.0")
                    shape, _, dtype = _NPY_HEADER_READERS[version](member)
                headers.append((info.filename.removesuffix(".npy"), shape, dtype))
    except _UNREADABLE_NPZ as error:
        raise InvalidInputError("height_map", f"is not an npz of .npy arrays: {first_line(error)}") from None
    return headers

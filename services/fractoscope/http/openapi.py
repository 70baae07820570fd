"""The OpenAPI 3.1 document of the HTTP/JSON API (api), served at /api/openapi.json."""

from __future__ import annotations

import functools
from importlib import metadata

from fractoscope.formats.exports import EXPORT_FORMATS
from fractoscope.http import openapi_schemas

_ID = "^[A-Za-z0-9_-]{1,64}$"
_NUMBER = r"-?[0-9]+(\.[0-9]+)?([eE][-+]?[0-9]+)?"
_REGION = f"^{_NUMBER},{_NUMBER},{_NUMBER},{_NUMBER}$"
_POINT = f"^{_NUMBER},{_NUMBER}$"
_ERRORS = {
    "400": "A parameter or the body is invalid; `field` names it.",
    "401": "A valid bearer token is required (when the server has tokens).",
    "403": "The token may only read.",
    "404": "The specimen, ROI, upload or job does not exist; `field` names what named it.",
    "414": "The request target (path and query) is too long; `field` is `url`.",
    "507": "The server's disk is full.",
}


def _error_responses(*codes: str, **extra: str) -> dict:
    described = {code: _ERRORS[code] for code in (*codes, "414")} | extra
    return {
        code: {"description": text, "content": {"application/json": {"schema": {"$ref": "#/components/schemas/Error"}}}}
        for code, text in described.items()
    }


def _query(name: str, description: str, schema: dict, *, required: bool = False) -> dict:
    return {"name": name, "in": "query", "required": required, "description": description, "schema": schema}


def _path_id(name: str, description: str, pattern: str) -> dict:
    return {
        "name": name,
        "in": "path",
        "required": True,
        "description": description,
        "schema": {"type": "string", "pattern": pattern},
    }


_SPECIMEN_ID = _path_id("specimen_id", "Specimen id.", _ID)
_UPLOAD_ID = _path_id("upload_id", "Upload id.", "^[0-9a-f]{32}$")
_ROI = _query("roi", "ROI id (default: the overview ROI).", {"type": "string", "pattern": _ID})
_AREA_REGION = _query(
    "region",
    "Region X0,Y0,X1,Y1 of the fused surface, µm in the specimen frame (not with roi).",
    {"type": "string", "pattern": _REGION},
)


_CUTOFF = {"type": "number", "minimum": 0}
_CHAIN = [
    _query(
        "form",
        "Form removed first (default plane).",
        {
            "type": "string",
            "enum": ["none", "plane", "poly2", "poly3", "poly4", "poly5", "poly6", "sphere", "cylinder"],
        },
    ),
    _query("s_filter_um", "S-filter cut-off λs, µm (0: none).", _CUTOFF),
    _query("l_filter_um", "L-filter cut-off λc, µm (0: none).", _CUTOFF),
    _query(
        "direction_deg", "Direction of the 'along' Hurst exponents, degrees from +x (default 0).", {"type": "number"}
    ),
    _query(
        "levelling_region",
        "Region X0,Y0,X1,Y1 µm the form is fitted on (default: all).",
        {"type": "string", "pattern": _REGION},
    ),
    _query(
        "window_px",
        "The matcher's smoothing width in the analysed map's pixels (default: its matching window).",
        {"type": "number", "minimum": 1, "maximum": 1000},
    ),
    _query(
        "min_windows", "The Hurst fit starts this many windows up.", {"type": "number", "minimum": 0.5, "maximum": 100}
    ),
    _query("robust_form", "Fit the form robustly.", {"type": "string", "enum": ["true", "false"]}),
]


def _json_ok(description: str, schema_ref: str) -> dict:
    return {
        "200": {
            "description": description,
            "content": {"application/json": {"schema": {"$ref": f"#/components/schemas/{schema_ref}"}}},
        }
    }


def _file_ok(description: str, media_types: list[str]) -> dict:
    return {
        "200": {
            "description": description,
            "headers": {"Content-Disposition": {"schema": {"type": "string"}}},
            "content": {media: {"schema": {"type": "string", "format": "binary"}} for media in media_types},
        }
    }


_EXPORT_MEDIA = list(dict.fromkeys(export_format.media_type for export_format in EXPORT_FORMATS.values()))
_EXPORT_OPTIONS = [
    _query("format", "File format.", {"type": "string", "enum": list(EXPORT_FORMATS)}, required=True),
    _query(
        "pixel_size_um",
        "Grid step of the export, µm (default: the source's own; a region's is the finest there).",
        {"type": "number", "exclusiveMinimum": 0},
    ),
    _query(
        "solid", "Meshes: close the surface into a watertight block.", {"type": "string", "enum": ["true", "false"]}
    ),
    _query("units", "Meshes: coordinate unit.", {"type": "string", "enum": ["um", "mm"]}),
]


@functools.cache
def document() -> dict:
    try:
        version = metadata.version("fractoscope-services")
    except metadata.PackageNotFoundError:
        version = "0"
    return {
        "openapi": "3.1.0",
        "info": {
            "title": "Fractoscope HTTP API",
            "version": version,
            "description": "Specimens, reconstructions and their jobs, roughness, profiles, zoom, exports and "
            "measurement reports. Lengths are µm in the specimen frame (x right, y down). Errors are JSON with the "
            "field at fault. With tokens on the server, send `Authorization: Bearer TOKEN` (or `?token=`): read "
            "tokens query, write tokens upload and build.",
        },
        "servers": [{"url": "/"}],
        "security": [{"bearer": []}, {"token": []}, {}],
        "paths": _paths(),
        "components": {
            "schemas": openapi_schemas.schemas(),
            "securitySchemes": {
                "bearer": {"type": "http", "scheme": "bearer"},
                "token": {"type": "apiKey", "in": "query", "name": "token"},
            },
        },
    }


_BUSY = {"413": "More than this server takes at all (memory, file).", "429": "Busy; retry after Retry-After s."}


def _specimen_get(operation_id: str, summary: str, parameters: list, ok: dict, *, analysis: bool = False) -> dict:
    """A GET on a specimen: its id in the path, `parameters` in the query; an `analysis` runs under
    the server's budget (413 when it can never fit, 429 when it cannot now)."""
    return {
        "get": {
            "operationId": operation_id,
            "summary": summary,
            "parameters": [_SPECIMEN_ID, *parameters],
            "responses": ok | _error_responses("400", "401", "404", **(_BUSY if analysis else {})),
        }
    }


def _delete(operation_id: str, summary: str, parameter: dict) -> dict:
    """A DELETE of the resource `parameter` names: write scope, 204 or 404."""
    return {
        "delete": {
            "operationId": operation_id,
            "summary": summary,
            "parameters": [parameter],
            "responses": {"204": {"description": "Deleted."}} | _error_responses("400", "401", "403", "404"),
        }
    }


def _paths() -> dict:
    """Every path of the API with its operations."""
    return _document_path() | _specimen_paths() | _specimen_area_paths() | _upload_paths() | _job_paths()


def _document_path() -> dict:
    """This document, public (no token needed)."""
    ok = {
        "200": {
            "description": "The OpenAPI 3.1 document.",
            "content": {"application/json": {"schema": {"type": "object"}}},
        }
    }
    return {
        "/api/openapi.json": {
            "get": {
                "operationId": "getOpenApi",
                "summary": "This document.",
                "security": [],
                "responses": ok | _error_responses(),
            }
        }
    }


def _specimen_paths() -> dict:
    """Specimens, their roughness and profiles."""
    point = {"type": "string", "pattern": _POINT}
    return {
        "/api/specimens": {
            "get": {
                "operationId": "listSpecimens",
                "summary": "The stored specimens, sorted by id.",
                "responses": _json_ok("The specimens.", "SpecimenList") | _error_responses("400", "401"),
            }
        },
        "/api/specimens/{specimen_id}": _specimen_get(
            "getSpecimen",
            "One specimen: its ROIs, their placement, calibration and matching report.",
            [],
            _json_ok("The specimen.", "Specimen"),
        )
        | _delete("deleteSpecimen", "Deletes a stored specimen, its tiles included.", _SPECIMEN_ID),
        "/api/specimens/{specimen_id}/roughness": _specimen_get(
            "getRoughness",
            "The ISO 25178 chain (form removal, S- and L-filters): every ISO 25178-2 parameter with its "
            "uncertainty, Hurst exponents by h(r) and PSD along and across a direction, the areal PSD, the chain "
            "used.",
            [_ROI, _AREA_REGION, *_CHAIN],
            _json_ok("The parameters by ISO name, the fits and the chain.", "Roughness"),
            analysis=True,
        ),
        "/api/specimens/{specimen_id}/profile": _specimen_get(
            "getProfile",
            "The fused surface along a line; its roughness profile (form removed, ISO 21920-3 S- and L-filters) and "
            "ISO 21920-2 parameters.",
            [
                _query("from", "Start X,Y, µm.", point, required=True),
                _query("to", "End X,Y, µm.", point, required=True),
                _query(
                    "magnification",
                    "Sample at this magnification (default: the finest data).",
                    {"type": "number", "minimum": 0},
                ),
                _query(
                    "spacing_um", "Sample spacing, µm (default: the pixel size used).", {"type": "number", "minimum": 0}
                ),
                *_CHAIN[:3],
            ],
            _json_ok("The profile.", "Profile"),
            analysis=True,
        ),
    }


def _specimen_area_paths() -> dict:
    """Heights, zoom, exports and reports of a specimen area."""
    return {
        "/api/specimens/{specimen_id}/heights": _specimen_get(
            "getHeightStatistics",
            "Mean, median, standard deviation and extremes of the measured heights in a region.",
            [
                _query(
                    "region",
                    "Region X0,Y0,X1,Y1, µm (X0 = X1 and Y0 = Y1: a point).",
                    {"type": "string", "pattern": _REGION},
                    required=True,
                )
            ],
            _json_ok("The statistics.", "HeightStatistics"),
            analysis=True,
        ),
        "/api/specimens/{specimen_id}/zoom": _specimen_get(
            "zoom",
            "The tiles that show a region at a magnification, optical or digital.",
            [
                _query("region", "Region X0,Y0,X1,Y1, µm.", {"type": "string", "pattern": _REGION}, required=True),
                _query(
                    "magnification", "Wanted magnification.", {"type": "number", "exclusiveMinimum": 0}, required=True
                ),
            ],
            _json_ok("The tiles.", "Zoom"),
        ),
        "/api/specimens/{specimen_id}/export": _specimen_get(
            "exportArea",
            "An ROI or a region as X3P, float32 TIFF, CSV, or an STL, PLY or OBJ mesh.",
            [_ROI, _AREA_REGION, *_EXPORT_OPTIONS],
            _file_ok("The file, streamed.", _EXPORT_MEDIA),
            analysis=True,
        ),
        "/api/specimens/{specimen_id}/report": _specimen_get(
            "getReport",
            "The measurement report of an ROI or a region, HTML or PDF.",
            [
                _ROI,
                _AREA_REGION,
                _query("format", "html (default) or pdf.", {"type": "string", "enum": ["html", "pdf"]}),
            ],
            _file_ok("The report.", ["text/html; charset=utf-8", "application/pdf"]),
            analysis=True,
        ),
        "/api/specimens/{specimen_id}/thumbnail": _specimen_get(
            "getThumbnail", "The overview's SEM image, 160 px wide.", [], _file_ok("A PNG.", ["image/png"])
        ),
    }


def _upload_paths() -> dict:
    """Height maps sent for export, and uploads."""
    return {
        "/api/exports": {
            "post": {
                "operationId": "exportHeightMap",
                "summary": "A height map sent as an npz (z_um, optional sigma_um and pixel_size_um) as a file.",
                "requestBody": {
                    "required": True,
                    "content": {"multipart/form-data": {"schema": {"$ref": "#/components/schemas/ExportForm"}}},
                },
                "responses": _file_ok("The file, streamed.", _EXPORT_MEDIA)
                | _error_responses(
                    "400",
                    "401",
                    "404",
                    **{
                        "413": "The body, the map (pixels) or its export (memory, file) is more than the server takes.",
                        "415": "The body is not multipart/form-data.",
                    },
                    **{"429": _BUSY["429"]},
                ),
            }
        },
        "/api/uploads": {
            "post": {
                "operationId": "upload",
                "summary": "Stores a specimen manifest with its images for builds to refer to.",
                "requestBody": {
                    "required": True,
                    "content": {"multipart/form-data": {"schema": {"$ref": "#/components/schemas/UploadForm"}}},
                },
                "responses": {
                    "201": {
                        "description": "Stored.",
                        "headers": {"Location": {"schema": {"type": "string"}}},
                        "content": {"application/json": {"schema": {"$ref": "#/components/schemas/Upload"}}},
                    }
                }
                | _error_responses(
                    "400",
                    "401",
                    "403",
                    "507",
                    **{"413": "Too large a body or build.", "415": "Not multipart/form-data.", "429": _BUSY["429"]},
                ),
            }
        },
        "/api/uploads/{upload_id}": _delete("deleteUpload", "Deletes a stored upload.", _UPLOAD_ID),
    }


def _job_paths() -> dict:
    """Reconstruction jobs."""
    return {
        "/api/jobs": {
            "get": {
                "operationId": "listJobs",
                "summary": "Every build job, oldest first: with object storage, those of every replica.",
                "responses": _json_ok("The jobs.", "JobList") | _error_responses("400", "401"),
            },
            "post": {
                "operationId": "submitJob",
                "summary": "Builds a specimen: from a stored upload (JSON) or from a manifest and images sent along "
                "(multipart).",
                "requestBody": {
                    "required": True,
                    "content": {
                        "application/json": {"schema": {"$ref": "#/components/schemas/JobRequest"}},
                        "multipart/form-data": {"schema": {"$ref": "#/components/schemas/UploadForm"}},
                    },
                },
                "responses": {
                    "202": {
                        "description": "Accepted; follow it at Location.",
                        "headers": {"Location": {"schema": {"type": "string"}}},
                        "content": {"application/json": {"schema": {"$ref": "#/components/schemas/Job"}}},
                    }
                }
                | _error_responses(
                    "400",
                    "401",
                    "403",
                    "404",
                    "507",
                    **{
                        "413": "The body is too large.",
                        "415": "Neither JSON nor multipart/form-data.",
                        "429": "Too many builds are waiting; retry after Retry-After seconds.",
                        "503": "This endpoint runs no builds.",
                    },
                ),
            },
        },
        "/api/jobs/{job_id}": {
            "get": {
                "operationId": "getJob",
                "summary": "A build's state and progress, and its specimen once it succeeded.",
                "parameters": [_path_id("job_id", "Job id.", "^[0-9a-f]{32}$")],
                "responses": _json_ok("The job.", "Job") | _error_responses("400", "401", "404"),
            }
        },
    }

"""The components schemas of the OpenAPI document (openapi): the bodies the HTTP API answers
with and the forms it takes."""

from __future__ import annotations

from fractoscope.formats.exports import EXPORT_FORMATS


def schemas() -> dict:
    """The components schemas the paths refer to."""
    return _specimen_schemas() | _query_schemas() | _form_schemas() | _job_schemas()


def _specimen_schemas() -> dict:
    """Errors, specimens and roughness."""
    number_or_null = {"type": ["number", "null"]}
    return {
        "Error": {
            "type": "object",
            "required": ["error", "field"],
            "properties": {
                "error": {"type": "string", "description": "What is wrong."},
                "field": {
                    "type": ["string", "null"],
                    "description": "The input at fault (parameter, body field or header).",
                },
            },
        },
        "Specimen": {
            "type": "object",
            "required": ["id", "rois", "tileset_uri"],
            "properties": {
                "id": {"type": "string"},
                "tileset_uri": {"type": "string"},
                "rois": {
                    "type": "array",
                    "items": {"type": "object", "required": ["id", "parent", "pixel_size_um", "region", "matching"]},
                },
            },
        },
        "SpecimenList": {"type": "array", "items": {"$ref": "#/components/schemas/Specimen"}},
        "Roughness": {
            "type": "object",
            "required": ["Sa", "Sq", "Sz", "units", "uncertainty", "chain", "pixel_size_um", "hurst", "psd"],
            "additionalProperties": {"type": ["number", "null", "array", "object", "string"]},
            "properties": {
                "units": {"type": "object", "additionalProperties": {"type": "string"}},
                "uncertainty": {
                    "type": "object",
                    "additionalProperties": {
                        "type": "object",
                        "properties": {
                            "u_total": number_or_null,
                            "u_tilt": number_or_null,
                            "u_noise": number_or_null,
                        },
                    },
                },
                "chain": {"type": "object"},
                "pixel_size_um": {"type": "number"},
                "noise_bias": {"type": "object", "additionalProperties": number_or_null},
                "tilt_rel_uncertainty": number_or_null,
                "hurst": {"type": "array", "items": {"type": "object"}},
                "hurst_note": {"type": "string"},
                "psd": {"type": "object", "properties": {"q_per_um": {"type": "array"}, "c_um4": {"type": "array"}}},
            },
        },
    }


def _query_schemas() -> dict:
    """Profiles, height statistics and zoom."""
    number_or_null = {"type": ["number", "null"]}
    return {
        "Profile": {
            "type": "object",
            "required": ["distance_um", "z_um", "source", "parameters"],
            "properties": {
                "distance_um": {"type": "array", "items": {"type": "number"}},
                "z_um": {"type": "array", "items": number_or_null},
                "source": {"type": "array", "items": {"type": "string"}},
                "parameters": {"type": ["object", "null"], "additionalProperties": number_or_null},
                "roughness_um": {"type": ["array", "null"], "items": number_or_null},
                "chain": {"type": ["object", "null"]},
            },
        },
        "HeightStatistics": {
            "type": "object",
            "required": [
                "mean_um",
                "median_um",
                "std_um",
                "min_um",
                "max_um",
                "count",
                "measured_fraction",
                "pixel_size_um",
            ],
            "properties": {
                **{name: number_or_null for name in ("mean_um", "median_um", "std_um", "min_um", "max_um")},
                "count": {"type": "integer"},
                "measured_fraction": {"type": "number"},
                "pixel_size_um": {"type": "number"},
            },
        },
        "Zoom": {
            "type": "object",
            "required": ["tiles"],
            "properties": {
                "tiles": {
                    "type": "array",
                    "items": {
                        "type": "object",
                        "required": ["uri", "roi", "magnification", "zoom"],
                        "properties": {
                            "uri": {"type": "string"},
                            "roi": {"type": "string"},
                            "magnification": {"type": "number"},
                            "zoom": {"type": "string", "enum": ["optical", "digital"]},
                            "geometric_error_m": {"type": "number"},
                        },
                    },
                }
            },
        },
    }


def _form_schemas() -> dict:
    """The multipart forms of exports and uploads."""
    return {
        "ExportForm": {
            "type": "object",
            "required": ["height_map", "format"],
            "additionalProperties": False,
            "properties": {
                "height_map": {
                    "type": "string",
                    "contentMediaType": "application/octet-stream",
                    "description": "An .npz with z_um (rows, cols) µm; sigma_um and pixel_size_um optional.",
                },
                "format": {"type": "string", "enum": list(EXPORT_FORMATS)},
                "map_pixel_size_um": {
                    "type": "string",
                    "description": "The map's pixel size, µm, when the npz stores none.",
                },
                "pixel_size_um": {"type": "string", "description": "Grid step of the export, µm (default: the map's)."},
                "solid": {"type": "string", "enum": ["true", "false"]},
                "units": {"type": "string", "enum": ["um", "mm"]},
            },
        },
        "UploadForm": {
            "type": "object",
            "required": ["manifest"],
            "additionalProperties": False,
            "properties": {
                "manifest": {
                    "type": "string",
                    "contentMediaType": "application/json",
                    "description": "The specimen manifest (as `fracto reconstruct` reads it); images by file name.",
                },
                "request_id": {"type": "string", "maxLength": 128},
                "images": {
                    "type": "array",
                    "items": {"type": "string", "contentMediaType": "application/octet-stream"},
                    "description": "The image files, each a part whose file name the manifest gives.",
                },
            },
        },
    }


def _job_schemas() -> dict:
    """Uploads and reconstruction jobs."""
    return {
        "Upload": {
            "type": "object",
            "required": ["upload_id", "specimen_id", "rois"],
            "properties": {
                "upload_id": {"type": "string"},
                "specimen_id": {"type": "string"},
                "rois": {"type": "array", "items": {"type": "string"}},
            },
        },
        "JobRequest": {
            "type": "object",
            "required": ["upload_id"],
            "additionalProperties": False,
            "properties": {
                "upload_id": {"type": "string", "pattern": "^[0-9a-f]{32}$"},
                "request_id": {"type": "string", "maxLength": 128},
            },
        },
        "JobList": {
            "type": "object",
            "required": ["jobs"],
            "properties": {"jobs": {"type": "array", "items": {"$ref": "#/components/schemas/Job"}}},
        },
        "Job": {
            "type": "object",
            "required": ["job_id", "specimen_id", "state", "progress"],
            "properties": {
                "job_id": {"type": "string"},
                "specimen_id": {"type": "string"},
                "request_id": {"type": "string"},
                "upload_id": {"type": "string"},
                "state": {"type": "string", "enum": ["queued", "running", "succeeded", "failed"]},
                "progress": {
                    "type": "object",
                    "properties": {"fraction": {"type": "number"}, "message": {"type": "string"}},
                },
                "created": {"type": "string"},
                "finished": {"type": ["string", "null"]},
                "specimen": {"oneOf": [{"$ref": "#/components/schemas/Specimen"}, {"type": "null"}]},
                "error": {"oneOf": [{"$ref": "#/components/schemas/Error"}, {"type": "null"}]},
            },
        },
    }

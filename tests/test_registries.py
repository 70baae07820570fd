"""Each list of names has one registry, which the API's enum names alike; every other list (the
OpenAPI document, the CLI's choices, the error messages) is derived from them. These tests fail
when one drifts: a format, method or mode added in one place and not in another."""

from __future__ import annotations

import dataclasses
import re

import numpy as np
import pytest

from fractoscope import report
from fractoscope.cli.main import build_parser
from fractoscope.client import _matching_method, _relief_sign_mode
from fractoscope.errors import InvalidInputError
from fractoscope.formats import exports
from fractoscope.http import inputs as http_inputs
from fractoscope.http import openapi
from fractoscope.matching import messages as matching_messages
from fractoscope.rpc import wire
from fractoscope.specimen import queries
from fractoscope.stereo import matching
from fractoscope.stereo.inputs import MatchingOptions, validate_options
from fractoscope.stereo.relief_sign import ReliefSignMode
from fractoscope.tiles import messages as tiles_messages
from fractoscope.v1 import matching_pb2, tiles_pb2


def _enum_names(enum, prefix: str) -> list[str]:
    """The API enum's value names, UNSPECIFIED aside, without `prefix`, lower case."""
    return [name.removeprefix(prefix).lower() for name, code in enum.items() if code]


def _listed(message: str, *, after: str) -> list[str]:
    """The comma-separated names an error message lists after `after` (quotes, dots and leading
    underscores, as in '.x3p' or '_TIFF', stripped; lower case)."""
    listed = message.split(after, 1)[1].split(", got")[0].split(" (")[0].split(";")[0]
    return [re.sub(r"^[\W_]+|\W+$", "", name).lower() for name in listed.split(",")]


def _cli_choices(verb: str, flag: str) -> list[str]:
    commands = next(action for action in build_parser()._actions if action.dest == "command")
    option = next(action for action in commands.choices[verb]._actions if flag in action.option_strings)
    return list(option.choices)


def _openapi_enums(parameter: str) -> list[list[str]]:
    """The enums of every query parameter and form property named `parameter` in the document."""
    document = openapi.document()
    found = [
        item["schema"]["enum"]
        for path in document["paths"].values()
        for operation in path.values()
        for item in operation.get("parameters", [])
        if item["name"] == parameter and "enum" in item["schema"]
    ]
    found += [
        schema["properties"][parameter]["enum"]
        for schema in document["components"]["schemas"].values()
        if "enum" in schema.get("properties", {}).get(parameter, {})
    ]
    return found


def _message_of(call, *args) -> str:
    with pytest.raises((InvalidInputError, ValueError)) as raised:
        call(*args)
    return str(raised.value)


def test_export_formats_are_one_list():
    names = list(exports.EXPORT_FORMATS)
    api = _enum_names(tiles_pb2.ExportFormat, "EXPORT_FORMAT_")
    assert [{"tiff": "tif"}.get(name, name) for name in api] == names == list(wire.EXPORT_FORMATS)
    # The export route's and the upload export form's; the report's are its own.
    export_enums = [enum for enum in _openapi_enums("format") if enum != list(report.MEDIA_TYPES)]
    assert len(export_enums) == 2 and all(enum == names for enum in export_enums)
    media = openapi.document()["paths"]["/api/specimens/{specimen_id}/export"]["get"]["responses"]["200"]["content"]
    assert set(media) == {export_format.media_type for export_format in exports.EXPORT_FORMATS.values()}
    assert _listed(_message_of(wire.export_format_of, "a.bad"), after="is none of") == names
    listed = _listed(_message_of(wire.export_format_name, 99), after="must be one of")
    assert [name.removeprefix("export_format_") for name in listed] == api
    bad_write = _message_of(lambda: exports.write_surface("a.bad", "bad", np.zeros((2, 2)), pixel_size_um=1.0))
    assert _listed(bad_write, after="is none of [") == names
    assert _listed(_message_of(lambda: http_inputs.export_options({"format": "bad"})), after="one of") == names


def test_matching_methods_are_one_list():
    names = list(matching.METHODS)
    assert _enum_names(matching_pb2.MatchingMethod, "MATCHING_METHOD_") == names == list(wire.method_names())
    assert _cli_choices("height", "--method") == [name.replace("_", "-") for name in names]
    assert _listed(_message_of(matching_messages.method_from_message, 99), after="known:") == names
    assert _listed(_message_of(_matching_method, "bad"), after="one of") == names
    bad = MatchingOptions(method="bad")
    assert _listed(_message_of(lambda: validate_options(bad, image_cols=64)), after="one of") == names


def test_relief_sign_modes_are_one_list():
    names = [mode.value for mode in ReliefSignMode]
    assert _enum_names(matching_pb2.ReliefSignMode, "RELIEF_SIGN_MODE_") == names == list(wire.relief_sign_names())
    assert _cli_choices("height", "--relief-sign") == names
    assert _listed(_message_of(matching_messages.relief_sign_from_message, 99), after="known:") == names
    assert _listed(_message_of(_relief_sign_mode, "bad"), after="one of") == names


def _route_parameters(path: str) -> list[str]:
    return [item["name"] for item in openapi.document()["paths"][path]["get"]["parameters"]]


def _cli_dests(verb: str) -> list[str]:
    commands = next(action for action in build_parser()._actions if action.dest == "command")
    return [action.dest for action in commands.choices[verb]._actions]


def test_the_roughness_chain_fields_are_one_list():
    """SurfaceChain's fields are the chain's settings everywhere: ChainRequest (levelling_region
    with its unit), the HTTP API's query parameters and the CLI's flags."""
    fields = list(tiles_pb2.SurfaceChain.DESCRIPTOR.fields_by_name)
    core = [field.name for field in dataclasses.fields(queries.ChainRequest)]
    assert [name.removesuffix("_um") if name == "levelling_region_um" else name for name in core] == fields
    assert list(wire.CHAIN_FIELDS) == fields == list(http_inputs.CHAIN_PARAMETERS)
    roughness = _route_parameters("/api/specimens/{specimen_id}/roughness")
    assert [name for name in roughness if name in fields] == fields == roughness[-len(fields) :]
    profile = tuple(name for name in _route_parameters("/api/specimens/{specimen_id}/profile") if name in fields)
    assert profile == tiles_messages.PROFILE_CHAIN_FIELDS == http_inputs.PROFILE_CHAIN_PARAMETERS
    assert set(fields) <= set(_cli_dests("roughness"))
    assert {name for name in _cli_dests("profile") if name in fields} == set(profile)

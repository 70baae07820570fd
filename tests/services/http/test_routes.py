"""The HTTP API's routes and the OpenAPI document's operations are the same set: a route missing
from the document, or an operation no route answers, fails here."""

from __future__ import annotations

import re

from fractoscope.http import api, openapi


def _template(pattern: re.Pattern) -> str:
    """A route's pattern as an OpenAPI path: named groups as {name}, escapes dropped."""
    return re.sub(r"\(\?P<(\w+)>[^)]*\)", r"{\1}", pattern.pattern).replace("\\", "")


def test_every_route_is_in_the_document_and_every_operation_is_a_route():
    routes = {(route.method, _template(route.pattern)) for route in api._ROUTES}
    operations = {
        (method.upper(), path) for path, operations in openapi.document()["paths"].items() for method in operations
    }
    assert routes == operations

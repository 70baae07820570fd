"""The external tools some tests run (validators, servers, a browser, poppler, curl): `make test`
installs them; a test run without one skips the tests that need it, naming the tool and the make
target that installs it, instead of failing."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

REPOSITORY = Path(__file__).resolve().parents[1]


def required_tool(tool: str, make_target: str) -> str:
    """The path of `tool` (a path in the repository, such as .tools/bin/kustomize, or a command
    on PATH), or a skip naming it and the make target that installs it."""
    path = REPOSITORY / tool
    found = str(path) if "/" in tool and path.is_file() else shutil.which(tool)
    if found is None:
        pytest.skip(f"{tool} is not installed: `make {make_target}` (or `make test`) installs it")
    return found

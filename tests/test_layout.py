"""The repository's layout as the product's design fixes it: proto/, services/, clients/, tests/,
deploy/ at the top and no src/; no import cycle between packages; modules and functions short
enough to read (argument parsers aside)."""

import ast
from pathlib import Path

import grimp
import pytest

ROOT = Path(__file__).resolve().parents[1]
SOURCES = [ROOT / "services", ROOT / "clients" / "python", ROOT / "clients" / "cli"]
MAX_MODULE_LINES = 600
MAX_FUNCTION_LINES = 60
# Functions that only declare a command line's flags may be as long as the flags are many.
PARSER_FUNCTIONS = {"build_parser", "add_parsers"}


def test_top_level_is_the_designed_one():
    for name in ("proto", "services", "clients", "tests", "deploy", "Makefile"):
        assert (ROOT / name).exists(), name
    assert not (ROOT / "src").exists()
    assert (ROOT / "clients" / "python" / "pyproject.toml").is_file()
    assert (ROOT / "clients" / "web" / "package.json").is_file()
    assert (ROOT / "services" / "pyproject.toml").is_file()


def _package_cycles(graph: grimp.ImportGraph, depth: int) -> list[set[str]]:
    """Strongly connected sets of sibling packages at `depth` (fractoscope.x is depth 2)."""
    edges: dict[str, set[str]] = {}
    for module in graph.modules:
        parts = module.split(".")
        if len(parts) < depth:
            continue
        for imported in graph.find_modules_directly_imported_by(module):
            other = imported.split(".")
            if (
                len(other) >= depth
                and parts[: depth - 1] == other[: depth - 1]
                and parts[depth - 1] != other[depth - 1]
            ):
                edges.setdefault(".".join(parts[:depth]), set()).add(".".join(other[:depth]))

    def reachable(start: str) -> set[str]:
        seen, stack = set(), [start]
        while stack:
            for successor in edges.get(stack.pop(), ()):
                if successor not in seen:
                    seen.add(successor)
                    stack.append(successor)
        return seen

    cycles = []
    for package in edges:
        members = {other for other in reachable(package) if package in reachable(other)}
        if members and members not in cycles:
            cycles.append(members)
    return cycles


@pytest.mark.parametrize("depth", [2, 3])
def test_no_import_cycle_between_packages(depth):
    graph = grimp.build_graph("fractoscope")
    assert _package_cycles(graph, depth) == []


def _python_files():
    for root in SOURCES:
        for path in root.rglob("*.py"):
            if "v1" not in path.relative_to(root).parts:
                yield path


def test_modules_and_functions_are_short():
    too_long = []
    for path in _python_files():
        text = path.read_text()
        if text.count("\n") > MAX_MODULE_LINES:
            too_long.append(f"{path.relative_to(ROOT)}: {text.count(chr(10))} lines")
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef) and node.name not in PARSER_FUNCTIONS:
                length = node.end_lineno - node.lineno + 1
                if length > MAX_FUNCTION_LINES:
                    too_long.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.name}: {length} lines")
    assert too_long == []

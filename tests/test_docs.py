"""No stale path: every repository path that the README, CHANGELOG.md, docs/ and deploy/README.md
cite in `code` exists. A cited path is one whose first folder is a top-level folder of the
repository or a package of fractoscope (docs/architecture.md names paths under
services/fractoscope/), `{a,b}` standing for each of a and b; templates (`{id}`, `LEVEL`, digits)
and URLs are not paths."""

import itertools
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCUMENTS = [
    ROOT / "README.md",
    ROOT / "CHANGELOG.md",
    ROOT / "deploy" / "README.md",
    *sorted((ROOT / "docs").glob("*.md")),
]
# Where a cited path may be rooted: the repository, the services' and clients' packages.
BASES = [
    ROOT,
    ROOT / "services" / "fractoscope",
    ROOT / "clients" / "python" / "fractoscope",
    ROOT / "clients" / "cli" / "fractoscope",
]
TOP_LEVEL = {path.name for path in ROOT.iterdir() if path.is_dir() and not path.name.startswith(".")} - {"node_modules"}
PACKAGES = {path.name for base in BASES[1:] for path in base.iterdir() if path.is_dir() and path.name != "__pycache__"}
_CODE = re.compile(r"`([^`\s]+)`")
_PLACEHOLDER = re.compile(r"^([A-Z][A-Z0-9_]*|[0-9]+|.*\{[^,}]*\}.*|.*[<>*$].*)$")


def _expanded(text: str) -> list[str]:
    """`services/{decoding,jobs}.py` as each path it stands for."""
    parts = re.split(r"\{([^{}]*,[^{}]*)\}", text)
    choices = [[part] if index % 2 == 0 else part.split(",") for index, part in enumerate(parts)]
    return ["".join(chosen) for chosen in itertools.product(*choices)]


def _cited_paths(document: Path) -> set[str]:
    cited = set()
    for span in _CODE.findall(document.read_text()):
        span = span.rstrip(".,:;)")
        if "://" in span or span.startswith(("/", "-", "..")) or "/" not in span:
            continue
        for path in _expanded(span):
            components = [part for part in path.split("/") if part]
            if components[0] not in TOP_LEVEL | PACKAGES:
                continue
            if any(_PLACEHOLDER.match(part) for part in components[1:]):
                continue
            cited.add(path)
    return cited


def _exists(path: str) -> bool:
    return any((base / path).exists() for base in BASES)


@pytest.mark.parametrize("document", DOCUMENTS, ids=lambda document: str(document.relative_to(ROOT)))
def test_every_cited_repository_path_exists(document):
    assert sorted(path for path in _cited_paths(document) if not _exists(path)) == []


def test_the_check_finds_a_stale_path(tmp_path):
    stale = tmp_path / "stale.md"
    stale.write_text("See `services/{decoding,jobs}.py`, `http/api.py` and `specimen/store.py`.")
    assert sorted(path for path in _cited_paths(stale) if not _exists(path)) == [
        "services/decoding.py",
        "services/jobs.py",
        "specimen/store.py",
    ]


def test_the_readme_is_a_front_page():
    assert (ROOT / "README.md").read_text().count("\n") < 300

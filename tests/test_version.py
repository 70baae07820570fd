"""One version: VERSION names it; each file that packaging formats make carry it as a literal
(the three distributions, their pins of each other, the viewer's package.json, the image tag of
deploy/k8s) names the same, and CHANGELOG.md has its entry."""

import json
import re
import tomllib
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
VERSION = (ROOT / "VERSION").read_text().strip()


def test_the_version_is_one_of_major_minor_patch():
    assert re.fullmatch(r"[0-9]+\.[0-9]+\.[0-9]+", VERSION)


def test_every_copy_of_the_version_is_the_one_in_version():
    found = {}
    for distribution in ("services", "clients/python", "clients/cli"):
        project = tomllib.loads((ROOT / distribution / "pyproject.toml").read_text())["project"]
        found[f"{distribution}/pyproject.toml"] = project["version"]
        pins = [*project.get("dependencies", ()), *project.get("optional-dependencies", {}).get("local", ())]
        for pin in pins:
            if pin.startswith("fractoscope-"):
                found[f"{distribution}/pyproject.toml: {pin}"] = pin.partition("==")[2]
    found["clients/web/package.json"] = json.loads((ROOT / "clients/web/package.json").read_text())["version"]
    kustomization = yaml.safe_load((ROOT / "deploy/k8s/kustomization.yaml").read_text())
    found["deploy/k8s/kustomization.yaml"] = kustomization["images"][0]["newTag"]
    assert {where: version for where, version in found.items() if version != VERSION} == {}
    assert len(found) >= 8


def test_the_changelog_has_an_entry_for_the_version():
    assert re.search(rf"^## {re.escape(VERSION)} ", (ROOT / "CHANGELOG.md").read_text(), re.MULTILINE)

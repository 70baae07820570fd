"""Every number the command line and the report print has a unit, and digits that follow its
uncertainty (issue 48: "Sa 16.115 ± 1.6 µm", "Smr1 31.22 ± 0.00089 %", "Ra 0.7308, Rq 1.268"):
their outputs on a grain standing on a substrate, scanned."""

from __future__ import annotations

import re
from html.parser import HTMLParser

import numpy as np
import pytest
from test_cli import _run

from fractoscope import synthetic
from fractoscope.formats.calibration import Calibration
from fractoscope.formats.height_npz import write_height_npz
from fractoscope.reconstruction.build import store_height_map
from fractoscope.store.folder import SpecimenStore

UNITS = ("µm", "%", "1", "deg", "°", "1/µm", "1/µm²", "µm³/µm²", "µm²", "µm/px", "px")
_NUMBER = r"[-+]?\d+(?:\.\d+)?"
# "value ± uncertainty unit" or "value unit": a unit is a token of UNITS (punctuation may follow).
_MEASURED = re.compile(rf"(?<![\w.])({_NUMBER})(?: ± ({_NUMBER}))? ([^\s,;()]+)")


def _decimals(text: str) -> int:
    return len(text.split(".")[1]) if "." in text else 0


def _significant(text: str) -> int:
    digits = text.lstrip("-+").replace(".", "").lstrip("0")
    return len(digits)


def _check_measured(line: str) -> int:
    """Asserts that every number of `line` has a unit and, with an uncertainty, the value's
    decimals are the uncertainty's, whose significant digits are two; returns how many."""
    found = 0
    for value, uncertainty, unit in _MEASURED.findall(line):
        assert unit.rstrip(".:") in UNITS, (line, value, unit)
        if uncertainty:
            assert _decimals(value) == _decimals(uncertainty) and _significant(uncertainty) <= 2, (line, value)
        found += 1
    return found


@pytest.fixture(scope="module")
def grain_map(tmp_path_factory):
    """A 20 µm grain on a rough substrate at 0.2 µm/px, with its matching noise, as an npz of
    fracto height and as a stored specimen of one ROI (data folder)."""
    folder = tmp_path_factory.mktemp("units")
    rows, cols = np.indices((320, 320)) * 0.2
    grain = 20.0 * np.sqrt(np.clip(1 - ((cols - 32) ** 2 + (rows - 32) ** 2) / 14.0**2, 0, None))
    z = (grain + synthetic.self_affine_surface((320, 320), hurst=0.8, rms_um=0.3, seed=4)).astype(np.float32)
    sigma = np.full(z.shape, 0.05, np.float32)
    calibration = Calibration((-5.0, 5.0), ("metadata", "metadata"), (0.5, 0.5), 0.2, "argument")
    path = folder / "grain.npz"
    write_height_npz(
        path,
        z_um=z,
        sigma_um=sigma,
        confidence=np.ones_like(sigma),
        local_sigma_um=sigma,
        calibration=calibration,
        record={"report": {"tilt_uncertainty_deg": 0.5}},
    )
    store_height_map(
        SpecimenStore(folder / "data"), "grain", z, pixel_size_um=0.2, report=calibration.to_report(), sigma_um=sigma
    )
    return path, folder / "data"


@pytest.mark.slow
def test_fracto_roughness_prints_units_and_the_uncertainty_s_digits(grain_map):
    path, _ = grain_map
    done = _run("roughness", path)
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    parameters = [line for line in lines if re.match(r"^[SV][a-z0-9]+\s", line)]
    assert len(parameters) == 23 and all(_check_measured(line) >= 1 for line in parameters if "n/a" not in line)
    for line in lines:
        if not line.startswith("caveat:"):
            _check_measured(line)
    assert any(line.startswith("caveat: Sk, Spk, Svk") for line in lines)  # a grain on a substrate
    assert "λs none, λc none" in lines[0]


@pytest.mark.slow
def test_fracto_profile_prints_units_and_the_cut_offs(grain_map, tmp_path):
    _, data = grain_map
    done = _run("profile", "grain", "--data", data, "--from", "1,32", "--to", "63,32", "-o", tmp_path / "p.csv")
    assert done.returncode == 0, done.stderr
    figures = done.stdout.split("; ", 1)[1]
    assert _check_measured(figures) >= 15 and "λs" in figures and "λc" in figures and "µm)" in figures


class _Tables(HTMLParser):
    """A report's tables: {anchor: [[cell text, ...], ...]}."""

    def __init__(self, html: str):
        super().__init__()
        self.tables, self._rows, self._cell = {}, None, None
        self.feed(html)

    def handle_starttag(self, tag, attrs):
        if tag == "table":
            self._rows = self.tables.setdefault(dict(attrs).get("id", f"table{len(self.tables)}"), [])
        elif tag == "tr" and self._rows is not None:
            self._rows.append([])
        elif tag in ("td", "th") and self._rows is not None:
            self._cell = []

    def handle_endtag(self, tag):
        if tag in ("td", "th") and self._cell is not None:
            self._rows[-1].append("".join(self._cell).strip())
            self._cell = None
        elif tag == "table":
            self._rows = None

    def handle_data(self, data):
        if self._cell is not None:
            self._cell.append(data)


@pytest.mark.slow
def test_the_report_s_tables_give_units_and_the_uncertainty_s_digits(grain_map, tmp_path):
    path, _ = grain_map
    out = tmp_path / "report.html"
    done = _run("report", path, "-o", out)
    assert done.returncode == 0, done.stderr
    page = out.read_text()
    tables = _Tables(page).tables
    roughness = tables["roughness-table"][1:]
    assert len(roughness) == 23
    for name, value, unit, u, *_ in roughness:
        assert unit, name
        if u != "—" and value != "n/a":
            assert _decimals(value) == _decimals(u) and _significant(u) <= 2, (name, value, u)
    for anchor in ("profile-horizontal-iso", "profile-vertical-iso"):
        assert all(unit for _, _, unit in tables[anchor][1:]) and all(
            _significant(value) <= 3 for _, value, _ in tables[anchor][1:] if value != "n/a"
        )
    assert "height map file grain.npz" in page and "specimen grain" not in page

"""One pair, one answer: a stereo pair's roughness, uncertainties, datum and coverage come out the
same by every route a user takes (issue 48): `fracto height` then `fracto roughness`, `report`
and `export` of its npz; `fracto reconstruct` then `fracto roughness`, `report` and `export` of
the specimen (gRPC); and the HTTP API the viewer reads. On a synthetic grain with known truth and
on the real pollen pair."""

from __future__ import annotations

import csv
import json
import math
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import tifffile
from conftest import ReportNumbers
from test_cli import _run

from fractoscope import synthetic
from fractoscope.http.server import start_http_server
from fractoscope.server.config import ServerConfig
from fractoscope.server.main import create_server
from fractoscope.store.folder import SpecimenStore
from fractoscope.synthetic.particles import particle_scene

PIXEL_SIZE_UM = 0.2


def _grain_pair(directory: Path):
    """A 12 µm grain standing 19 µm high on a textured, flat substrate, seen at ±5° (256² px at
    0.2 µm/px): the image files and the truth (heights seen at each pixel of the first, µm)."""
    scene = particle_scene(
        320, pixel_size_um=PIXEL_SIZE_UM, radii_um=(12.0,), centres_px=((160, 160),), seed=9, substrate_contrast=1.0
    )
    pair = synthetic.render_stereo_pair(
        scene.z_um, pixel_size_um=PIXEL_SIZE_UM, tilt_deg=(-5, 5), output_shape=(256, 256), material=scene.material
    )
    paths = directory / "left.tif", directory / "right.tif"
    for path, image in zip(paths, (pair.first, pair.second)):
        tifffile.imwrite(path, image)
    return paths, pair.z_seen_um


def _routes(tmp_path: Path, images, calibration: dict) -> dict:
    """Every route's answer for one pair: the npz's and the specimen's summaries, roughness,
    reports (their numbers and text) and CSV exports, and the HTTP API's roughness."""
    flags = []
    if "tilt_deg" in calibration:
        flags = ["--tilt", *map(str, calibration["tilt_deg"]), "--pixel-size-um", str(calibration["pixel_size_um"])]
    npz, data = tmp_path / "h.npz", tmp_path / "data"
    height = _run("height", *images, *flags, "--level", "substrate", "-o", npz, "--json")
    assert height.returncode == 0, height.stderr
    manifest = tmp_path / "m.json"
    roi = {"id": "overview", "left": str(images[0]), "right": str(images[1]), "level": "substrate", **calibration}
    manifest.write_text(json.dumps({"specimen": "pair", "rois": [roi]}))
    built = _run("reconstruct", manifest, "--data", data, "--json")
    assert built.returncode == 0, built.stderr
    answers = {"npz": json.loads(height.stdout), "specimen": json.loads(built.stdout)["rois"][0]}
    for name, source in (("npz", npz), ("specimen", "pair")):
        rough = _run("roughness", source, "--data", data, "--json")
        assert rough.returncode == 0, rough.stderr
        answers[f"{name} roughness"] = json.loads(rough.stdout)
        report, exported = tmp_path / f"{name}.html", tmp_path / f"{name}.csv"
        for verb, out in (("report", report), ("export", exported)):
            done = _run(verb, source, "--data", data, "-o", out)
            assert done.returncode == 0, done.stderr
        answers[f"{name} report"] = ReportNumbers(report.read_text())
        with exported.open() as rows:
            answers[f"{name} sigma"] = np.array([float(row["sigma_um"]) for row in csv.DictReader(rows)])
    answers["http roughness"] = _http_roughness(data, "pair")
    return answers


def _http_roughness(data: Path, specimen_id: str) -> dict:
    """GET /api/specimens/ID/roughness of a server on `data`: what the viewer shows."""
    store = SpecimenStore(data)
    server, port = create_server(ServerConfig(address="127.0.0.1:0"), store=store)
    server.start()
    endpoint = start_http_server(store, grpc_address=f"127.0.0.1:{port}")
    try:
        url = f"http://127.0.0.1:{endpoint.server_port}/api/specimens/{specimen_id}/roughness"
        with urllib.request.urlopen(url, timeout=600) as response:
            return json.loads(response.read())
    finally:
        endpoint.shutdown()
        server.stop(grace=None)


def _same(a, b, what: str) -> None:
    """Equal to float tolerance (None for None, lists and dicts item by item)."""
    if isinstance(a, dict):
        assert a.keys() == b.keys(), what
        for key in a:
            _same(a[key], b[key], f"{what}.{key}")
    elif isinstance(a, list):
        assert len(a) == len(b), what
        for index, (x, y) in enumerate(zip(a, b)):
            _same(x, y, f"{what}[{index}]")
    elif isinstance(a, float) or isinstance(b, float):
        assert a is not None and b is not None and math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-12), (what, a, b)
    else:
        assert a == b, (what, a, b)


def _check_one_answer(answers: dict) -> None:
    """The routes agree: every parameter with its uncertainty, the Hurst fits, coverage, caveats;
    the datum; the reports' numbers; the exported sigma (no zero where a height is)."""
    npz = answers["npz roughness"]
    for route in ("specimen roughness", "http roughness"):
        other = answers[route]
        for key in ("units", "uncertainty", "chain", "noise_bias", "coverage", "caveats", "hurst_note"):
            _same(npz[key], other[key], f"{route} {key}")
        for name in npz["units"]:
            _same(npz[name], other[name], f"{route} {name}")
        for fit, same in zip(npz["hurst"], other["hurst"]):
            for key in ("method", "side", "hurst", "hurst_stderr", "fit_min_um", "fit_max_um", "not_determinable"):
                _same(fit[key], same[key], f"{route} hurst {key}")
    for route, roughness in (("npz report", npz), ("specimen report", answers["specimen roughness"])):
        shown = answers[route].values
        for name in npz["units"]:
            assert shown.get(name) == roughness[name], (route, name)
            assert shown.get(f"u.{name}") == roughness["uncertainty"][name]["u_total"], (route, name)
        text = " ".join(answers[route].text)
        assert f"{100 * npz['coverage']['measured_fraction']:.1f} % of the points matched" in text, route
        assert "specimen h" not in text
    _same(answers["npz"]["datum"], answers["specimen"]["datum"] | {"region_um": None}, "datum")
    _same(answers["npz"]["coverage"] | {"points": None}, answers["specimen"]["coverage"] | {"points": None}, "coverage")
    _same(npz["coverage"], {k: v for k, v in answers["npz"]["coverage"].items() if k != "points"}, "coverage")
    sigma, npz_sigma = answers["specimen sigma"], answers["npz sigma"]
    assert sigma.size == npz_sigma.size and np.all(sigma > 0)
    assert abs(np.median(sigma) / np.median(npz_sigma) - 1) < 0.05


@pytest.mark.slow
def test_a_synthetic_grain_gives_one_answer_by_every_route(tmp_path):
    """The synthetic grain: every route agrees, and the answer is the truth's: zero on the
    substrate (within 0.5°), the grain's top at its true height within 5 %, and Sa within 20 % of
    the truth's on the matched points (measured: 14 % low, the matching window rounding the
    grain's rim)."""
    images, truth = _grain_pair(tmp_path)
    answers = _routes(tmp_path, images, {"tilt_deg": [-5.0, 5.0], "pixel_size_um": PIXEL_SIZE_UM})
    _check_one_answer(answers)
    datum = answers["specimen"]["datum"]
    assert datum["level"] == "substrate" and datum["tilt_deg"] < 0.5 and not datum["warning"]
    assert answers["npz"]["z_max_um"] == pytest.approx(np.max(truth[16:-16, 16:-16]), rel=0.05)
    from fractoscope.formats.height_npz import read_height_npz
    from fractoscope.surface.roughness import height_parameters_after_plane

    kept = read_height_npz(tmp_path / "h.npz")
    matched = np.isfinite(kept.z_um) & ~kept.filled
    true_sa = height_parameters_after_plane(np.where(matched, truth, np.nan))["Sa"]
    assert answers["npz roughness"]["Sa"] == pytest.approx(true_sa, rel=0.2)


@pytest.mark.slow
@pytest.mark.real_data
def test_the_pollen_pair_gives_one_answer_by_every_route(pollen_series, tmp_path):
    """The ±3° pollen pair (pot_02, pot_04; calibration from the TIFFs' metadata): every route
    agrees, the grain's sigma is the npz's (it was 0 on 75 % of the grain in the specimen's
    export), and the report's coverage is the matched share (it said 88.1 % where 71.2 % was
    matched)."""
    images = (pollen_series / "pot_02.tif", pollen_series / "pot_04.tif")
    answers = _routes(tmp_path, images, {})
    _check_one_answer(answers)
    assert answers["npz"]["datum"]["level"] == "substrate"
    assert answers["npz"]["coverage"]["measured_fraction"] == pytest.approx(answers["npz"]["valid_fraction"], abs=0.001)

"""A specimen of a tilt series with calibrated tilts, as a user builds and reports it: `fracto
reconstruct` of a manifest ROI of three views whose nominal tilts are 10 % off, against `fracto
height --calibrate-tilt` on the same images and the known surface, then `fracto report` of the
specimen and of the height map file."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import tifffile
from conftest import ReportNumbers

from fractoscope import synthetic
from fractoscope.numbers import value_text
from fractoscope.store.folder import SpecimenStore

FRACTO = str(Path(sys.executable).with_name("fracto"))
TRUE_TILT_DEG = (-5.0, 0.0, 5.0)
NOMINAL_TILT_DEG = (-4.5, 0.0, 4.5)  # each step read 10 % small, as a stage readout may


def _run(*args) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != "FRACTO_SERVER"}
    return subprocess.run([FRACTO, *map(str, args)], capture_output=True, text=True, env=env, timeout=300)


@pytest.fixture(scope="module")
def measured(tmp_path_factory):
    """(folder, truth µm on the reference's grid, `fracto reconstruct`'s run): the series' views as
    TIFFs, its manifest, the specimen built in folder/data, and the height maps of `fracto height`
    with calibrated (calibrated.npz) and nominal (nominal.npz) tilts."""
    folder = tmp_path_factory.mktemp("series")
    surface = synthetic.self_affine_surface((320, 320), hurst=0.8, rms_um=2.5, seed=9)
    views, truth = synthetic.render_tilt_series(
        surface, pixel_size_um=0.1, tilt_deg=TRUE_TILT_DEG, output_shape=(256, 256), seed=9
    )
    names = [f"view{index}.tif" for index in range(len(views))]
    for name, view in zip(names, views):
        tifffile.imwrite(folder / name, view)
    roi = {"id": "overview", "images": names, "tilt_deg": list(NOMINAL_TILT_DEG), "pixel_size_um": 0.1}
    (folder / "manifest.json").write_text(json.dumps({"specimen": "series", "rois": [{**roi, "calibrate": True}]}))
    built = _run("reconstruct", folder / "manifest.json", "--data", folder / "data")
    assert built.returncode == 0, built.stderr
    for output, calibrate in (("calibrated.npz", ["--calibrate-tilt"]), ("nominal.npz", [])):
        done = _run(
            "height", *(folder / name for name in names), "--tilt", *NOMINAL_TILT_DEG, "--pixel-size-um", 0.1,
            *calibrate, "-o", folder / output,
        )  # fmt: skip
        assert done.returncode == 0, done.stderr
    return folder, truth, built


def _rms_error_um(z_um: np.ndarray, truth: np.ndarray, known: np.ndarray) -> float:
    """RMS height error on `known` after removing the best plane (the frame's tilt and height zero
    are not observable)."""
    rows, cols = np.nonzero(known)
    error = z_um[known] - truth[known]
    design = np.column_stack([rows, cols, np.ones(rows.size)])
    error -= design @ np.linalg.lstsq(design, error, rcond=None)[0]
    return float(np.sqrt(np.mean(error**2)))


@pytest.mark.slow
def test_a_calibrated_series_specimen_is_as_accurate_as_fracto_height_calibrated(measured):
    """Measured on the points all three measured (99 %): the specimen 0.163 µm RMS, fracto height
    --calibrate-tilt 0.163 µm (the same heights; the specimen's filter only fills holes), the
    nominal tilts 0.214 µm (a range of 15.4 µm)."""
    folder, truth, built = measured
    assert built.stdout.strip() == "series"
    assert "tilts estimated" in built.stderr and "(nominal -4.50, +0.00, +4.50;" in built.stderr
    with np.load(folder / "calibrated.npz") as arrays:
        calibrated_um = arrays["z_um"]
    with np.load(folder / "nominal.npz") as arrays:
        nominal_um = arrays["z_um"]
    specimen_um = SpecimenStore(folder / "data").load("series").heights("overview").z_um
    known = np.isfinite(calibrated_um) & np.isfinite(specimen_um) & np.isfinite(nominal_um)
    assert known.mean() > 0.95
    errors = {
        name: _rms_error_um(z_um, truth, known)
        for name, z_um in (("specimen", specimen_um), ("height", calibrated_um), ("nominal", nominal_um))
    }
    assert errors["specimen"] == pytest.approx(errors["height"], rel=0.1), errors
    assert errors["nominal"] > 1.2 * errors["height"], errors  # the calibration can tell the tilts are off


@pytest.mark.slow
def test_the_specimen_keeps_and_reports_the_calibrated_tilts_with_their_sigmas(measured):
    folder, _, _ = measured
    data = folder / "data"
    listed = _run("list", "--data", data, "--json")
    assert listed.returncode == 0, listed.stderr
    (specimen,) = json.loads(listed.stdout)["specimens"]
    matching = specimen["rois"][0]["matching"]
    tilts, sigmas = np.array(matching["tilt_deg"]), np.array(matching["tilt_sigma_deg"])
    assert matching["tilt_deg_nominal"] == list(NOMINAL_TILT_DEG)
    assert matching["tilt_source"] == ["argument", "tilt_calibration", "tilt_calibration"]
    # The reference keeps its nominal tilt; the steps from it are recovered within two sigmas.
    steps_error = np.abs(tilts[1:] - tilts[0] - (np.array(TRUE_TILT_DEG[1:]) - TRUE_TILT_DEG[0]))
    assert tilts[0] == NOMINAL_TILT_DEG[0] and np.all(0 < sigmas[1:]) and np.all(steps_error <= 2 * sigmas[1:])
    done = _run("report", "series", "--data", data, "-o", folder / "series.html", "--pdf", folder / "series.pdf")
    assert done.returncode == 0, done.stderr
    from_file = _run("report", folder / "calibrated.npz", "-o", folder / "calibrated.html")
    assert from_file.returncode == 0, from_file.stderr
    for page in (
        ReportNumbers((folder / "series.html").read_text()),
        ReportNumbers((folder / "calibrated.html").read_text()),
    ):
        text = " ".join(page.text)
        assert "The tilt was not calibrated" not in text and "tilt calibrated from the images" in text
        shown = [page.values[f"overview.tilt_deg[{index}]"] for index in range(3)]
        nominal = [page.values[f"overview.tilt_deg_nominal[{index}]"] for index in range(3)]
        assert nominal == list(NOMINAL_TILT_DEG) and np.allclose(shown, tilts, atol=0.02)
        assert np.allclose([page.values[f"overview.tilt_sigma_deg[{index}]"] for index in (1, 2)], sigmas[1:], rtol=0.2)
    if shutil.which("pdftotext"):
        pdf = subprocess.run(
            ["pdftotext", "-layout", str(folder / "series.pdf"), "-"], capture_output=True, text=True, check=True
        ).stdout
        words = " ".join(pdf.split())
        # The tilt to its sigma's second significant digit (fractoscope.numbers), with its sign.
        assert "tilt_calibration" in words and f"+{value_text(tilts[2], sigmas[2])}" in words
        assert "starting from the nominal tilts -4.5, +0, +4.5 °" in words
    roughness = _run("roughness", folder / "calibrated.npz", "--json")
    assert roughness.returncode == 0, roughness.stderr
    sa = json.loads(roughness.stdout)["Sa"]
    assert ReportNumbers((folder / "calibrated.html").read_text()).values["Sa"] == pytest.approx(sa, rel=1e-9)

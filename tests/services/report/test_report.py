"""The measurement report of the example specimen: its PDF opens in poppler, its numbers are the
API's, and it says when the tilt was not calibrated."""

from __future__ import annotations

import json
import shutil
import subprocess
import urllib.request

import matplotlib.pyplot as plt
import numpy as np
import pytest
from conftest import ReportNumbers
from PIL import Image
from tools import required_tool

from fractoscope.http.server import start_http_server
from fractoscope.report import build_document, report_content, write_report
from fractoscope.store.folder import SpecimenStore

NOT_CALIBRATED = "The tilt was not calibrated"


@pytest.fixture(scope="module")
def http_api(built):
    _, _, data, _ = built
    endpoint = start_http_server(SpecimenStore(data))
    base = f"http://127.0.0.1:{endpoint.server_port}"

    def get(path: str) -> bytes:
        with urllib.request.urlopen(base + path, timeout=300) as response:
            return response.read()

    yield get
    endpoint.shutdown()


def test_the_numbers_in_the_report_are_the_apis(http_api, built):
    _, _, _, summary = built
    page = ReportNumbers()
    page.feed(http_api("/api/specimens/synthetic/report?roi=zoom").decode())
    roughness = json.loads(http_api("/api/specimens/synthetic/roughness?roi=zoom"))
    shown = page.values
    for name, value in roughness.items():
        if isinstance(value, float) and name in shown:
            assert shown[name] == value, name
    assert {
        "Sa",
        "Sq",
        "Sz",
        "Sdr",
        "Sal",
        "Sk",
        "Vmp",
        "hurst_exponent",
        "hurst_fit_min_um",
        "fractal_dimension",
    } <= set(shown)
    for name, parts in roughness["uncertainty"].items():
        for part, key in (("u", "u_total"), ("u_tilt", "u_tilt"), ("u_noise", "u_noise")):
            assert shown.get(f"{part}.{name}") == parts[key], (part, name)  # None where not propagated: no number shown
    zoom = summary["rois"][1]
    x0, y0 = zoom["region"]["min"]["x_um"], zoom["region"]["min"]["y_um"]
    x1, y1 = zoom["region"]["max"]["x_um"], zoom["region"]["max"]["y_um"]
    profile = json.loads(
        http_api(f"/api/specimens/synthetic/profile?from={x0},{(y0 + y1) / 2}&to={x1},{(y0 + y1) / 2}")
    )
    for name, value in profile["parameters"].items():
        assert shown.get(f"horizontal.roughness.{name}") == value, name
    assert {f"horizontal.roughness.{name}" for name in ("Ra", "Rq", "Rz", "RSm", "Rdq", "Rk")} <= set(shown)
    assert (
        shown["zoom.tilt_deg[1]"] == zoom["matching"]["tilt_deg"][1]
        and shown["zoom.pixel_size_um"] == zoom["pixel_size_um"]
    )
    assert len(roughness["hurst"]) == 4  # h(r) and PSD, along and across: each with its standard error and fit range
    text = " ".join(page.text)
    assert any(not fit["not_determinable"] for fit in roughness["hurst"])  # a self-affine surface, H = 0.8
    for fit in roughness["hurst"]:
        if fit["not_determinable"]:  # the report gives the reason instead of the number
            assert f"hurst.{fit['method']}.{fit['side']}.hurst" not in shown and "not determinable" in text
            continue
        for key in ("hurst", "hurst_stderr", "fit_min_um", "fit_max_um"):
            assert shown[f"hurst.{fit['method']}.{fit['side']}.{key}"] == fit[key], (fit["method"], fit["side"], key)
    chain = roughness["chain"]  # the roughness table names the chain the API ran
    assert f"After removing the form ({chain['form']}" in text and chain["s_filter_um"] == chain["l_filter_um"] == 0.0
    assert "Filters: λs = none, λc = none" in text and f"correlated over the {chain['window_px']:g} px window" in text
    assert NOT_CALIBRATED in text and "argument" in text  # the manifest gave the tilts and the pixel size


def test_the_psd_is_plotted_from_the_apis_data(built):
    """The report's PSD figure draws the API's areal PSD and its PSD Hurst fits' curves."""
    _, client, data, _ = built
    roughness = client.roughness("synthetic", roi="zoom")
    content = report_content(SpecimenStore(data).load("synthetic"), roi="zoom")
    document = build_document(content)
    try:
        figure = next(block.figure for block in document.blocks if getattr(block, "anchor", "") == "psd-figure")
        areal, profiles = figure.axes[:2]
        q, c = np.asarray(roughness["psd"]["q_per_um"]), np.asarray(roughness["psd"]["c_um4"], dtype=float)
        known = np.isfinite(c) & (c > 0)
        assert known.sum() > 0.9 * len(c) > 20
        np.testing.assert_array_equal(areal.lines[0].get_xdata(), q[known])
        np.testing.assert_array_equal(areal.lines[0].get_ydata(), c[known])
        for fit in (fit for fit in roughness["hurst"] if fit["method"] == "psd" and not fit["not_determinable"]):
            curve = next(line for line in profiles.lines if line.get_label().startswith(fit["side"]))
            np.testing.assert_allclose(curve.get_xdata(), 1 / np.asarray(fit["scale_um"]), rtol=1e-12)
            np.testing.assert_array_equal(curve.get_ydata(), np.asarray(fit["value"], dtype=float))
            assert any(
                line.get_label() == f"fit: H = {fit['hurst']:.3f} ± {fit['hurst_stderr']:.2g}"
                for line in profiles.lines
            )
        assert areal.get_xscale() == areal.get_yscale() == "log" and "1/µm" in areal.get_xlabel()
    finally:
        for block in document.blocks:
            if hasattr(block, "figure"):
                plt.close(block.figure)


def test_the_pdf_opens_in_poppler_and_says_the_tilt_was_not_calibrated(built, tmp_path):
    _, client, _, _ = built
    pdf = client.report("synthetic", tmp_path / "report.pdf", roi="zoom")
    pages = int(
        next(
            line.split()[-1]
            for line in subprocess.run(
                [required_tool("pdfinfo", "/usr/bin/pdftoppm"), str(pdf)], capture_output=True, text=True, check=True
            ).stdout.splitlines()
            if line.startswith("Pages:")
        )
    )
    subprocess.run(
        [required_tool("pdftoppm", "/usr/bin/pdftoppm"), "-r", "40", "-png", str(pdf), str(tmp_path / "page")],
        check=True,
        timeout=120,
    )
    images = sorted(tmp_path.glob("page-*.png"))
    assert pages >= 4 and len(images) == pages
    for path in images:
        grey = np.asarray(Image.open(path).convert("L"), dtype=np.float32)
        assert grey.shape[0] > grey.shape[1] > 200 and grey.std() > 5  # A4 portrait, not blank
    text = subprocess.run(["pdftotext", "-layout", str(pdf), "-"], capture_output=True, text=True, check=True).stdout
    assert NOT_CALIBRATED in text and "Areal parameters (ISO 25178-2)" in text and "Hurst exponent" in text
    assert "power spectral densities" in text and "profile PSD" in text


def test_a_calibrated_tilt_is_reported_with_its_sigma_and_no_warning(built, tmp_path):
    """An ROI whose report says its second tilt came from the tilt calibration (as a tilt series'
    would): the report names the source and the calibration's sigma and does not warn."""
    _, _, data, _ = built
    copy = tmp_path / "data"
    shutil.copytree(data, copy)
    description = copy / "specimens" / "synthetic" / "specimen.json"
    stored = json.loads(description.read_text())
    zoom = next(roi for roi in stored["rois"] if roi["id"] == "zoom")
    zoom["matching"].update(tilt_source=["argument", "tilt_calibration"], tilt_sigma_deg=[0.0, 0.02])
    description.write_text(json.dumps(stored))
    page = ReportNumbers()
    page.feed(write_report(SpecimenStore(copy).load("synthetic"), tmp_path, file_format="html", roi="zoom").read_text())
    text = " ".join(page.text)
    assert NOT_CALIBRATED not in text and "tilt_calibration" in text
    assert page.values["zoom.tilt_sigma_deg[1]"] == 0.02 and page.values["zoom.tilt_sigma_deg[0]"] == 0.5


def test_a_region_report_has_the_apis_numbers_for_that_region(built, tmp_path):
    """`fracto report SPECIMEN --region X0,Y0,X1,Y1`'s report (write_report with region_um): the
    area is named by its bounds and the parameters are GetRoughness's for the same region, a
    Hurst exponent the region is too small for included: no number, where the API has none."""
    _, client, data, summary = built
    region = summary["rois"][1]["region"]
    box = (
        region["min"]["x_um"] + 10,
        region["min"]["y_um"] + 10,
        region["min"]["x_um"] + 70,
        region["min"]["y_um"] + 50,
    )
    page = ReportNumbers()
    page.feed(
        write_report(SpecimenStore(data).load("synthetic"), tmp_path, file_format="html", region_um=box).read_text()
    )
    roughness = client.roughness("synthetic", region_um=box)
    for name in ("Sa", "Sq", "Sz", "Sdr", "Sk", "hurst_exponent", "hurst_fit_min_um", "fractal_dimension"):
        assert page.values.get(name) == roughness[name], name  # None: no number shown, as the API gives none
    text = " ".join(page.text)
    if roughness["hurst_exponent"] is None:  # 240 x 160 px: too small a field for a Hurst fit, and the report says why
        assert roughness["hurst_note"] and roughness["hurst_note"][1:] in text
    assert f"region x {box[0]:.6g} to {box[2]:.6g} µm, y {box[1]:.6g} to {box[3]:.6g} µm" in text


def test_lists_in_the_parameters_table_are_shown_as_their_items_are():
    """A per-view figure such as photometric_agreement reads as the single numbers do (six
    significant digits), not as Python's full repr."""
    from fractoscope.report import _shown

    assert _shown([0.9541111286385613, True]) == "0.954111; True"
    assert _shown(0.9541111286385613) == "0.954111" and _shown([]) == "none"


def test_the_report_of_a_white_noise_surface_marks_its_hurst_exponent_not_determinable(tmp_path):
    """A report once printed a profile PSD's H = -0.102 ± 0.842 and elsewhere 1.23 without a word."""
    from fractoscope.reconstruction.build import store_height_map

    noise = np.random.default_rng(7).normal(scale=0.2, size=(640, 640))  # the 15 px window: a field of 600 px
    noise[:, :40] = np.nan  # the profiles start where nothing is measured
    store = SpecimenStore(tmp_path / "data")
    specimen = store_height_map(store, "noise", noise, pixel_size_um=1.0, report={})
    content = report_content(specimen)
    assert content.roughness.hurst.fits and np.isnan(content.roughness.legacy()["hurst_exponent"])
    document = build_document(content)
    try:
        text = "\n".join(
            " ".join(str(getattr(block, name, "")) for name in ("text", "caption"))
            + " ".join(cell.text for row in getattr(block, "rows", []) for cell in row)
            for block in document.blocks
        )
    finally:
        for block in document.blocks:
            if hasattr(block, "figure"):
                plt.close(block.figure)
    assert "Hurst exponent H" in text and text.count("not determinable") >= 5  # the table, 4 fits, the note
    assert "fitted over" in text  # the reason comes with the fit range
    assert "on a grid of 1 µm" in text and "ISO 25178-3's nesting indices for the 1 µm grid" in text
    for profile in content.profiles:
        assert f"from samples {profile.spacing_um:.4g} µm apart" in text
        assert profile.lambda_s_um == 8.0  # not ISO 21920-3's 2.5 µm: 1 µm samples cannot carry it


def test_no_legend_entry_names_a_series_without_data(tmp_path):
    """A profile's legend once read "primary, ROI no data" for the stretch nothing was measured on."""
    from fractoscope.reconstruction.build import store_height_map
    from fractoscope.report import figures

    heights = np.random.default_rng(8).normal(scale=0.2, size=(96, 96))
    heights[:, :30] = np.nan
    specimen = store_height_map(SpecimenStore(tmp_path / "data"), "holes", heights, pixel_size_um=0.5, report={})
    profile = report_content(specimen).profiles[0]
    assert -1 in profile.found.source_index  # the line crosses the unmeasured stretch
    figure = figures.profile_figure(profile)
    try:
        labels = figure.axes[0].get_legend_handles_labels()[1]
    finally:
        plt.close(figure)
    assert labels and not any("no data" in label for label in labels)
    assert "primary, ROI overview" in labels

"""Our tilesets and the web viewer in headless Chromium (Debian's, which `make test` installs),
driven by the scripts beside this file through playwright-core. Screenshots are kept as artefacts in
bench-results/browser/ (not committed)."""

import base64
import json
import os
import re
import shutil
import subprocess
import time
from pathlib import Path
from urllib.parse import parse_qs, urlparse

import numpy as np
import pytest
import requests
from conftest import mesh_component_areas_um2, tile_seams_grey_levels
from tools import required_tool

from fractoscope.client import FractoscopeClient
from fractoscope.client.manifest import load_manifest
from fractoscope.http.server import start_http_server
from fractoscope.numbers import with_uncertainty
from fractoscope.server.config import ServerConfig
from fractoscope.server.main import create_server
from fractoscope.store.folder import SpecimenStore

pytestmark = pytest.mark.slow
ROOT = Path(__file__).resolve().parents[3]
ARTEFACTS = ROOT / "bench-results" / "browser"
# How long the pollen overview may take to settle before the test calls it stuck: a hang bound,
# not the issue's speed target (45 s; measured 6.8 s, kept in the artefacts' result.json), which
# a busy machine's software rendering would make a timing a test cannot assert.
STUCK_AFTER_S = 300.0


def _in_chromium(script: str, data: Path, *arguments: str, timeout_s: float = 900) -> dict:
    """Runs SCRIPT (beside this file) with the base URL of an HTTP endpoint serving `data` and `arguments`
    ("{base}" in them is replaced by that URL); its JSON result."""
    required_tool(os.environ.get("CHROMIUM", "/usr/bin/chromium"), "/usr/bin/chromium")
    http = start_http_server(SpecimenStore(data))
    base = f"http://127.0.0.1:{http.server_port}"
    runner = Path(__file__).resolve().parent / script
    try:
        done = subprocess.run(
            ["node", str(runner), *(argument.replace("{base}", base) for argument in arguments)],
            capture_output=True,
            text=True,
            timeout=timeout_s,
            cwd=ROOT,
        )
    finally:
        http.shutdown()
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.splitlines()[-1])


def _artefacts(name: str) -> Path:
    directory = ARTEFACTS / name
    directory.mkdir(parents=True, exist_ok=True)
    return directory


def test_tileset_loads_in_3d_tiles_renderer_in_headless_chromium(built):
    _, _, data, _ = built
    result = _in_chromium(
        "load_tileset.mjs", data, "{base}/specimens/synthetic/tileset.json", str(_artefacts("tileset") / "view.png")
    )
    assert result["tilesetLoaded"] and not result["failed"] and not result["errors"], result
    assert result["loaded"] >= 5  # the root and refining levels streamed in
    assert result["litFraction"] > 0.3  # the textured surface fills much of the view


def _numbers_in(text: str) -> list[float]:
    return [float(v) for v in re.findall(r"-?\d+(?:\.\d+)?", text)]


def test_web_viewer_tools_styles_permalink_and_snapshot(built):
    """The viewer page, served by the tile endpoint: a link to a missing specimen shows an error
    and opens nothing else; tiles stream in, counted on screen; the optical/digital legend and the
    ROI's label show; every measuring tool answers from the server's data; a profile's line is
    drawn on the surface, and two profiles share the plot; the heights' exaggeration changes the
    picture; roughness shows that it is busy; a style change
    reaches tiles cached outside the scene; the permalink reopens the view and its
    measurements; the snapshot is a PNG."""
    truth, _, data, _ = built
    out = _artefacts("viewer")
    result = _in_chromium("check_viewer.mjs", data, "{base}", "synthetic", str(out))
    (out / "result.json").write_text(json.dumps(result, indent=1))
    assert not result["errors"] and result["status"]["failed"] == 0, result["errors"]
    missing = result["missing"]
    assert missing["shown"] and "doesnotexist" in missing["message"] and "synthetic" in missing["message"]
    assert missing["chosen"] == "" and result["missingTileRequests"] == 0
    assert result["tileRequests"] >= 5 and result["status"]["loaded"] >= 5 and result["litFraction"] > 0.2
    overlays = result["overlays"]  # the tile counter, the optical/digital legend and the ROI's label on the surface
    assert re.fullmatch(r"tiles: \d+ shown, 0 loading", overlays["tileProgress"]), overlays
    assert (
        "optical zoom (measured)" in overlays["legend"]
        and "digital zoom (upsampled)" in overlays["legend"]
        and overlays["legendAfter"] == ""
    )
    assert any(
        label.startswith("zoom · ") and "×" in label and label.endswith("µm/px") for label in overlays["roiLabels"]
    ), overlays
    tools = result["tools"]
    assert (
        result["profile"]["samples"] > 100
        and result["profile"]["parameters"]["Ra"] > 0
        and "Ra" in result["profile"]["text"]
    )
    assert result["profileLinePixels"] > 300  # a 3 px line across a third of the view
    assert tools["secondProfile"].startswith("Profile 6:") and len(result["plotted"]) == 2
    assert all(curve["pixels"] > 50 for curve in result["plotted"]), result["plotted"]  # both profiles in the one plot
    assert result["exaggerationShown"] == "10.0" and result["exaggerationChange"] > 5.0, result["exaggerationChange"]
    assert tools["point"].startswith("Height 2: z = ") and "µm" in tools["point"]
    distance = _numbers_in(tools["distance"])
    assert tools["distance"].startswith("Distance 3:") and distance[1] >= distance[2] > 0  # 3D length >= horizontal
    angle = _numbers_in(tools["angle"])[1]
    assert tools["angle"].endswith("°") and 0 < angle < 180
    assert tools["step"].startswith("Step 5:") and "±" in tools["step"] and "area means" in tools["step"]
    assert result["roughnessBusy"] and result["roughness"]["Sa"] > 0 and 0 < result["roughness"]["hurst_exponent"] < 1.5
    rough = result["roughness"]  # the panel shows each value with its uncertainty's digits, then the chain
    panel = result["roughnessText"]
    for name in ("Sa", "Sq", "Sdr"):
        shown = with_uncertainty(rough[name], rough["uncertainty"][name]["u_total"], rough["units"][name])
        assert f"{name} {shown}" in panel, (name, panel)
    assert f"chain: form {rough['chain']['form']}, λs none, λc none, " in panel and panel.count("µm/px") == 1, panel
    assert f"{100 * rough['coverage']['measured_fraction']:.3g} % of the view" in panel, panel
    assert "Hurst " in panel and " µm)" in panel, panel
    assert result["scaleBar"] == {"hidden": True, "hint": True}  # perspective: no bar, but how to get one
    assert result["heightColourSpread"] > 0.3  # heights from the dequantized positions span the ramp
    assert (
        result["restyledSpread"] < 0.5 * result["heightColourSpread"]
    )  # cached tiles came back as SEM image, not height colours
    assert result["tintedBefore"] < 0.1 and result["tintedAfter"] > 0.8, (
        result["tintedBefore"],
        result["tintedAfter"],
    )  # and tinted
    link = parse_qs(urlparse(result["permalink"]).query)
    assert (
        link["specimen"] == ["synthetic"]
        and link["measurements"][0].startswith("profile:")
        and len(link["camera"][0].split(",")) == 6
    )
    np.testing.assert_allclose(result["reopened"]["camera"], result["camera"], rtol=1e-3)
    assert [text.split(":")[0] for text in result["reopened"]["tools"]] == [
        text.split(":")[0] for text in tools.values()
    ]
    for again, first in zip(result["reopened"]["tools"], tools.values()):  # points kept to the nm
        np.testing.assert_allclose(_numbers_in(again), _numbers_in(first), rtol=0.02, atol=0.01)
    assert result["snapshot"].startswith("data:image/png;base64,")
    assert (out / "snapshot.png").read_bytes()[:8] == base64.b64decode("iVBORw0KGgo=")


@pytest.fixture(scope="module")
def pollen_data(pollen_series, tmp_path_factory):
    """The real pollen pair (pot_02 / pot_04, full size) reconstructed as the demo builds it: tilts,
    pixel size and magnification from the metadata, heights from the substrate."""
    from fractoscope.cli.demo import _write_pollen_manifest

    root = tmp_path_factory.mktemp("pollen")
    manifest = _write_pollen_manifest(pollen_series, root / "input")
    server, port = create_server(ServerConfig(address="127.0.0.1:0", data_dir=root / "data"))
    server.start()
    try:
        with FractoscopeClient(f"127.0.0.1:{port}", timeout_s=1800) as client:
            specimen_id, rois = load_manifest(manifest)
            client.reconstruct_specimen(specimen_id, rois)
    finally:
        server.stop(grace=None)
    return root / "data"


@pytest.mark.real_data
def test_the_pollen_overview_settles_coarse_to_fine_with_few_tiles(pollen_data):
    """A first session on the real pollen pair: the overview in 1280 x 800 with the default error
    target settles (its time in the artefacts' result.json) and requests at most 60 of its 800-odd tiles; a profile's
    line is drawn on the surface; the shading follows the light; the colour bar shows the heights' range
    in µm."""
    out = _artefacts("pollen")
    result = _in_chromium(
        "pollen_overview.mjs", pollen_data, "{base}/viewer/?specimen=pollen", str(out), str(STUCK_AFTER_S)
    )
    (out / "result.json").write_text(json.dumps(result, indent=1))
    assert not result["errors"], result["errors"]
    assert result["status"]["failed"] == 0
    print(
        f"pollen overview settled in {result['settleS']:.1f} s (issue 20's target 45 s) after "
        f"{result['firstViewRequests']} tile requests"
    )
    assert 5 <= result["firstViewRequests"] <= 60, result["firstViewRequests"]
    assert result["profileLinePixels"] > 300 and result["profile"]["known"] > 100 and "Ra" in result["profile"]["text"]
    # Turning the light round changes the picture; with the shading off it does not.
    assert result["lightChange"] > 4 * max(result["unlitChange"], 0.25), (result["lightChange"], result["unlitChange"])
    bar = result["colourBar"]
    assert not bar["hidden"] and bar["min"].endswith("µm") and bar["max"].endswith("µm")
    low, high = bar["rangeUm"]
    assert _numbers_in(bar["min"])[0] == pytest.approx(low, abs=0.1) and _numbers_in(bar["max"])[0] == pytest.approx(
        high, abs=0.1
    )
    assert high - low > 30  # the grain stands some 40 µm above the substrate, the datum
    assert "substrate" in bar["datum"] and result["heightColourSpread"] > 0.3


@pytest.mark.real_data
def test_the_pollen_specimen_keeps_its_magnification_and_datum(pollen_data):
    """The demo's pollen specimen is built with the TIFFs' magnification (1000x), so zooming by
    magnification works on it, and with its heights from the substrate."""
    from fractoscope.specimen.quadtree import tiles_in_region

    specimen = SpecimenStore(pollen_data).load("pollen")
    overview = specimen.rois[0]
    assert overview.magnification == 1000.0 and overview.datum["level"] == "substrate"
    cell_um = specimen.pixel_size_at_magnification(2000.0)
    assert cell_um == pytest.approx(overview.pixel_size_um / 2)
    chosen = tiles_in_region(specimen.layout, specimen.tiles, (20.0, 20.0, 40.0, 40.0), cell_um=cell_um)
    assert chosen and all(upsampled for _, upsampled in chosen)  # 2000x is beyond the data: digital zoom


# An exponent in a number as text: "1.2e+2".
_EXPONENT = re.compile(r"\d[eE][+-]?\d")


def _check_workbench(data: Path, specimen_id: str, out: Path) -> dict:
    """Issue 38's viewer on one specimen (workbench.mjs): a clean console; the orthographic top view
    with a scale bar true within 2 % against the overview's field of view (the surface's width on
    screen) and against two points picked a bar's length apart; no bar where it cannot be true;
    "Reset view" back to the first view; numbers without exponents; the snapshot's texts inside it; the
    specimen list with thumbnails; the roughness of the view at the overview's pixel size."""
    result = _in_chromium("workbench.mjs", data, "{base}", specimen_id, str(out))
    (out / "result.json").write_text(json.dumps(result, indent=1))
    assert result["console"] == [], result["console"]
    overview = SpecimenStore(data).load(specimen_id).rois[0]
    assert result["projection"] == "orthographic"
    top = result["topBar"]
    assert not top["hidden"] and not top["hintShown"] and top["label"].endswith(" µm"), top
    bar_um_per_px = _numbers_in(top["label"])[0] / top["lengthPx"]
    # The surface on screen spans the overview's field less the sides too uncertain to mesh, more
    # what coarse tiles and fills carry back into them: the bar's length puts it between the two.
    x0, _, x1, _ = overview.region_um
    shown_um = bar_um_per_px * result["surfaceWidthPx"]
    assert 0.98 * _widest_meshed_row_um(data, specimen_id) <= shown_um <= 1.02 * (x1 - x0), shown_um
    assert result["pickedHorizontalUm"] == pytest.approx(_numbers_in(top["label"])[0], rel=0.02)
    for hidden in (result["perspectiveBar"], result["topPerspectiveBar"], result["sideBar"]):
        assert hidden["hidden"] and hidden["hintShown"], hidden  # perspective, or not from above
    np.testing.assert_allclose(result["resetDirection"], np.array([0, -0.18, 0.98]) / np.hypot(0.18, 0.98), atol=1e-3)
    assert not _EXPONENT.search(result["pageText"]), result["pageText"]
    assert result["formatted"] and not [text for text in result["formatted"] if "e" in text]
    assert "Hurst" in result["pageText"] and "Profile 2:" in result["pageText"]
    assert all(0 <= text["left"] and text["right"] <= result["viewWidthPx"] for text in result["snapshotTexts"])
    assert any(text["text"] == "height" for text in result["snapshotTexts"])  # the colour bar's title
    entry = next(entry for entry in result["list"] if entry["id"] == specimen_id)
    assert entry["current"] and entry["state"] == "built" and entry["thumbnailPx"] > 0, result["list"]
    assert result["roughness"]["pixelSizeUm"] == pytest.approx(overview.pixel_size_um)
    shown = re.search(r"([\d.]+) µm/px", result["roughness"]["text"])
    assert shown and float(shown[1]) == pytest.approx(overview.pixel_size_um, rel=0.01), result["roughness"]["text"]
    return result


def _widest_meshed_row_um(data: Path, specimen_id: str) -> float:
    """The widest span of meshed heights in any row of a specimen's overview, µm: its field, less
    the columns at its sides whose heights are too uncertain to mesh (mesh.walls)."""
    from fractoscope.mesh.walls import max_meshed_sigma_um
    from fractoscope.stereo.geometry import max_measurable_slope

    specimen = SpecimenStore(data).load(specimen_id)
    overview, placed = specimen.rois[0], specimen.heights(specimen.rois[0].id)
    meshed = np.isfinite(placed.z_um)
    tilts = overview.matching.get("tilt_deg") or []
    if placed.sigma_um is not None and len(tilts) >= 2:
        bound = max_meshed_sigma_um(max_slope=max_measurable_slope(tilts), pixel_size_um=overview.pixel_size_um)
        meshed &= ~(placed.sigma_um > bound)
    cols = np.arange(meshed.shape[1])
    first = np.where(meshed, cols, meshed.shape[1]).min(axis=1)
    last = np.where(meshed, cols, -1).max(axis=1)
    return float((last - first).max() * overview.pixel_size_um)


def test_the_workbench_on_the_demo_specimen(built):
    _, _, data, _ = built
    _check_workbench(data, "synthetic", _artefacts("workbench-synthetic"))


@pytest.mark.real_data
def test_the_workbench_on_the_pollen_specimen(pollen_data):
    _check_workbench(pollen_data, "pollen", _artefacts("workbench-pollen"))


@pytest.mark.real_data
def test_the_pollen_tiles_hold_no_island_below_the_minimum(pollen_data):
    """At every level, each connected piece of the real pollen specimen's mesh covers at least the
    least island area (mesh.outline, in the ROI's pixels), however the tile borders cut it."""
    from fractoscope.mesh.outline import DEFAULT_MIN_ISLAND_PX

    folder = pollen_data / "specimens" / "pollen"
    pixel_um = SpecimenStore(pollen_data).load("pollen").rois[0].pixel_size_um
    levels = sorted({int(path.parts[-3]) for path in folder.glob("tiles/*/*/*.glb")})
    smallest = {
        level: mesh_component_areas_um2(path.read_bytes() for path in folder.glob(f"tiles/{level}/*/*.glb")).min()
        / pixel_um**2
        for level in levels
    }
    assert len(levels) > 3 and min(smallest.values()) >= DEFAULT_MIN_ISLAND_PX, smallest


@pytest.mark.real_data
def test_the_pollen_tiles_show_no_seams(pollen_data):
    """Neighbouring tiles of the real pollen pair's specimen agree along their shared borders
    within 2 grey levels: the texture is normalized per ROI, never per tile."""
    worst = tile_seams_grey_levels(pollen_data / "specimens" / "pollen")
    assert len(worst) > 4 and max(worst) <= 2, worst


@pytest.mark.real_data
def test_a_build_submitted_over_http_shows_its_progress_in_the_page(pollen_series, tmp_path):
    """The viewer is open when a lab system submits a build (POST /api/jobs, multipart: the real
    pollen pair, long enough to be watched): the specimen list
    shows it under way with a progress bar that never goes back, then built with its thumbnail,
    and the console stays clean."""
    manifest = {"specimen": "submitted", "rois": [{"id": "pot", "left": "pot_02.tif", "right": "pot_04.tif"}]}
    server, port = create_server(ServerConfig(address="127.0.0.1:0", data_dir=tmp_path / "data"))
    server.start()
    http = start_http_server(SpecimenStore(tmp_path / "data"))
    http.send_builds_to(f"127.0.0.1:{port}")
    base, ready = f"http://127.0.0.1:{http.server_port}", tmp_path / "page-ready"
    try:
        page = subprocess.Popen(
            ["node", str(Path(__file__).resolve().parent / "build_progress.mjs"), base, "submitted", str(ready), "900"],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            cwd=ROOT,
        )
        deadline = time.monotonic() + 120
        while not ready.exists():
            assert page.poll() is None, page.stderr.read()[-3000:]
            assert time.monotonic() < deadline, "the page did not open within 120 s"
            time.sleep(0.2)
        parts = [("manifest", (None, json.dumps(manifest), "application/json"))]
        for name in ("pot_02.tif", "pot_04.tif"):
            parts.append(("images", (name, (pollen_series / name).read_bytes(), "image/tiff")))
        answer = requests.post(f"{base}/api/jobs", files=parts, timeout=120)
        assert answer.status_code == 202, answer.text
        out, err = page.communicate(timeout=1200)
        assert page.returncode == 0, err[-3000:]
    finally:
        http.shutdown()
        server.stop(grace=None)
    result = json.loads(out.splitlines()[-1])
    (_artefacts("build-progress") / "result.json").write_text(json.dumps(result, indent=1))
    assert result["console"] == [], result["console"]
    assert result["states"][-1] == "built" and result["thumbnailPx"] > 0, result
    assert "building" in result["states"], result  # seen under way, not only once done
    fractions = [float(value.rstrip("%")) for value in result["fractions"]]
    assert fractions and fractions == sorted(fractions), result  # a bar while it ran, never going back


def test_a_specimen_rebuilt_while_shown_opens_again_with_the_view_kept(built, tmp_path):
    """Tiles asked for under a build since replaced are 410 Gone (issue 49, item 9): the viewer
    opens the specimen again, as it is now, with its camera, and settles with nothing failed."""
    _, _, data, _ = built
    copy = tmp_path / "data"
    shutil.copytree(data / "specimens", copy / "specimens")
    http = start_http_server(SpecimenStore(copy))
    base, ready, go = f"http://127.0.0.1:{http.server_port}", tmp_path / "ready", tmp_path / "go"
    script = Path(__file__).resolve().parent / "replaced_build.mjs"
    try:
        page = subprocess.Popen(
            ["node", str(script), base, "synthetic", str(ready), str(go)],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            cwd=ROOT,
        )
        deadline = time.monotonic() + STUCK_AFTER_S
        while not ready.exists():
            assert page.poll() is None, page.stderr.read()[-3000:]
            assert time.monotonic() < deadline, "the page did not settle"
            time.sleep(0.2)
        description = copy / "specimens" / "synthetic" / "specimen.json"
        os.utime(description, ns=(time.time_ns(), time.time_ns()))  # a new build of the same content
        go.write_text("")
        out, err = page.communicate(timeout=900)
        assert page.returncode == 0, err[-3000:]
    finally:
        http.shutdown()
    result = json.loads(out.splitlines()[-1])
    (_artefacts("replaced-build") / "result.json").write_text(json.dumps(result, indent=1))
    assert result["gone"] >= 1 and result["status"]["reopened"] == 1, result
    assert result["status"]["failed"] == 0 and result["status"]["loaded"] >= 1 and not result["console"], result
    assert np.allclose(result["after"], result["before"], rtol=1e-6, atol=1e-12), result  # the view kept

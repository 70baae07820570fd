"""Our tilesets and the web viewer in headless Chromium (Debian's, which `make test` installs),
driven by the scripts in tests/js through playwright-core."""

import json
import subprocess
from pathlib import Path

import pytest

from fractoscope.services.tiles.http import start_http_server
from fractoscope.specimen.store import SpecimenStore

pytestmark = pytest.mark.slow


def _in_chromium(script: str, data: Path, path: str, screenshot: Path) -> dict:
    """Runs tests/js/SCRIPT against `path` on an HTTP endpoint serving `data`; its JSON result."""
    http = start_http_server(SpecimenStore(data))
    runner = Path(__file__).resolve().parents[1] / "js" / script
    try:
        done = subprocess.run(
            ["node", str(runner), f"http://127.0.0.1:{http.server_port}{path}", str(screenshot)],
            capture_output=True, text=True, timeout=400, cwd=runner.parents[2],
        )
    finally:
        http.shutdown()
    assert done.returncode == 0, done.stderr[-2000:]
    return json.loads(done.stdout.splitlines()[-1])


def test_tileset_loads_in_3d_tiles_renderer_in_headless_chromium(built, tmp_path):
    _, _, data, _ = built
    result = _in_chromium("load_tileset.mjs", data, "/specimens/synthetic/tileset.json", tmp_path / "view.png")
    assert result["tilesetLoaded"] and not result["failed"] and not result["errors"], result
    assert result["loaded"] >= 5  # the root and refining levels streamed in
    assert result["litFraction"] > 0.3  # the textured surface fills much of the view


def test_web_viewer_streams_tiles_and_measures_a_profile(built, tmp_path):
    """The viewer page, served by the tile endpoint, in headless Chromium: tiles requested and
    drawn, the profile tool (two clicks) and the roughness panel return numbers."""
    _, _, data, _ = built
    result = _in_chromium("check_viewer.mjs", data, "/viewer/?specimen=synthetic", tmp_path / "viewer.png")
    assert not result["errors"] and result["status"]["failed"] == 0, result
    assert result["tileRequests"] >= 5 and result["status"]["loaded"] >= 5
    assert result["litFraction"] > 0.2
    assert result["profile"]["samples"] > 100 and result["profile"]["parameters"]["Ra"] > 0
    assert "Ra" in result["profile"]["text"]
    assert result["roughness"]["Sa"] > 0 and 0 < result["roughness"]["hurst_exponent"] < 1.5
    assert result["scaleBar"].endswith("µm")
    assert result["heightColourSpread"] > 0.3  # heights from the dequantized positions span the ramp

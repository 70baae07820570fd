"""`fracto height` as a user runs it: a subprocess, embedded or against a running server."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pygltflib
import pytest
import tifffile
from conftest import fracture_pair

from fractoscope import synthetic
from fractoscope.formats.calibration import Calibration
from fractoscope.formats.height_npz import read_height_npz, write_height_npz

FRACTO = str(Path(sys.executable).with_name("fracto"))


@pytest.fixture(scope="module")
def pair_files(tmp_path_factory):
    directory = tmp_path_factory.mktemp("pair")
    pair = fracture_pair(size_px=256, seed=11)
    paths = directory / "left.tif", directory / "right.png"
    tifffile.imwrite(paths[0], pair.first)
    from PIL import Image

    Image.fromarray(pair.second).save(paths[1])
    return paths, pair


def _run(*args, env_extra=None):
    env = {k: v for k, v in os.environ.items() if k != "FRACTO_SERVER"}
    env.update(env_extra or {})
    return subprocess.run([FRACTO, *map(str, args)], capture_output=True, text=True, env=env, timeout=300)


@pytest.mark.slow
def test_height_writes_the_npz_contract(pair_files, tmp_path):
    (left, right), pair = pair_files
    out = tmp_path / "out.npz"
    done = _run(
        "height", left, right, "--tilt", "-5", "5", "--pixel-size-um", "0.1", "-o", out, "--json", "--level", "plane"
    )
    assert done.returncode == 0, done.stderr
    summary = json.loads(done.stdout)
    assert summary["valid_fraction"] > 0.6  # contract check; accuracy is tested on 640² pairs
    assert summary["datum"]["level"] == "plane"
    with np.load(out) as arrays:
        assert arrays["z_um"].shape == pair.first.shape and arrays["z_um"].dtype == np.float32
        assert arrays["sigma_um"].shape == pair.first.shape
        assert abs(np.nanmean(arrays["z_um"])) < 0.05 * np.ptp(pair.z_seen_um)  # zero on the fitted plane
        datum = summary["datum"]
        rows, cols = np.indices(arrays["z_um"].shape) * 0.1
        error = arrays["z_um"] + datum["offset_um"] + datum["slope_x"] * cols + datum["slope_y"] * rows - pair.z_seen_um
        assert np.nanstd(error[16:-16, 16:-16]) < 0.03 * np.ptp(pair.z_seen_um)
    heights = read_height_npz(out)  # the calibration travels with the heights
    assert heights.calibration.tilt_deg == (-5.0, 5.0) and heights.calibration.tilt_source == ("argument", "argument")
    assert heights.calibration.pixel_size_um == 0.1 and heights.calibration.pixel_size_source == "argument"
    assert heights.calibration.tilt_sigma_deg == (0.5, 0.5) and heights.record["tilt_axis_deg"] == 90.0
    assert heights.max_slope == pytest.approx(1 / np.sin(np.radians(10)) * np.cos(np.radians(5)))
    assert (
        heights.record["datum"]["level"] == "plane"
        and heights.record["report"]["valid_fraction"] == summary["valid_fraction"]
    )
    assert heights.record["method"] == heights.record["parameters"]["method"] == "tgv_zncc"
    assert np.nanmedian(heights.local_sigma_um) < np.nanmedian(heights.sigma_um)  # the tilt's shared error left out


@pytest.mark.slow
def test_height_names_the_method_and_takes_the_others_on_request(pair_files, tmp_path):
    (left, right), pair = pair_files
    for method, expected in (("window-zncc", "window_zncc"), ("fast", "fast"), (None, "tgv_zncc")):
        out = tmp_path / f"{expected}.npz"
        extra = ["--method", method] if method else []
        done = _run("height", left, right, "--tilt", "-5", "5", "--pixel-size-um", "0.1", *extra, "-o", out, "--json")
        assert done.returncode == 0, done.stderr
        assert json.loads(done.stdout)["report"]["method"] == expected
    done = _run("height", left, right, "--method", "sgbm", "-o", tmp_path / "x.npz")
    assert done.returncode == 2 and "--method" in done.stderr


@pytest.mark.slow
def test_height_never_claims_a_substrate_the_surface_lacks(pair_files, tmp_path):
    """The rough fracture surface has no flat level and no plane under it: --level substrate
    leaves the heights as measured (never a plane through all of them) and says so in the text
    summary, on stderr and in the file; --strict-level refuses and writes nothing."""
    (left, right), _ = pair_files
    out = tmp_path / "out.npz"
    calibration = ["--tilt", "-5", "5", "--pixel-size-um", "0.1", "--level", "substrate"]
    done = _run("height", left, right, *calibration, "-o", out)
    assert done.returncode == 0, done.stderr
    assert "warning: --level substrate: no measured substrate" in done.stderr
    assert "datum: none, the heights as measured" in done.stdout and "warning: no measured substrate" in done.stdout
    datum = read_height_npz(out).record["datum"]
    assert datum["level"] == "none" and datum["requested"] == "substrate" and "times their sigma" in datum["warning"]
    assert datum["tilt_deg"] == 0 and datum["residual_rms_um"] is None
    refused = _run("height", left, right, *calibration, "--strict-level", "-o", tmp_path / "strict.npz")
    assert refused.returncode == 2 and "error: --level substrate: no measured substrate" in refused.stderr
    assert not (tmp_path / "strict.npz").exists()


def test_height_against_a_running_server(pair_files, tmp_path, server_address):
    (left, right), _ = pair_files
    out = tmp_path / "out.npz"
    done = _run(
        "height",
        left,
        right,
        "--tilt",
        "-5",
        "5",
        "--pixel-size-um",
        "0.1",
        "-o",
        out,
        env_extra={"FRACTO_SERVER": server_address},
    )
    assert done.returncode == 0, done.stderr
    assert "% matched" in done.stdout and out.is_file()
    without_contrast = tmp_path / "without_contrast.npz"
    done = _run(
        "height",
        left,
        right,
        "--tilt",
        "-5",
        "5",
        "--pixel-size-um",
        "0.1",
        "--no-local-contrast",
        "-o",
        without_contrast,
        env_extra={"FRACTO_SERVER": server_address},
    )
    assert done.returncode == 0, done.stderr
    propagated = tmp_path / "propagated.npz"
    done = _run(
        "height",
        left,
        right,
        "--tilt",
        "-5",
        "5",
        "--pixel-size-um",
        "0.1",
        "--propagate-at-full-resolution",
        "-o",
        propagated,
        env_extra={"FRACTO_SERVER": server_address},
    )
    assert done.returncode == 0, done.stderr
    with (
        np.load(out) as default,
        np.load(without_contrast) as plain,
        np.load(propagated) as with_neighbours,
    ):  # the options reached the matcher
        assert not np.array_equal(default["z_um"], plain["z_um"], equal_nan=True)
        assert not np.array_equal(default["z_um"], with_neighbours["z_um"], equal_nan=True)


@pytest.mark.slow
@pytest.mark.parametrize(
    "extra, message",
    [
        (
            ["--tilt", "3", "3", "--pixel-size-um", "0.1"],
            "error: --tilt: the two tilts must differ",
        ),  # the flag, not images[1].tilt_deg
        (["--pixel-size-um", "0.1"], "error: give --tilt T1 T2 (no stage tilt in the metadata of left.tif, right.png)"),
        (
            [],
            "error: give --tilt T1 T2 (no stage tilt in the metadata of left.tif, right.png) and --pixel-size-um P "
            "(no pixel size in the metadata of left.tif)",
        ),  # every missing value at once
        (["--tilt", "-5", "5", "--pixel-size-um", "-1"], "error: --pixel-size-um: must be between"),
        (["--tilt", "-5", "5", "--tlit", "3"], "did you mean --tilt?"),
        (["--tilt", "-5", "5", "--level", "floor"], "--level: expected plane or substrate or X0,Y0,X1,Y1"),
    ],
)
def test_bad_input_gives_one_line_and_exit_code_2(pair_files, tmp_path, extra, message):
    (left, right), _ = pair_files
    done = _run("height", left, right, *extra, "-o", tmp_path / "x.npz")
    assert done.returncode == 2
    lines = [line for line in done.stderr.strip().splitlines() if not line.startswith("usage:")]
    assert len(lines) == 1 and message in lines[0], done.stderr


def test_a_mistyped_verb_gets_a_suggestion():
    done = _run("heigth", "a.tif", "b.tif")
    assert done.returncode == 2 and "did you mean height?" in done.stderr


@pytest.mark.slow
def test_unreadable_and_mismatched_images_give_one_line_and_exit_code_2(pair_files, tmp_path):
    (left, right), pair = pair_files
    garbage = tmp_path / "garbage.tif"
    garbage.write_bytes(b"II*\x00 this is not really a TIFF")
    small = tmp_path / "small.tif"
    tifffile.imwrite(small, pair.second[:200])
    for second, message in ((garbage, "corrupt TIFF"), (small, "differs from the first image's")):
        done = _run("height", left, second, "--tilt", "-5", "5", "--pixel-size-um", "0.1", "-o", tmp_path / "x.npz")
        assert done.returncode == 2
        lines = done.stderr.strip().splitlines()
        assert (
            len(lines) == 1 and lines[0].startswith(f"error: {second}: ") and message in lines[0]
        )  # the file, not images[1]


@pytest.mark.slow
def test_missing_file_and_unreachable_server(pair_files, tmp_path):
    (left, _), _ = pair_files
    done = _run("height", left, tmp_path / "absent.tif", "--tilt", "-5", "5", "-o", tmp_path / "x.npz")
    assert done.returncode == 2 and "absent.tif" in done.stderr
    done = _run(
        "height",
        left,
        left,
        "--tilt",
        "-5",
        "5",
        "--pixel-size-um",
        "0.1",
        "-o",
        tmp_path / "x.npz",
        "--server",
        "127.0.0.1:1",
    )
    assert done.returncode == 3
    assert done.stderr == (
        "error: the Fractoscope server at 127.0.0.1:1 cannot be reached; start it (fracto-server) or point --server "
        "or FRACTO_SERVER at a running one\n"
    )


@pytest.mark.slow
def test_height_then_mesh_writes_valid_glb_levels(pair_files, tmp_path):
    from conftest import validate_glbs

    (left, right), _ = pair_files
    heights = tmp_path / "heights.npz"
    assert _run("height", left, right, "--tilt", "-5", "5", "--pixel-size-um", "0.1", "-o", heights).returncode == 0
    out = tmp_path / "tiles"
    done = _run("mesh", heights, "--texture", left, "-o", out, "--json")  # the pixel size comes from the npz
    assert done.returncode == 0, done.stderr
    summary = json.loads(done.stdout)
    assert summary["pixel_size_um"] == 0.1 and summary["max_slope"] == pytest.approx(
        np.cos(np.radians(5)) / np.sin(np.radians(10))
    )
    errors = [row["geometric_error_m"] for row in summary["levels"]]
    assert len(errors) >= 2 and errors[0] == 0.0 and errors == sorted(errors)
    glbs = sorted(out.rglob("*.glb"))
    assert len(glbs) == sum(row["tiles"] for row in summary["levels"])
    assert all(report["errors"] == 0 for report in validate_glbs([p.read_bytes() for p in glbs], tmp_path))
    assert all(b"EXT_meshopt_compression" in p.read_bytes() for p in glbs)
    plain = tmp_path / "plain"
    assert _run("mesh", heights, "--pixel-size-um", "0.1", "-o", plain, "--plain-glb", "--levels", "2").returncode == 0
    plain_glbs = sorted(plain.rglob("*.glb"))
    assert plain_glbs and not any(b"EXT_meshopt_compression" in p.read_bytes() for p in plain_glbs)
    done = _run("mesh", heights, "--texture", right, "--pixel-size-um", "-1", "-o", out)
    assert done.returncode == 2 and done.stderr.startswith("error: --pixel-size-um: must be between")
    older = tmp_path / "older.npz"
    with np.load(heights) as arrays:
        np.savez(older, z_um=arrays["z_um"])
    done = _run("mesh", older, "-o", out)
    assert done.returncode == 2 and "records no calibration" in done.stderr and "--pixel-size-um" in done.stderr


@pytest.mark.slow
def test_demo_builds_the_specimens_and_prints_the_viewer_url(tmp_path):
    done = _run(
        "demo", "--data", tmp_path / "data", "--shared-data", tmp_path / "none", "--port", 0, "--http-port", 0, "--exit"
    )
    assert done.returncode == 0, done.stderr
    assert "viewer: http://127.0.0.1:" in done.stdout and "/viewer/?specimen=synthetic" in done.stdout
    assert "found" in done.stdout  # the ROI's automatic placement checked against the truth
    assert (tmp_path / "data" / "specimens" / "synthetic" / "tileset.json").is_file()
    lines = done.stdout.splitlines()
    progress = [line for line in lines if line.startswith("synthetic: ") and " % " in line]
    assert len(progress) >= 4 and any(
        "matching ROI overview" in line for line in progress
    )  # a log shows the build going on
    assert "synthetic: roughness of ROI zoom ..." in lines  # and the seconds between a build and the next
    table = lines[lines.index("Fractoscope demo specimens") :]
    assert table[1].split() == ["specimen", "ROI", "mag.", "µm/px", "at", "x,", "y", "µm", "Sz", "µm", "Sa", "µm"]
    assert all(len(line) <= 80 for line in table if not line.startswith(("viewer:", "gRPC:", "data:")))
    assert any(line.startswith("synthetic  zoom ") and "400x" in line for line in table)


@pytest.mark.slow
def test_specimen_commands_from_a_manifest(tmp_path):
    from fractoscope.synthetic.examples import write_multiscale_specimen

    write_multiscale_specimen(tmp_path / "input")
    data = tmp_path / "data"
    built = _run("reconstruct", tmp_path / "input" / "manifest.json", "--data", data, "--unmeasured", "flat")
    assert built.returncode == 0, built.stderr
    assert built.stdout.strip() == "synthetic"
    profile = _run(
        "profile",
        "synthetic",
        "--from",
        "100,200",
        "--to",
        "400,250",
        "-o",
        tmp_path / "p.csv",
        "--plot",
        tmp_path / "p.png",
        "--data",
        data,
    )
    assert profile.returncode == 0, profile.stderr
    rows = (tmp_path / "p.csv").read_text().splitlines()
    assert rows[0] == "distance_um,z_um,source" and {row.rsplit(",", 1)[1] for row in rows[1:]} == {"overview", "zoom"}
    assert (tmp_path / "p.png").read_bytes()[:4] == b"\x89PNG"
    rough = _run("roughness", "synthetic", "--roi", "zoom", "--json", "--data", data)
    values = json.loads(rough.stdout)
    assert {"Sa", "Sq", "Ssk", "Sku", "Sp", "Sv", "Sz", "Sdq", "Sdr", "hurst_exponent", "fractal_dimension"} <= set(
        values
    )
    zoom = _run("zoom", "synthetic", "--region", "270,200,300,240", "--magnification", "400", "--json", "--data", data)
    assert {tile["zoom"] for tile in json.loads(zoom.stdout)["tiles"]} == {"optical"}
    tiles = _run("tiles", "synthetic", "-o", tmp_path / "download", "--data", data)
    assert tiles.returncode == 0 and (tmp_path / "download" / "tileset.json").is_file()
    materials = {
        material.name
        for glb in (tmp_path / "download").rglob("*.glb")
        for material in pygltflib.GLTF2.load_from_bytes(glb.read_bytes()).materials
    }
    assert "unmeasured" in materials  # --unmeasured flat: a floor where nothing was measured
    missing = _run("roughness", "nothing", "--data", data)
    assert missing.returncode == 4 and missing.stderr.count("\n") == 1


@pytest.mark.slow
def test_height_png_is_a_picture(pair_files, tmp_path):
    (left, right), _ = pair_files
    done = _run(
        "height",
        left,
        right,
        "--tilt",
        -5,
        5,
        "--pixel-size-um",
        0.1,
        "-o",
        tmp_path / "h.npz",
        "--png",
        tmp_path / "h.png",
        "--json",
    )
    assert done.returncode == 0, done.stderr
    from PIL import Image

    with Image.open(tmp_path / "h.png") as picture:
        colours = np.asarray(picture.convert("RGB"))
    assert (
        picture.width > 400 and len(np.unique(colours.reshape(-1, 3), axis=0)) > 1000
    )  # a shaded colour map, not blank
    assert json.loads(done.stdout)["png"] == str(tmp_path / "h.png")


@pytest.mark.slow
def test_demo_serves_until_stopped_and_then_exits_cleanly(tmp_path):
    import signal
    import time
    import urllib.request

    process = subprocess.Popen(
        [
            FRACTO,
            "demo",
            "--data",
            str(tmp_path / "data"),
            "--shared-data",
            str(tmp_path / "none"),
            "--port",
            "0",
            "--http-port",
            "0",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        url = None
        deadline = time.monotonic() + 240
        while url is None and time.monotonic() < deadline:
            line = process.stdout.readline()
            if line.startswith("viewer: "):
                url = line.split()[1]
        assert url, process.stderr.read() if process.poll() is not None else "no viewer URL"
        with urllib.request.urlopen(url) as page:
            assert b"3d-tiles-renderer" in page.read()
        process.send_signal(signal.SIGTERM)
        assert process.wait(timeout=30) == 0
    finally:
        if process.poll() is None:
            process.kill()


@pytest.mark.slow
def test_height_of_a_tilt_series_with_calibrated_tilts(tmp_path):
    from fractoscope import synthetic

    surface = synthetic.self_affine_surface((320, 320), hurst=0.8, rms_um=2.5, seed=9)
    images, _ = synthetic.render_tilt_series(
        surface, pixel_size_um=0.1, tilt_deg=(-5.0, 0.0, 5.0), output_shape=(256, 256), seed=9
    )
    paths = []
    for index, image in enumerate(images):
        paths.append(tmp_path / f"view_{index}.tif")
        tifffile.imwrite(paths[-1], image)
    done = _run(
        "height", *paths, "--tilt", -5, 0.4, 5.4, "--pixel-size-um", 0.1, "--calibrate-tilt", "-o", tmp_path / "h.npz"
    )
    assert done.returncode == 0, done.stderr
    assert "tilts estimated" in done.stdout
    with np.load(tmp_path / "h.npz") as arrays:
        estimated = arrays["tilt_deg_estimated"]
        assert arrays["z_um"].shape == (256, 256)
    # On 256² views the calibrated steps scatter by 0.02-0.3° over surface seeds (this one: 0.27°),
    # within two of the sigmas the file reports (1.3 here; 3.9 while the tilt fit took its
    # points for independent).
    sigma_deg = np.array(read_height_npz(tmp_path / "h.npz").calibration.tilt_sigma_deg)
    assert estimated[0] == -5.0 and np.abs(np.diff(estimated) - 5.0).max() < 0.3
    assert np.all(np.abs(estimated - np.array([-5.0, 0.0, 5.0])) <= 2 * sigma_deg)
    too_few = _run("height", *paths[:2], "--calibrate-tilt", "-o", tmp_path / "x.npz")
    assert too_few.returncode == 2 and "three or more" in too_few.stderr


@pytest.mark.slow
@pytest.mark.real_data
def test_the_real_pair_meshes_with_its_stored_calibration(pollen_series, tmp_path):
    """The user's first session on the pollen pair: heights with the substrate as datum, then
    mesh with nothing asked again. Tiles where nothing was measured (the pair's upper corner) are
    left out instead of ending in a traceback, and the grain's rim becomes walls."""
    heights = tmp_path / "pot.npz"
    left, right = pollen_series / "pot_02.tif", pollen_series / "pot_04.tif"
    done = _run("height", left, right, "--level", "substrate", "-o", heights, "--json")
    assert done.returncode == 0, done.stderr
    stored = read_height_npz(heights)
    assert stored.calibration.tilt_deg == (-3.0, 3.0) and stored.calibration.tilt_source == ("metadata", "metadata")
    assert stored.pixel_size_um == pytest.approx(0.05582) and stored.calibration.pixel_size_source == "metadata"
    grain_top = np.nanpercentile(stored.z_um[770:1370, 430:1030], 99)
    assert abs(np.nanmedian(stored.z_um[stored.z_um < 5])) < 0.5 and 35 < grain_top < 50  # the grain stands on zero
    datum = json.loads(done.stdout)["datum"]  # measured: 48 % of the map, 0.67 µm RMS against a sigma of 0.39 µm
    assert datum == stored.record["datum"] and datum["level"] == "substrate" and not datum["warning"]
    assert datum["area_fraction"] > 0.3 and datum["residual_rms_um"] < 3 * datum["sigma_um"] and datum["tilt_deg"] < 2
    done = _run("mesh", heights, "--texture", left, "-o", tmp_path / "tiles", "--json")
    assert done.returncode == 0, done.stderr
    summary = json.loads(done.stdout)
    finest = summary["levels"][0]
    assert finest["tiles"] < 63  # 7 x 9 tiles of 254 cells; those with no measured point are skipped
    assert all(level["tiles"] > 0 for level in summary["levels"]) and finest["wall_triangles"] > 1000
    assert len(list((tmp_path / "tiles").rglob("*.glb"))) == sum(level["tiles"] for level in summary["levels"])


def _textured_form(form: str) -> tuple[np.ndarray, np.ndarray]:
    """(heights µm, texture µm): a known form at 0.2 µm/px carrying a known self-affine texture."""
    texture = synthetic.self_affine_surface((384, 384), hurst=0.7, rms_um=0.4, seed=5, max_wavelength_px=30)
    rows, cols = np.indices(texture.shape) * 0.2
    shapes = {
        "poly2": 0.004 * cols**2 - 0.002 * cols * rows + 0.05 * rows,
        "sphere": np.sqrt(300.0**2 - (cols - 38) ** 2 - (rows - 38) ** 2),
    }
    return shapes[form] + texture, texture


def _sa(z: np.ndarray) -> float:
    return float(np.mean(np.abs(z - z.mean())))


@pytest.mark.slow
def test_roughness_of_an_npz_height_map(tmp_path):
    z, texture = _textured_form("poly2")
    with_size = tmp_path / "map.npz"
    calibration = Calibration((-5.0, 5.0), ("metadata", "metadata"), (0.5, 0.5), 0.2, "argument")
    sigma_um = np.full(z.shape, 0.01, np.float32)
    write_height_npz(
        with_size,
        z_um=z,
        sigma_um=sigma_um,
        confidence=np.ones_like(sigma_um),
        local_sigma_um=sigma_um,
        calibration=calibration,
        record={"report": {"tilt_uncertainty_deg": 0.5}},
    )
    done = _run("roughness", with_size, "--form", "poly2", "--direction-deg", "90", "--json")
    assert done.returncode == 0, done.stderr
    values = json.loads(done.stdout)
    assert values["Sa"] == pytest.approx(_sa(texture), rel=0.01)
    assert (
        values["chain"]["form"] == "poly2"
        and values["chain"]["direction_deg"] == 90.0
        and values["pixel_size_um"] == 0.2
    )
    assert values["uncertainty"]["Sa"]["u_noise"] > 0 and values["noise_bias"]["Sq"] > 0
    assert values["tilt_rel_uncertainty"] == pytest.approx(
        0.1, rel=0.01
    )  # epsilon_z = 0.5 deg / tan 5 deg, as the file records
    bare = tmp_path / "bare.npz"
    np.savez(bare, z_um=z.astype(np.float32))
    refused = _run("roughness", bare, "--json")
    assert refused.returncode == 2 and "--pixel-size-um" in refused.stderr and refused.stderr.count("\n") == 1
    given = _run("roughness", bare, "--pixel-size-um", "0.2", "--form", "poly2", "--l-filter-um", "8")
    assert given.returncode == 0, given.stderr
    assert "form poly2" in given.stdout and "λc 8 µm" in given.stdout and "Sa" in given.stdout
    wrong = _run("roughness", with_size, "--roi", "overview")
    assert wrong.returncode == 2 and "--roi" in wrong.stderr


@pytest.mark.slow
def test_roughness_of_an_x3p_file(tmp_path):
    from fractoscope.formats.x3p import write_x3p

    z, texture = _textured_form("sphere")
    path = tmp_path / "dome.x3p"
    write_x3p(path, z, pixel_size_um=0.2)
    done = _run("roughness", path, "--form", "sphere", "--json")
    assert done.returncode == 0, done.stderr
    values = json.loads(done.stdout)
    assert values["Sa"] == pytest.approx(_sa(texture), rel=0.01)
    assert values["chain"]["form"] == "sphere" and values["chain"]["window_px"] == 1.0
    assert values["uncertainty"]["Sa"]["u_total"] is None  # an X3P file carries no sigma map
    assert {fit["method"] for fit in values["hurst"]} == {"hhc", "psd"}
    filtered = json.loads(
        _run("roughness", path, "--form", "sphere", "--s-filter-um", "0.5", "--l-filter-um", "10", "--json").stdout
    )
    assert (filtered["chain"]["s_filter_um"], filtered["chain"]["l_filter_um"]) == (0.5, 10.0) and filtered[
        "Sa"
    ] < values["Sa"]
    bad = _run("roughness", path, "--s-filter-um", "20", "--l-filter-um", "10")
    assert bad.returncode == 2 and bad.stderr.startswith("error: --s-filter-um: must be below")


@pytest.mark.slow
def test_list_export_and_report_of_a_stored_specimen(built, tmp_path):
    """The forms the issue fixes: `fracto list`, `fracto export SOURCE [--roi | --region]
    [--pixel-size-um] -o OUT.ext [--solid] [--units]` and `fracto report SPECIMEN -o .html --pdf`."""
    _, _, data, summary = built
    listed = _run("list", "--data", data, "--json")
    assert listed.returncode == 0, listed.stderr
    assert [s["id"] for s in json.loads(listed.stdout)["specimens"]] == ["synthetic"]
    done = _run("export", "synthetic", "--roi", "zoom", "-o", tmp_path / "zoom.tif", "--data", data, "--json")
    assert done.returncode == 0, done.stderr
    assert tifffile.imread(tmp_path / "zoom.tif").shape == (512, 512)
    region = summary["rois"][1]["region"]
    x0, y0 = region["min"]["x_um"], region["min"]["y_um"]
    box = f"{x0 + 4},{y0 + 4},{x0 + 24},{y0 + 14}"
    done = _run(
        "export",
        "synthetic",
        "--region",
        box,
        "--pixel-size-um",
        "0.5",
        "-o",
        tmp_path / "region.stl",
        "--solid",
        "--units",
        "mm",
        "--data",
        data,
        "--json",
    )
    assert done.returncode == 0, done.stderr
    assert (json.loads(done.stdout)["rows"], json.loads(done.stdout)["cols"]) == (21, 41)
    done = _run(
        "report",
        "synthetic",
        "--roi",
        "zoom",
        "-o",
        tmp_path / "report.html",
        "--pdf",
        tmp_path / "report.pdf",
        "--data",
        data,
    )
    assert done.returncode == 0, done.stderr
    assert (
        "Measurement report" in (tmp_path / "report.html").read_text()
        and (tmp_path / "report.pdf").read_bytes()[:5] == b"%PDF-"
    )
    wrong = _run("export", "synthetic", "-o", tmp_path / "zoom.docx", "--data", data)
    assert wrong.returncode == 2 and wrong.stderr.count("\n") == 1 and ".x3p" in wrong.stderr


@pytest.mark.slow
def test_export_of_an_npz_height_map(tmp_path):
    z_um = np.linspace(0, 1, 40 * 30, dtype=np.float32).reshape(30, 40)
    np.savez(tmp_path / "map.npz", z_um=z_um, sigma_um=np.full_like(z_um, 0.01))
    done = _run("export", tmp_path / "map.npz", "--pixel-size-um", "0.2", "-o", tmp_path / "map.csv", "--json")
    assert done.returncode == 0, done.stderr
    lines = (tmp_path / "map.csv").read_text().splitlines()
    assert lines[0] == "x_um,y_um,z_um,sigma_um" and len(lines) == 1 + z_um.size
    assert [float(v) for v in lines[-1].split(",")] == pytest.approx([39 * 0.2, 29 * 0.2, 1.0, 0.01], rel=1e-6)
    missing = _run("export", tmp_path / "map.npz", "-o", tmp_path / "map.x3p")
    assert missing.returncode == 2 and "--pixel-size-um" in missing.stderr

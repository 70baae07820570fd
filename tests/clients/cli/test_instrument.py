"""`fracto instrument learn` (issue 46): where an instrument's side detector lies, learned from one
pair whose tilts are trusted, then applied to that instrument's other pairs by their metadata, so
that pairs typed with reversed tilts come out the right way up."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from fractoscope import synthetic
from fractoscope.synthetic.files import fei_tiff
from fractoscope.synthetic.physics import SemPhysics

FRACTO = str(Path(sys.executable).with_name("fracto"))
# Another microscope: a side detector in the chamber at the image's lower left.
INSTRUMENT = SemPhysics(detector_azimuth_deg=215.0, detector_in_chamber=True, detector_strength=0.5)
TILT_PAIRS_DEG = ((-5.0, 5.0), (5.0, -5.0), (0.0, 5.0))


def _run(*args, profiles: Path):
    env = {k: v for k, v in os.environ.items() if k != "FRACTO_SERVER"} | {"FRACTO_INSTRUMENTS": str(profiles)}
    return subprocess.run([FRACTO, *map(str, args)], capture_output=True, text=True, env=env, timeout=300)


def _pair_files(directory: Path, seed: int, kind: str, tilts, *, scan_rotation_deg: float = 0.0):
    surface = synthetic.reference_surface(kind, 256 + 64, seed=3000 + seed)
    pair = synthetic.render_stereo_pair(
        surface, pixel_size_um=0.1, tilt_deg=tilts, output_shape=(256, 256), seed=seed, physics=INSTRUMENT
    )
    paths = []
    for index, (image, tilt) in enumerate(zip((pair.first, pair.second), tilts)):
        path = directory / f"pair{seed}_{index}.tif"
        path.write_bytes(fei_tiff(image, tilt_deg=tilt, pixel_size_um=0.1, scan_rotation_deg=scan_rotation_deg))
        paths.append(path)
    return paths, pair.z_seen_um


@pytest.mark.slow
def test_a_profile_learned_on_one_pair_turns_the_instruments_reversed_pairs_the_right_way_up(tmp_path):
    profiles = tmp_path / "instruments.json"
    learned_from, _ = _pair_files(tmp_path, 0, "self_affine", (-5.0, 5.0))
    learned = _run("instrument", "learn", *learned_from, "--json", profiles=profiles)
    assert learned.returncode == 0, learned.stderr
    profile = json.loads(learned.stdout)
    assert profile["profile"] == "FEI/Thermo Fisher Quanta 250 FEG, detector ETD, scan rotation 0°"
    assert abs(profile["detector_from_tilt_axis_deg"] - INSTRUMENT.detector_from_tilt_axis_deg) < 20.0
    listed = _run("instrument", "list", profiles=profiles)
    assert "Quanta 250 FEG" in listed.stdout and "pair0_0.tif" in listed.stdout
    for seed, kind in enumerate(("dimples", "self_affine", "dimples"), start=1):
        tilts = TILT_PAIRS_DEG[seed % len(TILT_PAIRS_DEG)]
        paths, truth = _pair_files(tmp_path, seed, kind, tilts)
        out = tmp_path / f"h{seed}.npz"
        done = _run("height", *paths, "--tilt", -tilts[0], -tilts[1], "-o", out, "--json", profiles=profiles)
        assert done.returncode == 0, done.stderr
        report = json.loads(done.stdout)["report"]
        assert report["relief_sign"] == "inverted" and report["detector_source"] == "profile", report
        assert profile["profile"] in report["relief_sign_sentence"]
        z_um = np.load(out)["z_um"]
        known = np.isfinite(z_um)
        assert np.corrcoef(z_um[known], truth[known])[0, 1] > 0.95


@pytest.mark.slow
def test_a_profile_is_not_applied_at_another_scan_rotation_and_says_why(tmp_path):
    profiles = tmp_path / "instruments.json"
    learned_from, _ = _pair_files(tmp_path, 0, "self_affine", (-5.0, 5.0))
    assert _run("instrument", "learn", *learned_from, profiles=profiles).returncode == 0
    paths, _ = _pair_files(tmp_path, 1, "dimples", (-5.0, 5.0), scan_rotation_deg=30.0)
    done = _run("height", *paths, "--tilt", 5, -5, "-o", tmp_path / "h.npz", "--json", profiles=profiles)
    report = json.loads(done.stdout)["report"]
    assert report["relief_sign"] == "nominal" and report["detector_source"] == "unknown"
    assert any("not these images' 30°" in warning for warning in report["warnings"])


def test_learning_needs_files_that_name_their_instrument(tmp_path):
    import tifffile

    paths = []
    for index in range(2):
        path = tmp_path / f"plain{index}.tif"
        tifffile.imwrite(path, (np.random.default_rng(index).random((128, 128)) * 255).astype(np.uint8))
        paths.append(path)
    done = _run("instrument", "learn", *paths, "--tilt", -5, 5, "--pixel-size-um", 0.1, profiles=tmp_path / "p.json")
    assert done.returncode == 2 and "names no instrument" in done.stderr, done.stderr
    assert not (tmp_path / "p.json").exists()

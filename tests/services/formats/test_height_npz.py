"""The height map file keeps its calibration: written by fracto height, read back by every command."""

import json
import math
import zipfile

import numpy as np
import pytest

from fractoscope.errors import InvalidInputError
from fractoscope.formats.calibration import Calibration
from fractoscope.formats.height_npz import read_height_npz, write_height_npz


def test_a_height_map_file_reads_back_with_its_calibration(tmp_path):
    z = np.arange(12, dtype=np.float32).reshape(3, 4)
    calibration = Calibration((-3.0, 3.0), ("metadata", "argument"), (0.5, 0.5), 0.05582, "metadata")
    record = {
        "tilt_axis_deg": 90.0,
        "max_slope": 9.55,
        "method": "window_zncc",
        "parameters": {"calibrate_tilt": False},
        "report": {"valid_fraction": 0.4, "min_disparity_px": math.nan},
        "datum": None,
    }
    write_height_npz(
        tmp_path / "h.npz",
        z_um=z,
        sigma_um=z / 10,
        confidence=z / 12,
        local_sigma_um=z / 20,
        calibration=calibration,
        record=record,
    )
    back = read_height_npz(tmp_path / "h.npz")
    np.testing.assert_array_equal(back.z_um, z)
    np.testing.assert_array_equal(back.local_sigma_um, z / 20)
    assert back.calibration == calibration and back.pixel_size_um == 0.05582 and back.max_slope == 9.55
    assert back.record["method"] == "window_zncc" and back.record["report"]["min_disparity_px"] is None  # NaN: unknown
    assert back.record["software"].startswith("Fractoscope")
    with np.load(tmp_path / "h.npz") as plain:  # what numpy alone sees
        assert float(plain["pixel_size_um"]) == 0.05582 and plain["tilt_deg"].tolist() == [-3.0, 3.0]
        assert json.loads(str(plain["record"]))["calibration"]["tilt_source"] == ["metadata", "argument"]


def test_older_files_and_other_files(tmp_path):
    np.savez(tmp_path / "old.npz", z_um=np.zeros((4, 4), np.float32), sigma_um=np.zeros((4, 4), np.float32))
    old = read_height_npz(tmp_path / "old.npz")
    assert old.calibration is None and old.pixel_size_um is None and old.max_slope is None
    np.savez(tmp_path / "other.npz", heights=np.zeros(3))
    with pytest.raises(InvalidInputError, match="no 2D z_um"):
        read_height_npz(tmp_path / "other.npz", field="other.npz")
    (tmp_path / "text.npz").write_text("not a zip")
    with pytest.raises(InvalidInputError) as error:
        read_height_npz(tmp_path / "text.npz", field="text.npz")
    assert error.value.field == "text.npz"


def _zip_of(path, **members: bytes) -> None:
    with zipfile.ZipFile(path, "w") as archive:
        for name, content in members.items():
            archive.writestr(name, content)


@pytest.mark.parametrize(
    ("name", "message"),
    [
        ("empty", "is not an npz file"),
        ("text", "is not an npz file"),
        ("truncated", "is not an npz file"),
        ("members_not_npy", "z_um is not a .npy array"),
        ("record_a_list", "has an unreadable record: a JSON list, not an object"),
        ("record_not_json", "has an unreadable record"),
        ("calibration_incomplete", "has an unreadable calibration in its record: no tilt_source"),
        ("sigma_of_another_shape", "its sigma_um array has shape (3, 3), its z_um (8, 8)"),
        ("z_um_3d", "holds no 2D z_um array"),
        ("z_um_text", "holds no 2D z_um array of real numbers"),
        ("pixel_size_zero", "its pixel_size_um array must hold one positive finite number"),
    ],
)
def test_unreadable_files_are_named_once_with_what_is_wrong(tmp_path, name, message):
    path = tmp_path / f"{name}.npz"
    z_um = np.zeros((8, 8), np.float32)
    if name == "empty":
        path.write_bytes(b"")
    elif name == "text":
        path.write_text("hello")
    elif name == "truncated":
        np.savez_compressed(tmp_path / "whole.npz", z_um=np.random.default_rng(0).normal(size=(64, 64)))
        path.write_bytes((tmp_path / "whole.npz").read_bytes()[:500])
    elif name == "members_not_npy":
        _zip_of(path, **{"z_um.npy": b"not a npy"})
    else:
        arrays = {
            "record_a_list": {"z_um": z_um, "record": np.str_("[1, 2]")},
            "record_not_json": {"z_um": z_um, "record": np.str_("{not json")},
            "calibration_incomplete": {
                "z_um": z_um,
                "record": np.str_(json.dumps({"calibration": {"tilt_deg": [1, 2]}})),
            },
            "sigma_of_another_shape": {"z_um": z_um, "sigma_um": np.zeros((3, 3), np.float32)},
            "z_um_3d": {"z_um": np.zeros((4, 4, 4))},
            "z_um_text": {"z_um": np.full((4, 4), "a")},
            "pixel_size_zero": {"z_um": z_um, "pixel_size_um": np.float64(0.0)},
        }[name]
        np.savez(path, **arrays)
    with pytest.raises(InvalidInputError) as raised:
        read_height_npz(path)
    assert raised.value.field == str(path) and message in raised.value.message
    assert str(path) not in raised.value.message  # named once: the field is the file


def test_a_pixel_size_array_without_a_record_is_the_pixel_size(tmp_path):
    np.savez(tmp_path / "numpy.npz", z_um=np.zeros((4, 4), np.float32), pixel_size_um=np.float64(0.25))
    assert read_height_npz(tmp_path / "numpy.npz").pixel_size_um == 0.25

"""The height map file keeps its calibration: written by fracto height, read back by every command."""

import json
import math

import numpy as np
import pytest

from fractoscope.errors import InvalidInputError
from fractoscope.formats.calibration import Calibration
from fractoscope.formats.height_npz import read_height_npz, write_height_npz


def test_a_height_map_file_reads_back_with_its_calibration(tmp_path):
    z = np.arange(12, dtype=np.float32).reshape(3, 4)
    calibration = Calibration((-3.0, 3.0), ("metadata", "argument"), (0.5, 0.5), 0.05582, "metadata")
    record = {"tilt_axis_deg": 90.0, "max_slope": 9.55, "method": "window_zncc", "parameters": {"calibrate_tilt": False},
              "report": {"valid_fraction": 0.4, "min_disparity_px": math.nan}, "datum": None}
    write_height_npz(tmp_path / "h.npz", z_um=z, sigma_um=z / 10, confidence=z / 12, local_sigma_um=z / 20,
                     calibration=calibration, record=record)
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

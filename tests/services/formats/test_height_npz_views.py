"""The views count of a tilt series' height map travels with it: into the .npz and back."""

import numpy as np

from fractoscope.formats.calibration import Calibration
from fractoscope.formats.height_npz import read_height_npz, write_height_npz


def test_the_views_used_read_back_as_written_and_older_files_have_none(tmp_path):
    z = np.arange(12, dtype=np.float32).reshape(3, 4)
    views = np.array([[0, 2, 3, 5]] * 3, np.uint8)
    calibration = Calibration((-5.0, 0.0, 5.0), ("argument",) * 3, (0.5, 0.5, 0.5), 0.1, "argument")
    written = {"z_um": z, "sigma_um": z, "confidence": z, "local_sigma_um": z, "calibration": calibration}
    write_height_npz(tmp_path / "series.npz", **written, record={}, views_used=views)
    write_height_npz(tmp_path / "older.npz", **written, record={})
    back = read_height_npz(tmp_path / "series.npz")
    assert back.views_used.dtype == np.uint8
    np.testing.assert_array_equal(back.views_used, views)
    assert read_height_npz(tmp_path / "older.npz").views_used is None

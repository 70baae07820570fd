"""The grid's quad triangulation and cell sums, shared by the levels of detail and the exports."""

from __future__ import annotations

import numpy as np

from fractoscope.mesh.grid import cell_sums, quad_triangles


def test_quads_turn_counter_clockwise_seen_from_above_and_skip_incomplete_ones():
    complete = np.array([[True, False, True]])
    faces = quad_triangles(complete, cols=4)
    assert faces.tolist() == [[0, 4, 1], [1, 4, 5], [2, 6, 3], [3, 6, 7]]
    # Point (r, c) at x = c, y = -r (rows run down the image): every triangle's signed area is positive.
    x, y = faces % 4, -(faces // 4)
    area = (x[:, 1] - x[:, 0]) * (y[:, 2] - y[:, 0]) - (x[:, 2] - x[:, 0]) * (y[:, 1] - y[:, 0])
    assert (area > 0).all()


def test_cell_sums_of_whole_fractional_and_partial_cells():
    values = np.arange(20, dtype=np.float64).reshape(4, 5)
    np.testing.assert_array_equal(cell_sums(values, factor=2), [[12, 20], [52, 60]])
    np.testing.assert_array_equal(cell_sums(values, factor=2, partial=True), [[12, 20, 13], [52, 60, 33]])
    assert cell_sums(np.ones((3, 3)), factor=1.5).tolist() == [[2.25, 2.25], [2.25, 2.25]]
    assert cell_sums(np.ones((3, 3), np.float32), factor=2, partial=True).dtype == np.float32

"""The views count crosses the wire: a ComputeHeightMap response's HeightMap carries it as a
uint8 raster, which the client reads back; a response without it reads as None."""

import numpy as np

from fractoscope.matching.messages import height_map_response
from fractoscope.rpc.calls import read_height_map
from fractoscope.stereo.pipeline import HeightMapResult
from fractoscope.v1 import matching_pb2


def test_views_used_reach_the_client_as_sent():
    z = np.linspace(0, 1, 12, dtype=np.float32).reshape(3, 4)
    views = np.array([[0, 3, 3, 2]] * 3, np.uint8)
    result = HeightMapResult(z, z, z, views, {"pixel_size_um": 0.1, "tilt_deg": [-5.0, 0.0, 5.0]})
    response = height_map_response(result, np.zeros((3, 4), np.uint8))
    sent = matching_pb2.ComputeHeightMapResponse.FromString(response.SerializeToString())
    back = read_height_map([sent], None)
    assert back.views_used.dtype == np.uint8
    np.testing.assert_array_equal(back.views_used, views)
    sent.height_map.ClearField("views_used")  # a server that predates the field
    assert read_height_map([sent], None).views_used is None

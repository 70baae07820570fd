"""Conversions between numpy arrays and the protobuf messages of the fractoscope.v1 API."""

from __future__ import annotations

import numpy as np

from fractoscope.errors import InvalidInputError
from fractoscope.v1 import common_pb2, matching_pb2

_DTYPES = {
    common_pb2.DATA_TYPE_FLOAT32: np.dtype("<f4"),
    common_pb2.DATA_TYPE_UINT8: np.dtype("u1"),
    common_pb2.DATA_TYPE_UINT16: np.dtype("<u2"),
}
_DATA_TYPES = {dtype: code for code, dtype in _DTYPES.items()}


def fill_raster(raster: common_pb2.Raster, values: np.ndarray) -> None:
    """Writes a (rows, cols) float32, uint8 or uint16 array into `raster`, a field of the message
    being built. Filling it in place matters: nesting a finished message copies it, which for a
    4096² height map costs about a second."""
    if values.dtype.kind == "f":
        values = values.astype("<f4")
    dtype = np.dtype(values.dtype).newbyteorder("<") if values.dtype.itemsize > 1 else values.dtype
    code = _DATA_TYPES.get(dtype)
    if code is None or values.ndim != 2:
        raise ValueError(f"cannot encode a {values.ndim}D {values.dtype} array as a raster")
    raster.rows, raster.cols = values.shape
    raster.data_type = code
    raster.data = np.ascontiguousarray(values, dtype).tobytes()


def raster_to_array(raster: common_pb2.Raster, *, field: str = "raster") -> np.ndarray:
    """Raster message to a (rows, cols) array, validating sizes."""
    dtype = _DTYPES.get(raster.data_type)
    if dtype is None:
        raise InvalidInputError(f"{field}.data_type", "must be FLOAT32, UINT8 or UINT16")
    if raster.rows <= 0 or raster.cols <= 0:
        raise InvalidInputError(field, f"rows and cols must be positive, got {raster.rows} x {raster.cols}")
    expected = raster.rows * raster.cols * dtype.itemsize
    if len(raster.data) != expected:
        raise InvalidInputError(f"{field}.data", f"holds {len(raster.data)} bytes, expected {expected}")
    return np.frombuffer(raster.data, dtype).reshape(raster.rows, raster.cols)


REPORT_FIELDS = [field.name for field in matching_pb2.MatchingReport.DESCRIPTOR.fields]
_REPEATED_REPORT_FIELDS = {field.name for field in matching_pb2.MatchingReport.DESCRIPTOR.fields if field.is_repeated}


def report_to_message(report: dict) -> matching_pb2.MatchingReport:
    """The `report` dict of a height map (keys as in MatchingReport) to its message."""
    return matching_pb2.MatchingReport(**{key: report[key] for key in REPORT_FIELDS if key in report})


def message_to_report(message: matching_pb2.MatchingReport) -> dict:
    """A MatchingReport message to a plain dict (lists for repeated fields)."""
    return {key: list(getattr(message, key)) if key in _REPEATED_REPORT_FIELDS else getattr(message, key) for key in REPORT_FIELDS}

"""JSON as RFC 8259 has it, for every document Fractoscope writes: unknown (NaN) and infinite
numbers are null, which JSON has instead of them, and numpy scalars plain numbers."""

from __future__ import annotations

import json
import math

import numpy as np


def json_ready(value):
    """`value` with NaN and infinite numbers as None and numpy scalars as Python numbers, in
    nested dicts, lists and tuples alike."""
    if isinstance(value, dict):
        return {key: json_ready(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_ready(item) for item in value]
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    return value


def dumps(value) -> str:
    """`value` as strict JSON (see `json_ready`)."""
    return json.dumps(json_ready(value), allow_nan=False)

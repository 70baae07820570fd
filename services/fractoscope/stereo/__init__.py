"""From SEM stereo pairs and tilt series to height maps (the matching service's work).

`alignment` rectifies a pair (tilt axis vertical, global shift and rotation removed); `matching`
drives dense matching (local contrast, strips, stitching) and `tgv_zncc` (the default),
`window_zncc` and `optical_flow` (FAST) are the methods that match a strip; `geometry` and
`tilt_series` turn disparities into heights and their uncertainty; `pipeline` runs the whole
chain for one request.
"""

__all__ = [
    "alignment",
    "correlation",
    "disparity",
    "geometry",
    "matching",
    "optical_flow",
    "photometric",
    "pipeline",
    "semi_global",
    "tgv_refinement",
    "tgv_zncc",
    "tilt_series",
    "visibility",
    "window_zncc",
]

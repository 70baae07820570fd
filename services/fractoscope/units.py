"""Unit conversions, in one place: micrometres throughout, SI metres only where a format demands
them (glTF positions, 3D Tiles bounding volumes and geometric errors)."""

METRES_PER_UM = 1e-6
# Heights that differ by less than this (1e-6 nm) differ by rounding, not by measurement: no
# instrument resolves it. Residual spreads below it count as zero.
HEIGHT_ROUNDING_UM = 1e-9

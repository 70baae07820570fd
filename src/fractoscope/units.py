"""Unit conversions, in one place: micrometres throughout, SI metres only where a format demands
them (glTF positions, 3D Tiles bounding volumes and geometric errors)."""

METRES_PER_UM = 1e-6

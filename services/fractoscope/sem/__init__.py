"""SEM images read from TIFF and PNG files (`image`) with their calibration from the vendors'
metadata (`metadata`): stage tilt, pixel size, data bar."""

__all__ = ["image", "metadata"]

"""SEM images and their calibration (stage tilt, pixel size, data bar) read from TIFF and PNG files."""

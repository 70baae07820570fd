"""Fractoscope: calibrated multi-scale 3D fracture surfaces from SEM stereo pairs."""

__version__ = "0.1.0"

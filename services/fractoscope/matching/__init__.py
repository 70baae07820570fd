"""The matching service: stereo pairs and tilt series of SEM images to height maps."""

__all__ = ["messages", "peers", "servicer"]

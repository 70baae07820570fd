"""The matching service: stereo pairs and tilt series of SEM images to height maps."""

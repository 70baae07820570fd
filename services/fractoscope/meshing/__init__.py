"""The meshing service: height maps to tiled GLB levels of detail."""

__all__ = ["messages", "servicer"]

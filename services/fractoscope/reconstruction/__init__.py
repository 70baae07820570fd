"""Reconstructing a specimen (`build`): every ROI measured, placed in its parent, fused, tiled and
written into a specimen store. Above the specimen's model (fractoscope.specimen) and the stores
(fractoscope.store), which know nothing of it."""

__all__ = ["build"]

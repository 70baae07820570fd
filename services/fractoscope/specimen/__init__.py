"""Multi-scale specimens: the stored specimen's model (`model`), ROIs placed in their parents
(`registration`), fused into one surface (`fusion`), cut into a quadtree of tiles (`quadtree`)
written as a 3D Tiles tileset (`tileset`), queried for profiles and roughness (`queries`) and
exported (`exports`). Stores keep specimens (fractoscope.store); fractoscope.reconstruction builds
them."""

__all__ = ["exports", "fusion", "model", "quadtree", "queries", "registration", "tileset"]

"""Multi-scale specimens (the tile service's work): ROIs placed in their parents (`registration`),
fused into one surface (`fusion`), cut into a quadtree of tiles (`quadtree`) written as a 3D Tiles
tileset (`tileset`), built (`build`), kept on disk (`store`) and queried for profiles and roughness
(`queries`)."""

__all__ = ["build", "exports", "fusion", "quadtree", "queries", "registration", "store", "tileset"]

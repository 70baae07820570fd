"""Multi-scale specimens (the tile service's work): ROIs placed in their parents (`registration`),
fused into one surface (`fusion`), cut into a quadtree of tiles (`quadtree`), built (`build`),
kept on disk (`store`) and queried for profiles and roughness (`queries`)."""

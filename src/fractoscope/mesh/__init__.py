"""Height maps as tiled triangle meshes: levels of detail (`levels`) and the meshing service's
chain from heights to GLB tiles (`pipeline`)."""

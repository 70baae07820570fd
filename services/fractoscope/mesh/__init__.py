"""Height maps as tiled triangle meshes: levels of detail (`levels`), steep walls (`walls`), the
grid triangulation (`grid`), glTF binary tiles (`glb`) and the meshing service's chain from
heights to GLB tiles (`pipeline`)."""

__all__ = ["glb", "grid", "levels", "pipeline", "walls"]

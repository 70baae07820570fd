"""File formats: glTF binary tiles (`glb`) and 3D Tiles tilesets (`tileset`) for viewers, and the standard
formats a surface leaves Fractoscope in: X3P (`x3p`), TIFF and CSV heights (`surface_export`), STL, PLY and
OBJ meshes (`mesh_export`)."""

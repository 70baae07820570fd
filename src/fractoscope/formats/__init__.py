"""File formats we write: glTF binary tiles (`glb`) and 3D Tiles tilesets (`tileset`)."""

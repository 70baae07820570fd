"""File formats a surface leaves Fractoscope in: X3P (`x3p`), TIFF and CSV heights
(`surface_export`), STL, PLY and OBJ meshes (`mesh_export`), chosen by name in `exports`; and the
height map files of the command line (`height_npz`) with the calibration they carry."""

__all__ = ["calibration", "exports", "height_npz", "mesh_export", "surface_export", "x3p"]

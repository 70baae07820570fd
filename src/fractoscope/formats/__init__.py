"""Ways a surface leaves Fractoscope: standard file formats for heights and meshes."""

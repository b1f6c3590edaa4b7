"""Texture stage: atlas, blended albedo baking, export to glTF/OBJ/PLY, MeshLab and Blender."""

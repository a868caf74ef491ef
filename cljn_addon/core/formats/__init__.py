"""Point-cloud and mesh file formats (numpy only; no torch, no bpy)."""

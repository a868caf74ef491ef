"""Point-cloud and mesh file formats (numpy only; no torch, no bpy).

points.py: .ply/.xyz/.npy point clouds and atomic writes; las.py: LAS/LAZ (laspy); meshes.py: OFF/OBJ/PLY triangle meshes.
"""

POINT_SUFFIXES = (".ply", ".xyz", ".npy", ".las", ".laz")   # the point-cloud files read and written

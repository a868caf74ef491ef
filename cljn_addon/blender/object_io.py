"""Blender objects <-> numpy arrays for the CLJN engine.

The one place that reads point clouds out of Blender objects and writes results back; used by
pipeline.py (the operators and the command line's .blend files). No UI code here, and no
import of torch.

A point cloud is a Blender PointCloud object or a mesh with vertices and no faces (any mesh
with vertices when use_mesh_vertices is set). The engine works in world space: points go out
through matrix_world and come back through its inverse; normals come back with the
inverse-transpose of that inverse (the transpose of the 3x3 part), renormalised.

Attributes written on the POINT domain (nothing is ever deleted):
- position                  the filtered positions (not by Estimate Normals)
- custom_normal             unit normals, object space: Blender 5.0 makes them the vertex
                            normals (PLY export writes nx/ny/nz; Geometry Nodes' Normal sees them)
- cljn_normal               the same normals under our own name
- cljn_displacement         distance each point moved, world units
- cljn_outlier              True for points the engine flagged as outliers
- cljn_original_position    the positions before the first change, written once
- cljn_original_normal      a pre-existing custom_normal, saved once before we overwrite it
"""
from __future__ import annotations

import bpy
import numpy as np

POSITION = "position"
CUSTOM_NORMAL = "custom_normal"
NORMAL = "cljn_normal"
DISPLACEMENT = "cljn_displacement"
OUTLIER = "cljn_outlier"
ORIGINAL_POSITION = "cljn_original_position"
ORIGINAL_NORMAL = "cljn_original_normal"

MIN_POINTS = 10   # fewer cannot form the engine's neighbourhoods

_VALUE_KEY = {"FLOAT_VECTOR": "vector", "FLOAT": "value", "BOOLEAN": "value"}
# Blender 5.0 turns a POINT-domain FLOAT_VECTOR "custom_normal" into the mesh's vertex normals.
# Older versions store custom normals differently; there only cljn_normal is written.
CUSTOM_NORMALS_SUPPORTED = bpy.app.version >= (5, 0, 0)


def _input_error(message):
    from ..core.errors import InputError

    return InputError(message)


def point_count(obj) -> int:
    if obj.type == "MESH":
        return len(obj.data.vertices)
    if obj.type == "POINTCLOUD":
        return len(obj.data.points)
    return 0


def check_point_cloud(obj, use_mesh_vertices=False) -> str | None:
    """None when obj can be processed, else the reason in plain words (names the object)."""
    if obj.type == "MESH":
        mesh = obj.data
        if len(mesh.polygons) and not use_mesh_vertices:
            return (f"'{obj.name}' is a mesh with faces, not a point cloud: tick 'Use Vertices of "
                    "Meshes' to filter its vertices anyway")
    elif obj.type != "POINTCLOUD":
        kind = obj.type.replace("_", " ").lower()
        return f"'{obj.name}' is a {kind} object, not a point cloud (a mesh without faces or a Point Cloud)"
    if obj.data.library is not None or obj.library is not None:
        return f"'{obj.name}' is linked from a library and cannot be changed"
    n = point_count(obj)
    if n < MIN_POINTS:
        return f"'{obj.name}' has too few points ({n}); at least {MIN_POINTS} are needed"
    m3 = np.array(obj.matrix_world, dtype=np.float64)[:3, :3]
    if abs(np.linalg.det(m3)) < 1e-12:
        return f"'{obj.name}' has a zero scale, so its points cannot be mapped back: fix its scale"
    return None


def is_point_cloud(obj, use_mesh_vertices=False) -> bool:
    return check_point_cloud(obj, use_mesh_vertices) is None


def point_cloud_objects(objects, use_mesh_vertices=False) -> list:
    """The objects (in order, each data-block once) that can be processed."""
    out, seen = [], set()
    for obj in objects:
        if is_point_cloud(obj, use_mesh_vertices) and obj.data.as_pointer() not in seen:
            seen.add(obj.data.as_pointer())
            out.append(obj)
    return out


def _get(data, name, data_type, n, dtype=np.float32):
    width = 3 if data_type == "FLOAT_VECTOR" else 1
    buf = np.empty(n * width, dtype=dtype)
    data.attributes[name].data.foreach_get(_VALUE_KEY[data_type], buf)
    return buf.reshape(n, 3) if width == 3 else buf


def _has(data, name, data_type) -> bool:
    attr = data.attributes.get(name)
    return attr is not None and attr.domain == "POINT" and attr.data_type == data_type


def _set(data, name, data_type, values) -> None:
    """Write a POINT attribute, creating it (or replacing our own of another type) as needed."""
    attr = data.attributes.get(name)
    if attr is not None and (attr.domain != "POINT" or attr.data_type != data_type):
        data.attributes.remove(attr)
        attr = None
    if attr is None:
        data.attributes.new(name, data_type, "POINT")
    dtype = bool if data_type == "BOOLEAN" else np.float32
    # Look the attribute up again: creating one can move the others in memory.
    data.attributes[name].data.foreach_set(_VALUE_KEY[data_type], np.ascontiguousarray(values, dtype=dtype).ravel())


def _tag_update(obj) -> None:
    data = obj.data
    if obj.type == "MESH":
        data.update()
    else:
        data.update_tag()
    obj.update_tag()


def read_local_points(obj) -> np.ndarray:
    """(N, 3) float32 positions in object space (a copy)."""
    return _get(obj.data, POSITION, "FLOAT_VECTOR", point_count(obj))


def _matrix(obj, matrix_world=None) -> np.ndarray:
    return np.array(obj.matrix_world if matrix_world is None else matrix_world, dtype=np.float64)


def read_world_points(obj, matrix_world=None) -> np.ndarray:
    """(N, 3) float64 positions in world space."""
    reason = check_point_cloud(obj, use_mesh_vertices=True)
    if reason is not None:
        raise _input_error(reason)
    m = _matrix(obj, matrix_world)
    local = read_local_points(obj).astype(np.float64)
    return local @ m[:3, :3].T + m[:3, 3]


def world_to_local_points(points, matrix_world) -> np.ndarray:
    m = np.asarray(matrix_world, dtype=np.float64)
    return np.linalg.solve(m[:3, :3], (np.asarray(points, np.float64) - m[:3, 3]).T).T


def world_to_local_normals(normals, matrix_world) -> np.ndarray:
    """Inverse-transpose of the world-to-local map (= transpose of the 3x3 part), renormalised."""
    m3 = np.asarray(matrix_world, dtype=np.float64)[:3, :3]
    local = np.asarray(normals, np.float64) @ m3
    length = np.linalg.norm(local, axis=1, keepdims=True)
    return np.divide(local, length, out=np.zeros_like(local), where=length > 0)


def save_original(obj) -> bool:
    """Store the current positions (and custom normals) once; True if stored now."""
    data = obj.data
    if _has(data, ORIGINAL_POSITION, "FLOAT_VECTOR"):
        return False
    n = point_count(obj)
    _set(data, ORIGINAL_POSITION, "FLOAT_VECTOR", read_local_points(obj))
    if _has(data, CUSTOM_NORMAL, "FLOAT_VECTOR") and not _has(data, ORIGINAL_NORMAL, "FLOAT_VECTOR"):
        _set(data, ORIGINAL_NORMAL, "FLOAT_VECTOR", _get(data, CUSTOM_NORMAL, "FLOAT_VECTOR", n))
    return True


def write_result(obj, result, normals_only=False, matrix_world=None) -> list[str]:
    """Write an engine result (world space) onto obj; returns warnings (plain sentences).

    matrix_world: the matrix the points were read with (defaults to the current one).
    """
    n = point_count(obj)
    if len(result.normals) != n:
        raise _input_error(f"'{obj.name}' now has {n} points, the result has {len(result.normals)}: "
                           "it was edited while the engine ran; nothing was written")
    m = _matrix(obj, matrix_world)
    warnings = []
    data = obj.data
    save_original(obj)
    if not normals_only:
        _set(data, POSITION, "FLOAT_VECTOR", world_to_local_points(result.points, m))
    normals = world_to_local_normals(result.normals, m)
    custom = data.attributes.get(CUSTOM_NORMAL)
    if not CUSTOM_NORMALS_SUPPORTED:
        warnings.append(f"Blender {bpy.app.version_string} keeps custom normals differently: "
                        f"normals of '{obj.name}' are in the '{NORMAL}' attribute only")
    elif custom is not None and (custom.domain != "POINT" or custom.data_type != "FLOAT_VECTOR"):
        warnings.append(f"'{obj.name}' has face-corner custom normals, which were kept: "
                        f"the new normals are in the '{NORMAL}' attribute")
    else:
        _set(data, CUSTOM_NORMAL, "FLOAT_VECTOR", normals)
    _set(data, NORMAL, "FLOAT_VECTOR", normals)
    if not normals_only:
        _set(data, DISPLACEMENT, "FLOAT", np.asarray(result.displacement, np.float64))
    elif not _has(data, DISPLACEMENT, "FLOAT"):
        _set(data, DISPLACEMENT, "FLOAT", np.zeros(n))   # Estimate Normals moves nothing
    _set(data, OUTLIER, "BOOLEAN", np.asarray(result.outliers, bool))
    _tag_update(obj)
    return warnings


def has_original(obj) -> bool:
    return obj.type in ("MESH", "POINTCLOUD") and _has(obj.data, ORIGINAL_POSITION, "FLOAT_VECTOR")


def restore_original(obj) -> bool:
    """Put back the positions (and custom normals) saved before the first change.

    Returns False, changing nothing, when obj holds no saved original. The saved attributes
    stay, so a later run still remembers the true original.
    """
    if not has_original(obj):
        return False
    data = obj.data
    n = point_count(obj)
    _set(data, POSITION, "FLOAT_VECTOR", _get(data, ORIGINAL_POSITION, "FLOAT_VECTOR", n))
    if _has(data, ORIGINAL_NORMAL, "FLOAT_VECTOR") and _has(data, CUSTOM_NORMAL, "FLOAT_VECTOR"):
        _set(data, CUSTOM_NORMAL, "FLOAT_VECTOR", _get(data, ORIGINAL_NORMAL, "FLOAT_VECTOR", n))
    _tag_update(obj)
    return True


def mesh_world_triangles(obj) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (V, 3) float64 world space, triangles (F, 3) int64) of a mesh with faces."""
    mesh = obj.data
    m = _matrix(obj)
    v = np.empty(len(mesh.vertices) * 3, np.float32)
    mesh.vertices.foreach_get("co", v)
    v = v.reshape(-1, 3).astype(np.float64) @ m[:3, :3].T + m[:3, 3]
    mesh.calc_loop_triangles()
    tris = np.empty(len(mesh.loop_triangles) * 3, np.int32)
    mesh.loop_triangles.foreach_get("vertices", tris)
    return v, tris.reshape(-1, 3).astype(np.int64)

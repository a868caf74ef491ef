"""Triangle-mesh reading for training and evaluation: OFF (and COFF), OBJ, PLY.

Polygons are fanned into triangles. Errors name the file and, where it helps, the line.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError

MESH_SUFFIXES = (".off", ".obj", ".ply")


def _fan(polygons):
    """Triangles (a, b_i, b_{i+1}) from polygons given as lists of vertex indices."""
    tris = [(p[0], p[i], p[i + 1]) for p in polygons for i in range(1, len(p) - 1)]
    return np.asarray(tris, dtype=np.int64).reshape(-1, 3)


def read_off(path):
    path = Path(path)
    with open(path, "r", errors="replace") as fh:
        lines = [(i + 1, ln.split("#", 1)[0].split()) for i, ln in enumerate(fh)]
    lines = [(no, toks) for no, toks in lines if toks]
    if not lines:
        raise InputError(f"{path}: empty file")
    no, head = lines[0]
    if not head[0].upper().endswith("OFF"):
        raise InputError(f"{path}, line {no}: expected an OFF header, found {head[0]!r}")
    rest = head[1:]
    pos = 1
    if not rest:
        no, rest = lines[1]
        pos = 2
    try:
        n_vert, n_face = int(rest[0]), int(rest[1])
    except (ValueError, IndexError):
        raise InputError(f"{path}, line {no}: expected 'vertices faces edges' counts") from None
    if len(lines) < pos + n_vert + n_face:
        raise InputError(f"{path}: truncated, header promises {n_vert} vertices and {n_face} faces")
    vert_rows = lines[pos:pos + n_vert]
    try:
        # COFF and friends put colour columns after x y z: keep the first three.
        vertices = np.array([[float(t) for t in toks[:3]] for _, toks in vert_rows], np.float64)
    except ValueError:
        bad = next(n for n, toks in vert_rows if not _floats_ok(toks[:3]))
        raise InputError(f"{path}, line {bad}: vertex coordinates are not numbers") from None
    polygons = []
    for no, toks in lines[pos + n_vert:pos + n_vert + n_face]:
        try:
            k = int(toks[0])
            polygons.append([int(t) for t in toks[1:1 + k]])
        except (ValueError, IndexError):
            raise InputError(f"{path}, line {no}: malformed face") from None
        if len(polygons[-1]) != k:
            raise InputError(f"{path}, line {no}: face lists fewer vertices than its count {k}")
    return vertices, _check_faces(path, vertices, _fan(polygons))


def _floats_ok(toks):
    try:
        [float(t) for t in toks]
        return len(toks) == 3
    except ValueError:
        return False


def read_obj(path):
    path = Path(path)
    vertices, polygons = [], []
    with open(path, "r", errors="replace") as fh:
        for no, line in enumerate(fh, 1):
            toks = line.split()
            if not toks:
                continue
            try:
                if toks[0] == "v":
                    vertices.append([float(t) for t in toks[1:4]])
                elif toks[0] == "f":
                    # v, v/vt, v//vn, v/vt/vn; negative indices count from the end.
                    idx = [int(t.split("/")[0]) for t in toks[1:]]
                    polygons.append([i - 1 if i > 0 else len(vertices) + i for i in idx])
            except ValueError:
                raise InputError(f"{path}, line {no}: cannot parse {toks[0]!r} record") from None
    vertices = np.asarray(vertices, np.float64).reshape(-1, 3)
    return vertices, _check_faces(path, vertices, _fan(polygons))


def read_ply_mesh(path):
    from .points import read_ply  # the project's one PLY reader

    cloud = read_ply(path)
    faces = cloud.faces
    if faces is None or len(faces) == 0:
        raise InputError(f"{path}: PLY has no faces (a mesh is needed here)")
    if not (isinstance(faces, np.ndarray) and faces.ndim == 2 and faces.shape[1] == 3):
        faces = _fan(faces)                      # polygons of other sizes
    points = np.asarray(cloud.points, np.float64)
    return points, _check_faces(path, points, np.asarray(faces, np.int64))


def _check_faces(path, vertices, faces):
    if len(vertices) == 0 or len(faces) == 0:
        raise InputError(f"{path}: the mesh has no {'vertices' if len(vertices) == 0 else 'faces'}")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise InputError(f"{path}: a face refers to a vertex that does not exist")
    if not np.isfinite(vertices).all():
        raise InputError(f"{path}: vertex coordinates contain NaN or inf")
    return faces


def read_mesh(path):
    """(vertices (V,3) float64, triangles (F,3) int64) from .off/.obj/.ply."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: file not found")
    suffix = path.suffix.lower()
    if suffix == ".off":
        return read_off(path)
    if suffix == ".obj":
        return read_obj(path)
    if suffix == ".ply":
        return read_ply_mesh(path)
    raise InputError(f"{path}: unsupported mesh format {suffix!r} (use {', '.join(MESH_SUFFIXES)})")


def find_meshes(folder):
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"{folder}: not a folder")
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in MESH_SUFFIXES)

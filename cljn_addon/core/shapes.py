"""Synthetic shapes (closed triangle meshes with outward winding) and surface sampling.

Used by the demo, the tests and as extra CAD-like training shapes; no data files needed.
"""
from __future__ import annotations

import numpy as np


def face_normals_and_areas(vertices, faces):
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    cross = np.cross(b - a, c - a)
    double_area = np.linalg.norm(cross, axis=1)
    normals = cross / np.maximum(double_area, 1e-300)[:, None]
    return normals, 0.5 * double_area


def sample_mesh(vertices, faces, n, rng):
    """n area-uniform surface points with their exact face normals, and the face ids."""
    vertices = np.asarray(vertices, np.float64)
    faces = np.asarray(faces, np.int64)
    normals, areas = face_normals_and_areas(vertices, faces)
    if areas.sum() <= 0:
        raise ValueError("mesh has no surface area")
    face = rng.choice(len(faces), size=n, p=areas / areas.sum())
    u, v = rng.random(n), rng.random(n)
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    a, b, c = (vertices[faces[face, i]] for i in range(3))
    points = a + u[:, None] * (b - a) + v[:, None] * (c - a)
    return points, normals[face], face


def normalise_unit_diagonal(vertices):
    """Centre on the bbox centre and scale so the bbox diagonal is 1."""
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    return (vertices - (lo + hi) / 2) / np.linalg.norm(hi - lo)


def signed_volume(vertices, faces):
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def _outward(vertices, faces):
    faces = np.asarray(faces, np.int64)
    if signed_volume(vertices, faces) < 0:
        faces = faces[:, ::-1].copy()
    return np.asarray(vertices, np.float64), faces


def _grid_faces(rows, cols, wrap_cols=True, wrap_rows=False):
    """Quads of a (rows x cols) vertex grid split into triangles."""
    faces = []
    r_max = rows if wrap_rows else rows - 1
    c_max = cols if wrap_cols else cols - 1
    r, c = np.meshgrid(np.arange(r_max), np.arange(c_max), indexing="ij")
    r, c = r.ravel(), c.ravel()
    a = r * cols + c
    b = r * cols + (c + 1) % cols
    d = ((r + 1) % rows) * cols + c
    e = ((r + 1) % rows) * cols + (c + 1) % cols
    faces.append(np.stack([a, b, e], 1))
    faces.append(np.stack([a, e, d], 1))
    return np.concatenate(faces)


def box(size=(1.0, 0.7, 0.5)):
    sx, sy, sz = np.asarray(size) / 2
    v = np.array([[x, y, z] for x in (-sx, sx) for y in (-sy, sy) for z in (-sz, sz)])
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    faces = []
    for a, b, c, d in quads:
        faces += [(a, b, c), (a, c, d)]
    return _outward(v, faces)


def prism(polygon_xy, height):
    """Extrude a simple, star-shaped-about-origin polygon: sharp edges all round."""
    poly = np.asarray(polygon_xy, np.float64)
    m = len(poly)
    bottom = np.c_[poly, np.full(m, -height / 2)]
    top = np.c_[poly, np.full(m, height / 2)]
    v = np.vstack([bottom, top, [[0, 0, -height / 2], [0, 0, height / 2]]])
    i = np.arange(m)
    j = (i + 1) % m
    sides = np.concatenate([np.stack([i, j, j + m], 1), np.stack([i, j + m, i + m], 1)])
    caps_bottom = np.stack([np.full(m, 2 * m), j, i], 1)
    caps_top = np.stack([np.full(m, 2 * m + 1), i + m, j + m], 1)
    return _outward(v, np.concatenate([sides, caps_bottom, caps_top]))


def cylinder(radius=0.4, height=1.0, segments=96):
    t = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    return prism(np.c_[radius * np.cos(t), radius * np.sin(t)], height)


def star(points=5, outer=0.5, inner=0.22, height=0.3):
    t = np.linspace(0, 2 * np.pi, 2 * points, endpoint=False)
    rad = np.where(np.arange(2 * points) % 2 == 0, outer, inner)
    return prism(np.c_[rad * np.cos(t), rad * np.sin(t)], height)


def sphere(radius=0.5, rows=48, cols=96):
    """UV sphere; poles closed by fans."""
    theta = np.linspace(0, np.pi, rows + 2)[1:-1]
    phi = np.linspace(0, 2 * np.pi, cols, endpoint=False)
    th, ph = np.meshgrid(theta, phi, indexing="ij")
    v = radius * np.c_[(np.sin(th) * np.cos(ph)).ravel(), (np.sin(th) * np.sin(ph)).ravel(), np.cos(th).ravel()]
    faces = _grid_faces(rows, cols, wrap_cols=True)
    north, south = len(v), len(v) + 1
    v = np.vstack([v, [[0, 0, radius], [0, 0, -radius]]])
    c = np.arange(cols)
    cn = (c + 1) % cols
    last = (rows - 1) * cols
    fans = np.concatenate([np.stack([np.full(cols, north), cn, c], 1),
                           np.stack([np.full(cols, south), last + c, last + cn], 1)])
    return _outward(v, np.concatenate([faces, fans]))


def torus(major=0.5, minor=0.18, rows=96, cols=48):
    u = np.linspace(0, 2 * np.pi, rows, endpoint=False)
    w = np.linspace(0, 2 * np.pi, cols, endpoint=False)
    uu, ww = np.meshgrid(u, w, indexing="ij")
    ring = major + minor * np.cos(ww)
    v = np.c_[(ring * np.cos(uu)).ravel(), (ring * np.sin(uu)).ravel(), (minor * np.sin(ww)).ravel()]
    return _outward(v, _grid_faces(rows, cols, wrap_cols=True, wrap_rows=True))


def octahedron(radius=0.5):
    v = radius * np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)
    faces = [(0, 2, 4), (2, 1, 4), (1, 3, 4), (3, 0, 4), (2, 0, 5), (1, 2, 5), (3, 1, 5), (0, 3, 5)]
    return _outward(v, faces)


def stepped_block():
    """An L-shaped block: convex and concave sharp edges (a union of two boxes)."""
    profile = np.array([[-0.5, -0.3], [0.5, -0.3], [0.5, 0.0], [0.0, 0.0], [0.0, 0.3], [-0.5, 0.3]])
    # Extrude along y: build in (x, z) then swap axes. The profile is star-shaped about
    # (-0.2, -0.1), which is where the cap fans start.
    v, f = prism(profile - [-0.2, -0.1], 0.6)
    v = v[:, [0, 2, 1]]
    return _outward(v, f[:, ::-1])


SHAPES = {
    "box": box,
    "sphere": sphere,
    "torus": torus,
    "cylinder": cylinder,
    "star": star,
    "octahedron": octahedron,
    "stepped_block": stepped_block,
}


def shape_mesh(name):
    """(vertices, faces) of a named synthetic shape, normalised to a unit bbox diagonal."""
    try:
        v, f = SHAPES[name]()
    except KeyError:
        raise ValueError(f"unknown shape {name!r}; choose one of {', '.join(SHAPES)}") from None
    return normalise_unit_diagonal(v), f


def sample_shape(name, n, noise=0.0, seed=0):
    """(noisy points, clean points, clean outward normals) of a named shape.

    noise is the Gaussian sigma as a fraction of the (unit) bbox diagonal.
    """
    rng = np.random.default_rng(seed)
    v, f = shape_mesh(name)
    clean, normals, _ = sample_mesh(v, f, n, rng)
    noisy = clean + rng.normal(scale=noise, size=clean.shape) if noise > 0 else clean.copy()
    return noisy, clean, normals

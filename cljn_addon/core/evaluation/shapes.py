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


def sample_noisy(vertices, faces, n, noise, seed):
    """(clean (n, 3), clean normals (n, 3), face ids (n,), noisy (n, 3)): `sample_mesh` and
    Gaussian noise of sigma `noise` in every coordinate, both from one generator seeded `seed`."""
    rng = np.random.default_rng(seed)
    clean, normals, face = sample_mesh(vertices, faces, n, rng)
    return clean, normals, face, clean + rng.normal(scale=noise, size=clean.shape)


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


def carved_sphere(radius=0.5, wavelength=0.05, depth=0.02, rows=240, cols=480):
    """A sphere carved with bumps half a wavelength across and `depth` high: relief at a
    dense scan's point spacing and at its noise's own scale (at 50K points the bumps are ~4
    points across and 1.2% of the diagonal from trough to crest), as on a carved capital or a
    statue: its clean surface alone reads 0.48 sigma of 0.6% noise."""
    v, f = sphere(radius, rows, cols)
    k = 2 * np.pi / wavelength
    bumps = np.sin(k * v[:, 0]) * np.sin(k * v[:, 1]) * np.sin(k * v[:, 2])
    v = v * (1 + depth / radius * bumps)[:, None]
    return _outward(v, f)


SHAPES = {
    "box": box,
    "sphere": sphere,
    "torus": torus,
    "cylinder": cylinder,
    "star": star,
    "octahedron": octahedron,
    "stepped_block": stepped_block,
    "carved_sphere": carved_sphere,
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
    clean, normals, _, noisy = sample_noisy(*shape_mesh(name), n, noise, seed)
    return noisy, clean, normals


def sample_shape_varying_noise(name, n, low, high, seed=0, profile="linear"):
    """(noisy points, clean points, per-point noise sigma) of a named shape whose noise grows
    along x from `low` to `high` (fractions of the unit bbox diagonal): linearly (profile
    'linear', as a LiDAR's grows with range) or in one step at the middle ('step', two scans
    of different noise merged)."""
    if profile not in ("linear", "step"):
        raise ValueError(f"unknown noise profile {profile!r}; choose 'linear' or 'step'")
    rng = np.random.default_rng(seed)
    v, f = shape_mesh(name)
    clean, _, _ = sample_mesh(v, f, n, rng)
    x = (clean[:, 0] - clean[:, 0].min()) / np.ptp(clean[:, 0])
    if profile == "step":
        x = (x >= 0.5).astype(np.float64)
    sigma = low + (high - low) * x
    return clean + rng.normal(size=clean.shape) * sigma[:, None], clean, sigma


# ---- Thin parts: plates, walls, tubes, brackets. A patch of 5% of the diagonal sees both
# sides of such parts; the eval scores them and the training families teach the network
# to keep the centre point's own sheet.

def triangulate_polygon(polygon_xy):
    """Ear-clipping triangulation of a simple polygon (any winding): (m-2, 3) vertex indices.

    Polygons here have tens of vertices, so a plain loop is fine.
    """
    poly = np.asarray(polygon_xy, np.float64)
    area2 = np.sum(poly[:, 0] * np.roll(poly[:, 1], -1) - np.roll(poly[:, 0], -1) * poly[:, 1])
    order = list(range(len(poly))) if area2 > 0 else list(range(len(poly)))[::-1]
    tris = []

    def cross(o, a, b):
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    guard = 0
    while len(order) > 3 and guard < 10 * len(poly) ** 2:
        guard += 1
        m = len(order)
        for i in range(m):
            a, b, c = order[i - 1], order[i], order[(i + 1) % m]
            pa, pb, pc = poly[a], poly[b], poly[c]
            if cross(pa, pb, pc) <= 1e-15:
                continue                        # reflex or degenerate: not an ear
            others = [j for j in order if j not in (a, b, c)]
            if others:
                q = poly[others]
                d1 = (pb[0] - pa[0]) * (q[:, 1] - pa[1]) - (pb[1] - pa[1]) * (q[:, 0] - pa[0])
                d2 = (pc[0] - pb[0]) * (q[:, 1] - pb[1]) - (pc[1] - pb[1]) * (q[:, 0] - pb[0])
                d3 = (pa[0] - pc[0]) * (q[:, 1] - pc[1]) - (pa[1] - pc[1]) * (q[:, 0] - pc[0])
                if np.any((d1 >= 0) & (d2 >= 0) & (d3 >= 0)):
                    continue                    # another vertex inside: not an ear
            tris.append((a, b, c))
            order.pop(i)
            break
        else:
            raise ValueError("polygon is not simple")
    tris.append(tuple(order))
    return np.asarray(tris, np.int64)


def extrude(polygon_xy, height, z0=None):
    """Closed prism of any simple polygon (L, T, U and I sections, gears), z in [z0, z0 + h]."""
    poly = np.asarray(polygon_xy, np.float64)
    m = len(poly)
    z0 = -height / 2 if z0 is None else z0
    v = np.vstack([np.c_[poly, np.full(m, z0)], np.c_[poly, np.full(m, z0 + height)]])
    i = np.arange(m)
    j = (i + 1) % m
    cap = triangulate_polygon(poly)
    faces = np.concatenate([np.stack([i, j, j + m], 1), np.stack([i, j + m, i + m], 1),
                            cap[:, ::-1], cap + m])
    return _outward(v, faces)


def _wall_faces(m):
    """Outer wall, inner wall (reversed) and top rim of two stacked loops of m vertices whose
    vertex blocks are: outer bottom, outer top, inner bottom, inner top."""
    i = np.arange(m)
    j = (i + 1) % m
    ob, ot, ib, it = i, i + m, i + 2 * m, i + 3 * m
    jb, jt, kb, kt = j, j + m, j + 2 * m, j + 3 * m
    return np.concatenate([
        np.stack([ob, jb, jt], 1), np.stack([ob, jt, ot], 1),       # outer wall
        np.stack([ib, kt, kb], 1), np.stack([ib, it, kt], 1),       # inner wall (reversed)
        np.stack([ot, jt, kt], 1), np.stack([ot, kt, it], 1),       # top rim
    ])


def extrude_ring(outer_xy, inner_xy, height, z0=None):
    """Closed thin-walled tube: outer and inner loops (same vertex count, same winding)."""
    outer, inner = np.asarray(outer_xy, np.float64), np.asarray(inner_xy, np.float64)
    m = len(outer)
    z0 = -height / 2 if z0 is None else z0
    z1 = z0 + height
    v = np.vstack([np.c_[outer, np.full(m, z0)], np.c_[outer, np.full(m, z1)],
                   np.c_[inner, np.full(m, z0)], np.c_[inner, np.full(m, z1)]])
    i = np.arange(m)
    j = (i + 1) % m
    bottom_rim = np.concatenate([np.stack([i, j + 2 * m, j], 1), np.stack([i, i + 2 * m, j + 2 * m], 1)])
    return _outward(v, np.concatenate([_wall_faces(m), bottom_rim]))


def open_cup(outer_xy, inner_xy, height, floor):
    """Closed open-topped container: walls between the loops, a floor `floor` thick."""
    outer, inner = np.asarray(outer_xy, np.float64), np.asarray(inner_xy, np.float64)
    m = len(outer)
    z0, z1, zf = -height / 2, height / 2, -height / 2 + floor
    v = np.vstack([np.c_[outer, np.full(m, z0)], np.c_[outer, np.full(m, z1)],
                   np.c_[inner, np.full(m, zf)], np.c_[inner, np.full(m, z1)]])
    cap_o = triangulate_polygon(outer)
    cap_i = triangulate_polygon(inner)
    ccw = np.sum(outer[:, 0] * np.roll(outer[:, 1], -1) - np.roll(outer[:, 0], -1) * outer[:, 1]) > 0
    if not ccw:
        cap_o, cap_i = cap_o[:, ::-1], cap_i[:, ::-1]
    faces = np.concatenate([_wall_faces(m),
                            cap_o[:, ::-1],            # bottom, facing down
                            cap_i + 2 * m])            # inner floor, facing up
    return _outward(v, faces)


def concat_meshes(*meshes):
    """Disjoint union of closed meshes (parts must not overlap)."""
    verts, faces, offset = [], [], 0
    for v, f in meshes:
        verts.append(np.asarray(v, np.float64))
        faces.append(np.asarray(f, np.int64) + offset)
        offset += len(v)
    return np.vstack(verts), np.concatenate(faces)


def regular_polygon(n, radius=0.5, phase=0.0):
    t = phase + np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.c_[radius * np.cos(t), radius * np.sin(t)]


def rectangle(w, h):
    return np.array([[-w / 2, -h / 2], [w / 2, -h / 2], [w / 2, h / 2], [-w / 2, h / 2]])


def thin_plate(thickness=0.018):
    """A 1 x 0.7 plate; the default is 1.5% of its bbox diagonal thick."""
    return box((1.0, 0.7, thickness))


def thin_open_box(wall=0.02):
    """Open-topped box with walls and floor ~1.5% of the diagonal."""
    return open_cup(rectangle(1.0, 0.7), rectangle(1.0 - 2 * wall, 0.7 - 2 * wall), 0.5, wall)


def thin_tube(wall=0.02, segments=96):
    """A thin-walled round tube, open through (no caps), walls ~1.5% of the diagonal."""
    return extrude_ring(regular_polygon(segments, 0.3), regular_polygon(segments, 0.3 - wall), 1.0)


def l_bracket(thickness=0.025):
    """An angle bracket: two legs of a thin L section, extruded."""
    t = thickness
    profile = [[0, 0], [0.6, 0], [0.6, t], [t, t], [t, 0.45], [0, 0.45]]
    return extrude(profile, 0.4)


def stool(seat=0.025, leg=0.04):
    """A thin round seat on four square legs (the legs stop just under the seat)."""
    v_seat, f_seat = prism(regular_polygon(64, 0.35), seat)
    v_seat = v_seat + [0, 0, 0.5 - seat / 2]
    parts = [(v_seat, f_seat)]
    for x, y in ((0.2, 0.2), (-0.2, 0.2), (-0.2, -0.2), (0.2, -0.2)):
        v, f = box((leg, leg, 0.5 - 0.004))
        parts.append((v + [x, y, 0.25 - 0.002 - 0.001], f))
    return concat_meshes(*parts)


def gear(teeth=16, outer=0.5, root=0.42, height=0.12, bore=None):
    """A spur gear (trapezoid teeth) with sharp tips and notches, for orientation tests."""
    t = np.linspace(0, 2 * np.pi, 4 * teeth, endpoint=False) + np.pi / (4 * teeth)
    rad = np.tile([root, outer, outer, root], teeth)
    return prism(np.c_[rad * np.cos(t), rad * np.sin(t)], height)


def star_prism(points=6, outer=0.5, inner=0.15, height=0.15):
    """A star with long sharp tips: both sides of a tip fall in one neighbourhood."""
    return star(points, outer, inner, height)


SHAPES.update({"gear": gear, "star_prism": star_prism})


def _quad(corner, u, v):
    """One rectangle (two triangles) from a corner and its two edge vectors; one-sided."""
    corner, u, v = (np.asarray(a, np.float64) for a in (corner, u, v))
    return np.array([corner, corner + u, corner + u + v, corner + v]), np.array([[0, 1, 2], [0, 2, 3]])


def street_scene(length=8.0, depth=6.0, wall_gap=0.6):
    """A mobile-LiDAR street in metres (not normalised: a scene's size is its own): open ground,
    a parked car (a 4.5 x 1.8 x 1.5 m box, no underside) with a building's wall
    `wall_gap` behind it, and a pole 0.1 m in radius. The case of issue #12's street scan, where
    a patch of 5% of the diagonal is wider than the gap between the car and the wall. Faces in
    order: the ground (0-1), the wall (2-3, at y = 1.3 + wall_gap), the car, the pole."""
    half = length / 2
    car_v, car_f = box((4.5, 1.8, 1.5))
    car_v = car_v + [0.0, 0.4, 0.75]                     # its back at y = 1.3
    underside = np.all(np.isclose(car_v[car_f][:, :, 2], 0.0), axis=1)
    wall_y = 1.3 + wall_gap
    pole_v, pole_f = cylinder(0.1, 4.0, 32)
    return concat_meshes(
        _quad([-half, wall_y - depth, 0.0], [length, 0, 0], [0, depth, 0]),      # ground
        _quad([-half, wall_y, 0.0], [length, 0, 0], [0, 0, 4.0]),                  # wall, facing the street
        (car_v, car_f[~underside]),
        (pole_v + [3.0, -2.5, 2.0], pole_f))

def city_street(length=150.0, depth=30.0, seed=5):
    """A longer street in metres: open ground `length` x `depth`, a row of buildings 6-20 m tall
    (their fronts 6 m back from the far edge), cars (boxes with no underside) along both kerbs
    and a pole every 25 m. At this extent a ball of 5% of the diagonal (7.7 m at 150 m) holds
    buildings, cars and poles at once: the case of `noise.SCENE_SPAN`."""
    rng = np.random.default_rng(seed)
    parts = [_quad([-length / 2, -depth / 2, 0.0], [length, 0, 0], [0, depth, 0])]
    x = -length / 2 + 5
    while x < length / 2 - 20:
        width, height = rng.uniform(8, 20), rng.uniform(6, 20)
        v, f = box((width, 10.0, height))
        parts.append((v + [x + width / 2, depth / 2 - 6, height / 2], f))
        x += width + rng.uniform(1, 4)
    for side in (-1, 1):
        x = -length / 2 + 3
        while x < length / 2 - 6:
            v, f = box((4.5, 1.8, 1.5))
            underside = np.all(np.isclose(v[f][:, :, 2], -0.75), axis=1)
            parts.append((v + [x, side * 6.0, 0.75], f[~underside]))
            x += rng.uniform(5.5, 12)
    for px in np.arange(-length / 2 + 10, length / 2 - 10, 25.0):
        v, f = cylinder(0.1, 6.0, 24)
        parts.append((v + [px, -8.0, 3.0], f))
    return concat_meshes(*parts)


# The eval's thin-part block (fixed instances; the training family below draws other sizes).
THIN_SHAPES = {
    "thin_plate": thin_plate,
    "thin_open_box": thin_open_box,
    "thin_tube": thin_tube,
    "l_bracket": l_bracket,
    "stool": stool,
}
SHAPES.update(THIN_SHAPES)


def _section(kind, rng):
    """A thin structural profile (L, T, U, I, Z) with flanges 0.6-4% of its size."""
    w, h = rng.uniform(0.3, 0.7), rng.uniform(0.3, 0.7)
    t = rng.uniform(0.006, 0.04)
    if kind == "L":
        return [[0, 0], [w, 0], [w, t], [t, t], [t, h], [0, h]]
    if kind == "T":
        return [[-t / 2, 0], [t / 2, 0], [t / 2, h - t], [w / 2, h - t], [w / 2, h], [-w / 2, h],
                [-w / 2, h - t], [-t / 2, h - t]]
    if kind == "U":
        return [[0, 0], [w, 0], [w, h], [w - t, h], [w - t, t], [t, t], [t, h], [0, h]]
    if kind == "I":
        return [[-w / 2, 0], [w / 2, 0], [w / 2, t], [t / 2, t], [t / 2, h - t], [w / 2, h - t],
                [w / 2, h], [-w / 2, h], [-w / 2, h - t], [-t / 2, h - t], [-t / 2, t], [-w / 2, t]]
    # Z
    return [[0, 0], [w / 2, 0], [w / 2, h - t], [w, h - t], [w, h], [w / 2 - t, h], [w / 2 - t, t], [0, t]]


def thin_training_shape(index, seed=0):
    """The index-th member of a seeded family of thin-part shapes (training only).

    Plates of random thickness, pairs of parallel plates a small gap apart, thin-walled
    tubes and open containers of random sections, extruded L/T/U/I/Z profiles and gears.
    """
    rng = np.random.default_rng([seed, index, 77])
    kind = index % 6
    if kind == 0:       # a plate, 0.5-4% thick
        return box((1.0, rng.uniform(0.3, 1.0), rng.uniform(0.005, 0.04)))
    if kind == 1:       # two parallel plates with a small gap (a wall behind a wall)
        t1, t2, gap = rng.uniform(0.01, 0.05), rng.uniform(0.01, 0.05), rng.uniform(0.01, 0.06)
        a = box((1.0, 0.6, t1))
        b = box((rng.uniform(0.5, 1.0), rng.uniform(0.4, 0.8), t2))
        b = (b[0] + [rng.uniform(-0.2, 0.2), rng.uniform(-0.1, 0.1), (t1 + t2) / 2 + gap], b[1])
        return concat_meshes(a, b)
    sides = int(rng.choice([3, 4, 5, 6, 8, 64]))
    outer = regular_polygon(sides, 0.4, rng.uniform(0, np.pi))
    outer *= [1.0, rng.uniform(0.5, 1.0)]
    wall = rng.uniform(0.006, 0.04)
    # Inset each vertex by `wall` along its bisector (a convex offset, exact for the edges).
    prev, nxt = np.roll(outer, 1, axis=0), np.roll(outer, -1, axis=0)
    e1 = (outer - prev) / np.linalg.norm(outer - prev, axis=1, keepdims=True)
    e2 = (nxt - outer) / np.linalg.norm(nxt - outer, axis=1, keepdims=True)
    n1 = np.c_[-e1[:, 1], e1[:, 0]]
    n2 = np.c_[-e2[:, 1], e2[:, 0]]
    bis = n1 + n2
    inner = outer + wall * bis / np.maximum(np.einsum("ij,ij->i", bis, n1), 1e-6)[:, None]
    if kind == 2:
        return extrude_ring(outer, inner, rng.uniform(0.3, 1.0))
    if kind == 3:
        return open_cup(outer, inner, rng.uniform(0.3, 0.8), rng.uniform(0.006, 0.04))
    if kind == 4:
        return extrude(_section("LTUIZ"[rng.integers(5)], rng), rng.uniform(0.2, 0.8))
    teeth = int(rng.integers(8, 30))
    return gear(teeth, 0.5, rng.uniform(0.38, 0.46), rng.uniform(0.02, 0.2))


def relief_training_shape(index, seed=0):
    """The index-th member of a seeded family of carved solids (training only): ellipsoids
    carved like `carved_sphere` with bumps 3-12% of the size across and 0.3-3% high, relief
    at the noise's own scale (a carved capital, a statue's hair). The eval's carved_sphere
    (wavelength 5%, depth 2%, a sphere) lies inside the family's range, but no draw is that
    instance: each is an ellipsoid with axes drawn at random."""
    rng = np.random.default_rng([seed, index, 91])
    wavelength = rng.uniform(0.03, 0.12)
    depth = rng.uniform(0.003, 0.03)
    v, f = carved_sphere(0.5, wavelength, depth)
    v = v * [1.0, rng.uniform(0.5, 1.0), rng.uniform(0.4, 1.0)]
    return _outward(v, f)


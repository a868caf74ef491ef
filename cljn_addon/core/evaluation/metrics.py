"""Evaluation metrics in METHOD.md's units (shapes normalised to a unit bbox diagonal)."""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..origin import karcher_axes
from .shapes import face_normals_and_areas, sample_mesh


def angles(pred, true):
    """Unsigned angle (radians) between normals: arccos |n . n_gt|."""
    pred = pred / np.maximum(np.linalg.norm(pred, axis=1, keepdims=True), 1e-300)
    true = true / np.maximum(np.linalg.norm(true, axis=1, keepdims=True), 1e-300)
    return np.arccos(np.clip(np.abs(np.einsum("ij,ij->i", pred, true)), 0.0, 1.0))


def msae(pred, true, mask=None):
    """Mean squared angular error (radians^2), sign ignored; optionally over a mask."""
    a = angles(pred, true)
    if mask is not None:
        a = a[mask]
    return float(np.mean(a ** 2)) if len(a) else float("nan")


def sign_agreement(pred, true):
    """Fraction of normals pointing the same way as the (oriented) truth."""
    return float(np.mean(np.einsum("ij,ij->i", pred, true) > 0))


def chamfer(a, b):
    """Mean squared nearest distance a->b plus b->a (report x 1e5)."""
    d_ab, _ = cKDTree(b).query(a, workers=-1)
    d_ba, _ = cKDTree(a).query(b, workers=-1)
    return float(np.mean(d_ab ** 2) + np.mean(d_ba ** 2))


def sharp_feature_mask(clean_points, clean_normals, k=10, low=30.0, high=150.0):
    """Clean points with a k-NN neighbour whose normal is 30-150 degrees from their own."""
    _, idx = cKDTree(clean_points).query(clean_points, k=k + 1, workers=-1)
    cos = np.einsum("ic,ikc->ik", clean_normals, clean_normals[idx[:, 1:]])
    ang = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    return ((ang > low) & (ang < high)).any(axis=1)


def closest_point_on_triangles(p, a, b, c):
    """Closest points on triangles (a, b, c) to points p, all (..., 3) (Voronoi regions)."""
    ab, ac, ap = b - a, c - a, p - a
    d1 = np.einsum("...i,...i->...", ab, ap)
    d2 = np.einsum("...i,...i->...", ac, ap)
    bp = p - b
    d3 = np.einsum("...i,...i->...", ab, bp)
    d4 = np.einsum("...i,...i->...", ac, bp)
    cp = p - c
    d5 = np.einsum("...i,...i->...", ab, cp)
    d6 = np.einsum("...i,...i->...", ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    denom = va + vb + vc
    safe = np.where(np.abs(denom) < 1e-300, 1e-300, denom)
    v = vb / safe
    w = vc / safe
    out = a + v[..., None] * ab + w[..., None] * ac            # interior
    # Edges and vertices, later assignments win in the order of the regions' priority.
    def ratio(num, den):
        return num / np.where(np.abs(den) < 1e-300, 1e-300, den)
    cond_bc = (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0)
    t = ratio(d4 - d3, (d4 - d3) + (d5 - d6))
    out = np.where(cond_bc[..., None], b + t[..., None] * (c - b), out)
    cond_ac = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
    t = ratio(d2, d2 - d6)
    out = np.where(cond_ac[..., None], a + t[..., None] * ac, out)
    cond_ab = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
    t = ratio(d1, d1 - d3)
    out = np.where(cond_ab[..., None], a + t[..., None] * ab, out)
    out = np.where(((d6 >= 0) & (d5 <= d6))[..., None], c, out)
    out = np.where(((d3 >= 0) & (d4 <= d3))[..., None], b, out)
    out = np.where(((d1 <= 0) & (d2 <= 0))[..., None], a, out)
    return out


class MeshDistance:
    """Exact point-to-mesh distance, with candidate triangles found through dense samples."""

    def __init__(self, vertices, faces, samples=400_000, candidates=24, seed=0):
        self.v = np.asarray(vertices, np.float64)
        self.f = np.asarray(faces, np.int64)
        pts, _, face_id = sample_mesh(self.v, self.f, samples, np.random.default_rng(seed))
        # Every face gets at least its centroid so tiny faces are never missed.
        cent = self.v[self.f].mean(axis=1)
        self.sample_face = np.concatenate([face_id, np.arange(len(self.f))])
        self.tree = cKDTree(np.vstack([pts, cent]))
        self.k = candidates
        self.face_normals = face_normals_and_areas(self.v, self.f)[0]

    def distance(self, points, chunk=20000):
        return self.nearest(points, chunk)[0]

    def _candidate_distances(self, p):
        """Distances (M, k) from points p to their candidate faces, and those faces' ids."""
        _, idx = self.tree.query(p, k=self.k, workers=-1)
        cand = self.sample_face[idx]                          # (M, k) face ids
        tri = self.f[cand]                                    # (M, k, 3)
        a, b, c = self.v[tri[..., 0]], self.v[tri[..., 1]], self.v[tri[..., 2]]
        q = closest_point_on_triangles(np.broadcast_to(p[:, None, :], a.shape), a, b, c)
        return np.linalg.norm(q - p[:, None, :], axis=2), cand

    def nearest(self, points, chunk=20000):
        """(distance to the mesh, normal of the nearest face) for every point. Where the
        nearest point is an edge or a vertex (a point beyond a convex edge), the faces that
        meet there are equally near and one of them is returned (`sign_at_any_nearest_face`)."""
        dist = np.empty(len(points))
        face = np.empty(len(points), np.int64)
        for s in range(0, len(points), chunk):
            d, cand = self._candidate_distances(points[s:s + chunk])
            best = d.argmin(axis=1)
            rows = np.arange(len(d))
            dist[s:s + chunk] = d[rows, best]
            face[s:s + chunk] = cand[rows, best]
        return dist, self.face_normals[face]

    def sign_at_any_nearest_face(self, points, normals, tol=1e-9, chunk=20000):
        """Per point, whether its normal faces the same way (positive dot) as at least one of
        the faces nearest it. Off an edge that is the one nearest face; beyond a convex edge
        (or vertex) every face meeting there is nearest, and the surface's normal there is any
        direction between theirs, so a normal agreeing with either is a right sign."""
        agree = np.empty(len(points), bool)
        for s in range(0, len(points), chunk):
            d, cand = self._candidate_distances(points[s:s + chunk])
            tied = d <= d.min(axis=1, keepdims=True) + tol
            dots = np.einsum("mkc,mc->mk", self.face_normals[cand], normals[s:s + chunk])
            agree[s:s + chunk] = (tied & (dots > 0)).any(axis=1)
        return agree


def point2surface(points, vertices, faces):
    """Mean distance from points to the triangle mesh (report x 1e3)."""
    return float(MeshDistance(vertices, faces).distance(points).mean())


def _origin_posterior(noisy, vertices, faces, sigma, k, chunk, seed):
    """Per chunk of noisy points: (slice, weights (M, k), oriented normals (M, k, 3)) of the
    posterior over each point's origin: the area-uniform surface weighted by N(x; y, sigma^2),
    a Monte-Carlo sample of the surface dense enough that the k nearest samples reach 3 sigma."""
    vertices, faces = np.asarray(vertices, np.float64), np.asarray(faces, np.int64)
    _, areas = face_normals_and_areas(vertices, faces)
    n_samples = int(min(4_000_000, max(50_000, k * areas.sum() / (np.pi * (3.0 * sigma) ** 2))))
    surface, surface_n, _ = sample_mesh(vertices, faces, n_samples, np.random.default_rng(seed))
    tree = cKDTree(surface)
    for s in range(0, len(noisy), chunk):
        d, idx = tree.query(noisy[s:s + chunk], k=k, workers=-1)
        w = np.exp(-0.5 * (d / sigma) ** 2)
        w /= w.sum(axis=1, keepdims=True)
        yield slice(s, s + chunk), w, surface_n[idx]


def _likeliest_side(w, nb):
    """Per point, the direction the weighted oriented normals nb (M, k, 3) agree with most, of
    three: their mean (the bisector at an edge) and both ways of their principal axis."""
    mean = np.einsum("mk,mkc->mc", w, nb)
    _, vecs = np.linalg.eigh(np.einsum("mk,mka,mkb->mab", w, nb, nb))
    axis = vecs[:, :, -1]
    candidates = np.stack([mean / np.maximum(np.linalg.norm(mean, axis=1, keepdims=True), 1e-300),
                           axis, -axis], axis=1)                                   # (M, 3, 3)
    agree = np.einsum("mk,mjk->mj", w, (np.einsum("mjc,mkc->mjk", candidates, nb) > 0).astype(np.float64))
    return candidates[np.arange(len(w)), agree.argmax(axis=1)]


def floor_and_ceiling_normals(noisy, vertices, faces, sigma, k=400, steps=8, chunk=10000, seed=0):
    """(`msae_floor_normals`, `sign_ceiling_normals`) from one pass over the origin posterior
    (the eval needs both for every cloud; the posterior is the expensive part)."""
    floor, ceiling = np.empty((len(noisy), 3)), np.empty((len(noisy), 3))
    for part, w, nb in _origin_posterior(noisy, vertices, faces, sigma, k, chunk, seed):
        floor[part] = karcher_axes(w, nb, steps)
        ceiling[part] = _likeliest_side(w, nb)
    return floor, ceiling


def msae_floor_normals(noisy, vertices, faces, sigma, k=400, steps=8, chunk=10000, seed=0):
    """The normals that minimise the expected MSAE given everything but the face of origin.

    MSAE compares each noisy point's normal with the normal of the surface point it was
    sampled from. Knowing the exact surface and the noise sigma, the posterior over that
    origin is the area-uniform surface weighted by N(x; y, sigma^2); near an edge it spans
    both faces, so no estimator can be sure of the face. This returns, per point, the
    posterior's spherical (Karcher) mean of the unsigned surface normals, which minimises
    the expected theta^2: the MSAE of these normals is a floor for any method on the cloud.
    """
    out = np.empty((len(noisy), 3))
    for part, w, nb in _origin_posterior(noisy, vertices, faces, sigma, k, chunk, seed):
        out[part] = karcher_axes(w, nb, steps)
    return out


def sign_ceiling_normals(noisy, vertices, faces, sigma, k=400, chunk=10000, seed=0):
    """Oriented normals that maximise the expected sign agreement given everything but the
    face of origin: the sign agreement of these normals is a ceiling for any method.

    Where a part is thinner than the noise, its two faces (opposite normals) both lie within
    the posterior of a point, and only the point's height between them tells which face it
    came from: on a plate t thick no method can pass Phi(t / 2 sigma) of its faces (89% at
    t = 2.5 sigma, 65% at 0.75 sigma). Per point the best of three directions is kept: the
    posterior mean of the oriented normals (at an edge, the bisector agrees with both faces)
    and both ways of the principal axis (on a plate, the likelier face). Those are the best
    directions on a plate and at an edge; where the posterior spans more faces a direction
    outside the three could do slightly better, so strictly this is a lower bound of the
    ceiling (and, like the MSAE floor, an expectation realised on this cloud)."""
    out = np.empty((len(noisy), 3))
    for part, w, nb in _origin_posterior(noisy, vertices, faces, sigma, k, chunk, seed):
        out[part] = _likeliest_side(w, nb)
    return out

"""Normals at the rims of thin parts.

A plate's rim (its edge face, as wide as the plate is thick) is a strip thinner than the noise.
The noise scatters the plate's points along the surface as well as across it, so a band about
one sigma wide lies beyond the plate's edge; the passes move points only along their normals,
so that band stays beyond the edge, where the nearest surface, and what its shading should
show, is the rim. The network gives those points the plate's normal, at right angles to the
rim's (l_bracket at 1.5%, 50K: 6% of the points more than 70 degrees off, 63% of the
output-normal MSAE; 92% of them lie within one sigma of a face carrying their normal).

A point beyond the edge of the sheet it lies on sees its neighbours on one side only. Seen in
its tangent plane, the neighbours within `REACH_SIGMAS` sigma lie mostly behind it; the
direction away from their centroid is the rim's outward normal. Where the sheet is uniformly
sampled and its edge blurred by the tangential noise (density Phi(-x / sigma) across the edge),
a point exactly on the edge has `edge_share_ahead(reach)` of its neighbours ahead of it;
points with fewer lie beyond the edge and take the rim's normal, where the normals round them
(oriented outward) show the part's two faces (`OPPOSED_SHARE`).
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree
from scipy.stats import norm

from .errors import Cancelled
from .origin import median_count_within

REACH_SIGMAS = 2.0
# The share ahead is read off a sample of the neighbours, and the direction it is read along
# comes from the same sample: with few points an interior point can read as an edge (a plate at
# 0.6%, 50K points: ~16 points within 2 sigma). The reach widens until it holds this many, and
# the share an edge point has ahead is taken at that reach (`edge_share_ahead`).
LEAST_NEIGHBOURS = 96
MOST_REACH_SIGMAS = 8.0    # sparser than this: no reading
MIN_NEIGHBOURS = 16        # a point with fewer within reach is not read (beyond an edge the count falls)
# Dense clouds are read through a random subset holding about this many points within reach:
# the share ahead is a proportion, and the reach stays the same whatever the density.
SAMPLED_NEIGHBOURS = 128
CHUNK = 4_000
# A rim joins two faces that face apart: within reach, some neighbours' outward normals face
# away from the point's (the other face, or the points of a merged wall orientation turned to
# the other side). The border of a hole in one sheet has none, and is not a rim (column_head,
# an open mesh, at 0.6%: 76% of the points read as beyond an edge lie within 3 sigma of its
# holes' borders, output MSAE 0.4249 -> 0.4297 without this, 0.4247 with it).
OPPOSED_SHARE = 0.05
# The passes seat a point beyond the edge on (or near) its own face's plane, at the corner where
# that face meets the rim; there the nearest surface is the rim or the face, so the normal leans
# from the rim's toward the face's, by atan(RIM_LEAN) (11 degrees). Output MSAE against the clean
# surface nearest each point, rim normal without lean -> with it: l_bracket 0.1403 -> 0.1388,
# thin_plate 0.0642 -> 0.0613, column_head 0.5625 -> 0.5606 (50K, 1.5%); sign on the star prism
# (30K, 2%) 98.40% -> 98.73%. (0.1 loses 1-3% of that; 0.3 gains 1-2% more on most but loses on
# l_bracket and the star prism's sign at 0.6 / 1.1%: README, "The lean toward the point's own face".)
RIM_LEAN = 0.2


def edge_share_ahead(reach_sigmas, offset_sigmas=0.0, grid=801):
    """The share of the points within `reach_sigmas` sigma of a point that lie ahead of it,
    where it stands `offset_sigmas` sigma inside the edge of a uniformly sampled half-plane
    whose edge the noise blurred (density Phi(offset - x) at x sigma ahead)."""
    g = np.linspace(-reach_sigmas, reach_sigmas, grid)
    x, y = np.meshgrid(g, g)
    density = norm.cdf(offset_sigmas - x) * (x ** 2 + y ** 2 <= reach_sigmas ** 2)
    return float(density[x > 0].sum() / density.sum())


def rim_normals(points, normals, sigma, lean=RIM_LEAN, cancel=None):
    """The points (N, 3) that lie beyond the edge of their sheet (bool mask) and, for those, the
    rim's outward normal (M, 3): in each point's tangent plane (`normals`), the direction away
    from the centroid of its neighbours within `REACH_SIGMAS` sigma (wider where the cloud holds
    fewer than `LEAST_NEIGHBOURS` there), where fewer than `edge_share_ahead` (at that reach) of
    them lie ahead of it and at least `OPPOSED_SHARE` of them face away from it (`normals` are
    oriented outward); leaning toward the point's own normal by `lean` (`RIM_LEAN`). No reading
    on a cloud too sparse for its noise."""
    points = np.asarray(points, np.float64)
    normals = np.asarray(normals, np.float64)
    rim = np.zeros(len(points), bool)
    if not (np.isfinite(sigma) and sigma > 0) or len(points) <= LEAST_NEIGHBOURS:
        return rim, np.zeros((0, 3))
    reach = REACH_SIGMAS * sigma
    tree = cKDTree(points)
    within_reach = median_count_within(tree, points, reach, 1, len(points))
    if within_reach < LEAST_NEIGHBOURS:
        # Widen by area to hold the least count.
        reach *= np.sqrt(LEAST_NEIGHBOURS / within_reach)
        if reach > MOST_REACH_SIGMAS * sigma:
            return rim, np.zeros((0, 3))
        within_reach = median_count_within(tree, points, reach, 1, len(points))
    edge_share = edge_share_ahead(reach / sigma)
    if within_reach > SAMPLED_NEIGHBOURS:
        rng = np.random.default_rng(0)
        chosen = rng.choice(len(points), size=max(len(points) * SAMPLED_NEIGHBOURS // within_reach,
                                                  LEAST_NEIGHBOURS), replace=False)
        sample, sample_normals = points[chosen], normals[chosen]
        tree = cKDTree(sample)
    else:
        sample, sample_normals = points, normals
    k = min(2 * SAMPLED_NEIGHBOURS, len(sample))
    outward = np.zeros((len(points), 3))
    for start in range(0, len(points), CHUNK):
        if cancel is not None and cancel.is_set():
            raise Cancelled("cancelled")
        rows = slice(start, min(start + CHUNK, len(points)))
        dist, near = tree.query(points[rows], k=k, distance_upper_bound=reach, workers=-1)
        # The point itself (distance 0) is neither ahead nor behind.
        within = np.isfinite(dist) & (dist > 0)
        near = np.minimum(near, len(sample) - 1)
        offsets = sample[near] - points[rows, None]
        offsets[~within] = 0.0
        n = normals[rows]
        tangential = offsets - np.einsum("mkc,mc->mk", offsets, n)[..., None] * n[:, None]
        count = within.sum(axis=1)
        centroid = tangential.sum(axis=1) / np.maximum(count, 1)[:, None]
        length = np.linalg.norm(centroid, axis=1)
        away = -centroid / np.maximum(length, 1e-300)[:, None]
        ahead = ((np.einsum("mkc,mc->mk", tangential, away) > 0) & within).sum(axis=1)
        share = ahead / np.maximum(count, 1)
        opposed = ((np.einsum("mkc,mc->mk", sample_normals[near], n) < 0) & within).sum(axis=1) / np.maximum(count, 1)
        rim[rows] = (count >= MIN_NEIGHBOURS) & (length > 0) & (share < edge_share) & (opposed >= OPPOSED_SHARE)
        outward[rows] = away
    leaned = outward[rim] + lean * normals[rim]
    return rim, leaned / np.linalg.norm(leaned, axis=1, keepdims=True)

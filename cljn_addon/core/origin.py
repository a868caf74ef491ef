"""The normal of the surface each noisy input point was sampled from (normals-only mode).

Near an edge a noisy point may have come from either face, and no method can tell which; under
squared angular error the best answer is then the posterior mean of the surface normals within
the noise of the point, weighted by N(x; y, sigma^2) over the surface (the floor of
`evaluation.metrics.msae_floor_normals`, which uses the true mesh). Here the surface is the
filtered cloud with its network normals and sigma the cloud's noise: an empirical Bayes
estimate of that floor. Away from edges it averages a few good normals; at an edge it blends
the faces as much as the noise leaves the face in doubt, where a sharp normal is fully wrong
for the points from the other face.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .errors import Cancelled

# The posterior's reach: beyond 3 sigma a surface point's weight is under 1.2% of the nearest's.
REACH_SIGMAS = 3.0
MIN_NEIGHBOURS, MAX_NEIGHBOURS = 16, 256
COUNT_SAMPLE = 2000
KARCHER_STEPS = 4
CHUNK = 20_000


def karcher_axes(weights, normals, steps=KARCHER_STEPS):
    """Per row, the weighted spherical (Karcher) mean of the unsigned unit normals (M, k, 3)
    under weights (M, k) that sum to 1: the axis that minimises the expected squared angle."""
    # Start from the principal axis of the weighted normals, then Karcher steps.
    _, vecs = np.linalg.eigh(np.einsum("mk,mka,mkb->mab", weights, normals, normals))
    axis = vecs[:, :, -1]
    for _ in range(steps):
        cos = np.einsum("mc,mkc->mk", axis, normals)
        aligned = normals * np.where(cos < 0, -1.0, 1.0)[..., None]
        cos = np.minimum(np.abs(cos), 1.0)
        theta = np.arccos(cos)
        tangent = aligned - cos[..., None] * axis[:, None, :]               # length sin(theta)
        scale = np.where(theta > 1e-7, theta / np.maximum(np.sin(theta), 1e-12), 1.0)
        step = np.einsum("mk,mkc->mc", weights * scale, tangent)          # mean of the log maps
        length = np.linalg.norm(step, axis=1, keepdims=True)
        axis = np.cos(length) * axis + np.sin(length) * step / np.maximum(length, 1e-12)
        axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    return axis


def median_count_within(tree, points, radius, least, most, seed=0) -> int:
    """The median number of `points` (in `tree`, their cKDTree) within `radius` of a sample of
    them, clipped to [least, most] and to the cloud's size: a k for k-nearest queries that
    reaches about `radius`."""
    rng = np.random.default_rng(seed)
    probe = points[rng.choice(len(points), size=min(COUNT_SAMPLE, len(points)), replace=False)]
    counts = tree.query_ball_point(probe, radius, return_length=True, workers=-1)
    return int(np.clip(np.median(counts), least, min(most, len(points))))


def posterior_neighbours(tree, surface, sigma, seed=0) -> int:
    """How many surface points (in `tree`, a cKDTree of `surface`) the posterior needs: the
    median count within its reach."""
    return median_count_within(tree, surface, REACH_SIGMAS * sigma, MIN_NEIGHBOURS, MAX_NEIGHBOURS, seed)


def origin_normals(points, surface, surface_normals, sigma, seed=0, cancel=None):
    """Unit normals (N, 3) for the noisy `points`: the posterior mean normal of `surface` (the
    filtered cloud, its points standing for area-uniform samples) with `surface_normals`,
    within noise `sigma` of each point (one number, or one per point where the noise varies
    across the cloud); each faces the way most of its weighted neighbours' normals face, so an
    oriented surface gives oriented normals."""
    points = np.asarray(points, np.float64)
    sigma = np.broadcast_to(np.asarray(sigma, np.float64), (len(points),))
    if not (np.all(np.isfinite(sigma)) and np.all(sigma > 0)) or len(surface) < 2:
        return np.array(surface_normals, np.float64)
    tree = cKDTree(surface)
    # Enough neighbours for the noisiest point's reach; the quieter ones' weights fall off sooner.
    k = posterior_neighbours(tree, surface, float(sigma.max()), seed)
    surface_normals = np.asarray(surface_normals, np.float64)
    out = np.empty((len(points), 3))
    for start in range(0, len(points), CHUNK):
        if cancel is not None and cancel.is_set():
            raise Cancelled("cancelled")
        rows = slice(start, min(start + CHUNK, len(points)))
        dist, near = tree.query(points[rows], k=k, workers=-1)
        # Relative to the nearest: the same weights once normalised, and no underflow where
        # the filtered surface lies many sigmas from the point.
        weights = np.exp(-0.5 * (dist ** 2 - dist[:, :1] ** 2) / sigma[rows, None] ** 2)
        weights /= weights.sum(axis=1, keepdims=True)
        normals = surface_normals[near]
        axes = karcher_axes(weights, normals)
        flip = np.einsum("mk,mk->m", weights, np.einsum("mc,mkc->mk", axes, normals)) < 0
        axes[flip] *= -1
        out[rows] = axes
    return out

"""Local PCA planes: the classic normals and the plane-projection filter. The eval's baselines
(`evaluation.baselines`) and the engine's risk check (`risk`) share them."""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

CHUNK = 50000


def local_planes(points, query, k, tree=None):
    """Centroid and smallest-variance direction of the k nearest neighbours of each query."""
    tree = tree or cKDTree(points)
    k = min(k, len(points))
    centroids = np.empty_like(query)
    normals = np.empty_like(query)
    for s in range(0, len(query), CHUNK):
        _, idx = tree.query(query[s:s + CHUNK], k=k, workers=-1)
        nb = points[idx.reshape(-1, k)]
        c = nb.mean(axis=1)
        x = nb - c[:, None, :]
        cov = np.einsum("mki,mkj->mij", x, x)
        _, vecs = np.linalg.eigh(cov)
        centroids[s:s + CHUNK] = c
        normals[s:s + CHUNK] = vecs[:, :, 0]
    return centroids, normals


def pca_normals(points, k=60):
    """Unoriented PCA normals from k nearest neighbours (Hoppe et al.)."""
    points = np.asarray(points, np.float64)
    return local_planes(points, points, k)[1]


def pca_projection_filter(points, k=60, iterations=2):
    """Iteratively project every point onto the PCA plane of its k nearest neighbours."""
    p = np.asarray(points, np.float64).copy()
    for _ in range(iterations):
        c, n = local_planes(p, p, k)
        p = p - np.einsum("ij,ij->i", p - c, n)[:, None] * n
    return p

"""Classic baselines users compare us with: PCA normals, PCA-plane projection filtering and
CGAL's jet smoothing (the `cgal` package, an evaluation-only dependency)."""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

CHUNK = 50000


def _local_planes(points, query, k, tree=None):
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
    return _local_planes(points, points, k)[1]


def pca_projection_filter(points, k=60, iterations=2):
    """Iteratively project every point onto the PCA plane of its k nearest neighbours."""
    p = np.asarray(points, np.float64).copy()
    for _ in range(iterations):
        c, n = _local_planes(p, p, k)
        p = p - np.einsum("ij,ij->i", p - c, n)[:, None] * n
    return p


def jet_smoothing_available() -> bool:
    try:
        from CGAL import CGAL_Point_set_processing_3  # noqa: F401
    except ImportError:
        return False
    return True


def jet_smooth(points, k=30):
    """CGAL's jet_smooth_point_set: project each point onto a degree-2 jet (local polynomial
    surface) fitted to its k nearest neighbours. Evaluation only; the points cross into CGAL
    one by one through its SWIG bindings (about 0.1 s per 50K points)."""
    from CGAL import CGAL_Point_set_processing_3 as psp
    from CGAL.CGAL_Kernel import Point_3
    from CGAL.CGAL_Point_set_3 import Point_set_3

    pts = np.asarray(points, np.float64)
    cloud = Point_set_3()
    cloud.reserve(len(pts))
    for x, y, z in pts.tolist():
        cloud.insert(Point_3(x, y, z))
    # Only k: the bindings' later positional arguments are not the fitting degrees.
    psp.jet_smooth_point_set(cloud, int(k))
    out = np.empty_like(pts)
    for i in range(len(pts)):
        q = cloud.point(i)
        out[i] = (q.x(), q.y(), q.z())
    return out

"""Classic baselines users compare us with: PCA normals, PCA-plane projection filtering and
CGAL's jet smoothing (the `cgal` package, an evaluation-only dependency)."""
from __future__ import annotations

import numpy as np

from ..planes import pca_normals, pca_projection_filter

__all__ = ["pca_normals", "pca_projection_filter", "jet_smoothing_available", "jet_smooth"]


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

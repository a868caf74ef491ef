"""Post-processing of each inference iteration (METHOD.md, Inference steps 2 and 3)."""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

CHUNK = 65536  # rows per neighbour query: bounds memory for million-point clouds


def inflation(filtered: np.ndarray, before: np.ndarray, k: int = 100) -> np.ndarray:
    """Taubin-like inflation: p_bar_i = p'_i - mean_{j in kNN(p'_i)} (p'_j - p_j).

    The k nearest filtered neighbours include the point itself, as a shrink that is uniform
    over the neighbourhood should be undone exactly.
    """
    k = min(k, len(filtered))
    tree = cKDTree(filtered)
    shift = filtered - before
    out = np.empty_like(filtered)
    for s in range(0, len(filtered), CHUNK):
        _, idx = tree.query(filtered[s:s + CHUNK], k=k, workers=-1)
        idx = idx.reshape(-1, k)
        out[s:s + CHUNK] = filtered[s:s + CHUNK] - shift[idx].mean(axis=1)
    return out


def lrma_update(points: np.ndarray, normals: np.ndarray, k: int = 20) -> np.ndarray:
    """p_i += 1/(3|N|) sum_j (n_j n_j^T + n_i n_i^T)(p_j - p_i) over the k nearest (self excluded).

    Moves each point along the normals only: towards the neighbours' tangent planes, not
    along the surface.
    """
    k = min(k, len(points) - 1)
    if k < 1:
        return points.copy()
    tree = cKDTree(points)
    out = np.empty_like(points)
    for s in range(0, len(points), CHUNK):
        p = points[s:s + CHUNK]
        _, idx = tree.query(p, k=k + 1, workers=-1)
        idx = idx[:, 1:]                                  # drop self
        diff = points[idx] - p[:, None, :]                # (M, k, 3)
        n_j = normals[idx]
        n_i = normals[s:s + CHUNK]
        along_j = np.einsum("mkc,mkc->mk", n_j, diff)[..., None] * n_j
        along_i = np.einsum("mc,mkc->mk", n_i, diff)[..., None] * n_i[:, None, :]
        out[s:s + CHUNK] = p + (along_j + along_i).sum(axis=1) / (3.0 * k)
    return out

"""Patch extraction: fixed-size balls, centred, scaled by r, rotated into their PCA frame.

Everything here works on whole arrays of centres at once (no per-point Python loops).
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

# Gather candidates from the this-many nearest neighbours (x points per patch). When a ball
# holds many more points than that, the source cloud is thinned first (see PatchSource), so
# the K nearest are almost always the whole ball and the sample stays uniform over the ball.
CANDIDATE_FACTOR = 4
TARGET_BALL_FACTOR = 2


def bbox_diagonal(points: np.ndarray) -> float:
    """Length of the axis-aligned bounding-box diagonal."""
    if len(points) == 0:
        return 0.0
    return float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))


def ball_counts(tree: cKDTree, centres: np.ndarray, radius: float, cap: int) -> np.ndarray:
    """Number of points within `radius` of each centre, counted up to `cap` (cheap kNN form)."""
    dist, _ = tree.query(centres, k=cap, distance_upper_bound=radius, workers=-1)
    dist = dist.reshape(len(centres), cap)
    return np.isfinite(dist).sum(axis=1)


class PatchSource:
    """A cloud prepared for ball queries of radius `radius` and `points_per_patch` samples.

    If balls hold far more points than a patch needs, patches are drawn from a fixed random
    subset of the cloud: a uniform sample of a uniform subset is still a uniform sample of the
    ball, and the nearest-K candidate query stays cheap for dense scans (1M points).
    """

    def __init__(self, points: np.ndarray, radius: float, points_per_patch: int,
                 rng: np.random.Generator):
        self.points = np.ascontiguousarray(points, dtype=np.float64)
        self.radius = float(radius)
        self.n = int(points_per_patch)
        self.full_tree = cKDTree(self.points)
        self.k = min(CANDIDATE_FACTOR * self.n, len(self.points))
        probe = self.points[rng.choice(len(self.points), size=min(256, len(self.points)), replace=False)]
        mean_count = float(np.mean(self.full_tree.query_ball_point(probe, self.radius, return_length=True, workers=-1)))
        keep = TARGET_BALL_FACTOR * self.n / max(mean_count, 1.0)
        if keep < 0.9:
            subset = np.sort(rng.choice(len(self.points), size=max(int(keep * len(self.points)), self.k), replace=False))
            self.subset_points = self.points[subset]
            self.tree = cKDTree(self.subset_points)
        else:
            self.subset_points = self.points
            self.tree = self.full_tree

    def gather(self, centres: np.ndarray, rng: np.random.Generator):
        """Local patches (M, n, 3) float32 in radius units (not yet rotated) and ball counts."""
        local, counts = gather_patches(self.subset_points, self.tree, centres, self.radius, self.n, self.k, rng)
        if self.tree is not self.full_tree:
            # Thinning can empty a sparse ball: redo those from the full cloud.
            sparse = counts < min(self.n, 8)
            if sparse.any():
                k_full = min(CANDIDATE_FACTOR * self.n, len(self.points))
                local[sparse], counts[sparse] = gather_patches(
                    self.points, self.full_tree, centres[sparse], self.radius, self.n, k_full, rng)
        return local, counts


def gather_patches(points, tree, centres, radius, n, k, rng):
    """Sample n points uniformly without replacement from each ball (pad by repetition).

    Returns (M, n, 3) float32 patches as (p - centre) / radius, and (M,) candidate counts.
    Balls with no point at all come back as n copies of the centre (count 0).
    """
    m = len(centres)
    if m == 0:
        return np.zeros((0, n, 3), np.float32), np.zeros(0, np.int64)
    k = max(1, min(k, len(points)))
    dist, idx = tree.query(centres, k=k, distance_upper_bound=radius, workers=-1)
    dist = dist.reshape(m, k)
    idx = idx.reshape(m, k)
    valid = np.isfinite(dist)
    counts = valid.sum(axis=1)
    # Random keys, invalid candidates pushed last: the n smallest keys form a uniform subset.
    keys = rng.random((m, k))
    keys[~valid] = 2.0
    if k > n:
        pick = np.argpartition(keys, n - 1, axis=1)[:, :n]
    else:
        pick = np.argsort(keys, axis=1)
        if k < n:
            pick = np.concatenate([pick, np.full((m, n - k), k - 1)], axis=1)
    chosen = np.take_along_axis(idx, np.minimum(pick, k - 1), axis=1)
    ok = np.take_along_axis(valid, np.minimum(pick, k - 1), axis=1) & (pick < k)
    # Pad: slots without a distinct ball point repeat a random point of the ball (valid
    # candidates are the first `count` columns, since kNN returns them sorted by distance).
    pad_col = np.floor(rng.random((m, n)) * np.maximum(counts, 1)[:, None]).astype(np.int64)
    pad_idx = np.take_along_axis(idx, pad_col, axis=1)
    chosen = np.where(ok, chosen, pad_idx)
    empty = counts == 0
    chosen[empty] = 0
    patch = (points[chosen] - centres[:, None, :]) / radius
    patch[empty] = 0.0
    return patch.astype(np.float32), counts


def pca_frames(local: np.ndarray) -> np.ndarray:
    """Rotation (M, 3, 3) per patch: rows are the PCA axes, largest variance first.

    The covariance is taken about the patch centre (the origin of `local`), so the rough
    normal (smallest variance) becomes the z axis. Sign convention, deterministic: the first
    and third axes point where the patch's third moment along them is positive (ties: +),
    and the second is e3 x e1 so every frame is a proper rotation (det = +1).
    """
    x = local.astype(np.float64)
    cov = np.matmul(x.transpose(0, 2, 1), x) / x.shape[1]     # 5x einsum's speed, the same sums
    # Tiny isotropic term keeps degenerate (all-duplicate, collinear) patches well posed.
    cov += np.eye(3) * 1e-12
    _, vecs = np.linalg.eigh(cov)            # ascending eigenvalues, columns are vectors
    e1 = vecs[:, :, 2]
    e3 = vecs[:, :, 0]
    along1 = np.einsum("mni,mi->mn", x, e1)
    along3 = np.einsum("mni,mi->mn", x, e3)
    skew1 = along1 * along1 * along1          # 45x faster than ** 3; only the sum's sign is used
    skew3 = along3 * along3 * along3
    e1 = e1 * np.where(skew1.sum(axis=1) < 0, -1.0, 1.0)[:, None]
    e3 = e3 * np.where(skew3.sum(axis=1) < 0, -1.0, 1.0)[:, None]
    e2 = np.cross(e3, e1)
    return np.stack([e1, e2, e3], axis=1)


def to_frame(local: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """Rotate (M, n, 3) patch points (or (M, 3) vectors) into the frames: x -> R x."""
    if local.ndim == 2:
        return np.einsum("mij,mj->mi", frames, local)
    return np.matmul(local, frames.transpose(0, 2, 1))     # 8x einsum's speed


def from_frame(vectors: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """Exact inverse of `to_frame` for (M, 3) vectors: R^T v."""
    return np.einsum("mji,mj->mi", frames, vectors)


def make_patches(source: PatchSource, centres: np.ndarray, rng: np.random.Generator, own_sheet=False):
    """Patches around `centres` in their PCA frames: (patches (M,n,3) float32, frames, counts).

    own_sheet (ours): where a patch holds both sides of a thin part, the other side's points
    are replaced by points of the centre's own side (`sheets.own_sheet_patches`) and the
    frame is taken again from what is left."""
    local, counts = source.gather(centres, rng)
    return (*framed_patches(local, rng, own_sheet), counts)


def framed_patches(local: np.ndarray, rng: np.random.Generator, own_sheet=False):
    """`make_patches` on gathered balls (`PatchSource.gather`): (patches, frames)."""
    frames = pca_frames(local)
    if own_sheet:
        from .sheets import own_sheet_patches

        local, fit = own_sheet_patches(local, to_frame(local, frames), rng)
        if fit["two"].any():
            frames[fit["two"]] = pca_frames(local[fit["two"]])
    return to_frame(local, frames).astype(np.float32), frames

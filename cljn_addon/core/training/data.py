"""Training data: sampled shapes, their noise variants, and batches of patches.

A training shape is a clean cloud with exact normals (area-uniform samples of a mesh,
normalised to a unit bbox diagonal) plus noisy variants at METHOD.md's levels. Batches are
drawn with whole-array operations so the network, not patch gathering, sets the pace.
"""
from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..config import ROTATION_ANGLES_DEG, TRAIN_NOISE_LEVELS
from ..evaluation.shapes import normalise_unit_diagonal, relief_training_shape, sample_mesh, shape_mesh, thin_training_shape
from ..formats.meshes import read_mesh
from ..patches import PatchSource, bbox_diagonal, pca_frames, to_frame


@dataclass
class TrainingShape:
    name: str
    clean: np.ndarray          # (N, 3) unit bbox diagonal
    normals: np.ndarray        # (N, 3) exact face normals
    variants: list             # PatchSource per noise level (level 0 is the clean cloud)


def sample_clean(vertices, faces, n_points, seed):
    rng = np.random.default_rng(seed)
    points, normals, _ = sample_mesh(normalise_unit_diagonal(vertices), faces, n_points, rng)
    return points.astype(np.float64), normals.astype(np.float64)


def _cache_key(source: str, n_points: int, seed: int) -> str:
    return hashlib.sha1(f"{source}|{n_points}|{seed}".encode()).hexdigest()[:16]


def load_clean_cloud(source, n_points, seed, cache_dir=None):
    """Clean samples of a mesh file, a named synthetic shape ("shape:box"), the i-th member
    of the thin-part family ("thin:3"), of the carved family ("relief:2") or (V, F) arrays.

    Samples of mesh files are cached as .npz under cache_dir (outside git).
    """
    if isinstance(source, tuple):
        return sample_clean(source[0], source[1], n_points, seed)
    source = str(source)
    if source.startswith("shape:"):
        v, f = shape_mesh(source[len("shape:"):])
        return sample_clean(v, f, n_points, seed)
    if source.startswith("thin:"):
        return sample_clean(*thin_training_shape(int(source[len("thin:"):])), n_points, seed)
    if source.startswith("relief:"):
        return sample_clean(*relief_training_shape(int(source[len("relief:"):])), n_points, seed)
    cache = None
    if cache_dir is not None:
        stat = Path(source).stat()
        key = _cache_key(f"{Path(source).resolve()}|{stat.st_size}|{int(stat.st_mtime)}", n_points, seed)
        cache = Path(cache_dir) / f"{Path(source).stem}-{key}.npz"
        if cache.exists():
            with np.load(cache) as data:
                return data["points"], data["normals"]
    points, normals = sample_clean(*read_mesh(source), n_points, seed)
    if cache is not None:
        cache.parent.mkdir(parents=True, exist_ok=True)
        tmp = cache.with_name(cache.stem + ".tmp.npz")
        np.savez(tmp, points=points, normals=normals)
        tmp.replace(cache)
    return points, normals


def make_training_shape(name, clean, normals, points_per_patch, patch_radius_fraction, seed,
                        noise_levels=TRAIN_NOISE_LEVELS):
    """Noise variants (sigma x the clean diagonal, which is 1) with their patch sources."""
    rng = np.random.default_rng(seed)
    variants = []
    for level in noise_levels:
        cloud = clean + rng.normal(scale=level, size=clean.shape) if level > 0 else clean
        radius = patch_radius_fraction * bbox_diagonal(cloud)
        variants.append(PatchSource(cloud, radius, points_per_patch, rng))
    return TrainingShape(name, clean, normals, variants)


def _rotation_about_axis(axis_index: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """(B, 3, 3) rotations about x, y or z (axis_index 0..2) by angle (radians)."""
    c, s = np.cos(angle), np.sin(angle)
    rot = np.zeros((len(angle), 3, 3))
    for axis in range(3):
        sel = axis_index == axis
        i, j = [a for a in range(3) if a != axis]
        rot[sel, axis, axis] = 1.0
        rot[sel, i, i] = c[sel]
        rot[sel, j, j] = c[sel]
        rot[sel, i, j] = -s[sel]
        rot[sel, j, i] = s[sel]
    return rot


def _split_by_shape(shapes, batch, rng):
    """Shape index per sample, grouped so queries run one array per (shape, variant)."""
    return np.sort(rng.integers(0, len(shapes), size=batch))


def contrastive_batch(shapes, batch_pairs, rng):
    """Positive pairs (P, Q): (B, n, 3) float32 each.

    Same shape, same centre index, two random noise variants; both in the PCA frame of P;
    Q then rotated about x, y or z by one of the paper's angles.
    """
    shape_of = _split_by_shape(shapes, batch_pairs, rng)
    n = shapes[0].variants[0].n
    p_local = np.empty((batch_pairs, n, 3), np.float32)
    q_local = np.empty((batch_pairs, n, 3), np.float32)
    for s in np.unique(shape_of):
        rows = np.flatnonzero(shape_of == s)
        shape = shapes[s]
        centre_idx = rng.integers(0, len(shape.clean), size=len(rows))
        v1 = rng.integers(0, len(shape.variants), size=len(rows))
        v2 = rng.integers(0, len(shape.variants), size=len(rows))
        centres = np.empty((len(rows), 3))
        for v in np.unique(v1):
            sel = v1 == v
            centres[sel] = shape.variants[v].points[centre_idx[sel]]
            p_local[rows[sel]], _ = shape.variants[v].gather(centres[sel], rng)
        for v in np.unique(v2):
            sel = v2 == v
            q_local[rows[sel]], _ = shape.variants[v].gather(centres[sel], rng)
    frames = pca_frames(p_local)
    p = to_frame(p_local, frames)
    q = to_frame(q_local, frames)
    angles = np.deg2rad(rng.choice(ROTATION_ANGLES_DEG, size=batch_pairs))
    rot = _rotation_about_axis(rng.integers(0, 3, size=batch_pairs), angles)
    q = np.einsum("bij,bnj->bni", rot, q)
    return p.astype(np.float32), q.astype(np.float32)


# Ground truth from "the centre's own side" only: clean points whose normal is within 120
# degrees of the normal at the centre's origin. Both faces of a 90-degree edge stay in; the
# far side of a thin wall, plate or spike tip (normals ~180 degrees apart) goes out.
OWN_SIDE_COS = -0.5


def regression_batch(shapes, batch, gt_points, rng, own_side=False):
    """Noisy patches and their clean ground truth in the same frame.

    own_side=True (ours) keeps in the ground truth only the clean surface on the centre's
    own side of a thin part (see OWN_SIDE_COS). With both sides in, the joint loss's min term
    is indifferent to which sheet a point lands on and its max term (the farthest clean point)
    is smallest between the sheets, so training teaches the network to collapse thin parts.

    Returns patches (B, n, 3), gt (B, m, 3), gt_normals (B, m, 3), target (B, 3) and
    target_normal (B, 3) (the clean point of the same index, for the fixed-target ablation).
    """
    shape_of = _split_by_shape(shapes, batch, rng)
    n = shapes[0].variants[0].n
    local = np.empty((batch, n, 3), np.float32)
    gt = np.empty((batch, gt_points, 3), np.float32)
    gt_n = np.empty((batch, gt_points, 3), np.float32)
    target = np.empty((batch, 3))
    target_n = np.empty((batch, 3))
    for s in np.unique(shape_of):
        rows = np.flatnonzero(shape_of == s)
        shape = shapes[s]
        clean_source = shape.variants[0]
        centre_idx = rng.integers(0, len(shape.clean), size=len(rows))
        var = rng.integers(0, len(shape.variants), size=len(rows))
        for v in np.unique(var):
            sel = var == v
            source = shape.variants[v]
            centres = source.points[centre_idx[sel]]
            local[rows[sel]], _ = source.gather(centres, rng)
            # Clean points of the same ball, sampled like a patch but with its own size;
            # normalised by the noisy patch's radius. Normals come along through the index.
            g_loc, g_idx = _gather_with_index(clean_source, centres, source.radius, gt_points, rng)
            if own_side:
                g_loc, g_idx = _keep_own_side(g_loc, g_idx, shape.normals, shape.normals[centre_idx[sel]], rng)
            gt[rows[sel]] = g_loc
            gt_n[rows[sel]] = shape.normals[g_idx]
            target[rows[sel]] = (shape.clean[centre_idx[sel]] - centres) / source.radius
            target_n[rows[sel]] = shape.normals[centre_idx[sel]]
    frames = pca_frames(local)
    return (to_frame(local, frames).astype(np.float32), to_frame(gt, frames).astype(np.float32),
            to_frame(gt_n, frames).astype(np.float32), to_frame(target, frames).astype(np.float32),
            to_frame(target_n, frames).astype(np.float32))


def _keep_own_side(local, idx, normals, own_normal, rng):
    """Replace ground-truth points from the far side by random own-side points of the same
    ball (repetition changes neither the loss's min nor its max). Balls with no own-side
    point at all are left as they are."""
    same = np.einsum("bmc,bc->bm", normals[idx], own_normal) > OWN_SIDE_COS
    count = same.sum(axis=1)
    order = np.argsort(np.where(same, rng.random(same.shape), 2.0), axis=1)   # own side first
    pick = np.floor(rng.random(same.shape) * np.maximum(count, 1)[:, None]).astype(np.int64)
    donor = np.take_along_axis(order, pick, axis=1)
    replace = ~same & (count[:, None] > 0)
    cols = np.where(replace, donor, np.arange(same.shape[1])[None, :])
    return np.take_along_axis(local, cols[..., None], axis=1), np.take_along_axis(idx, cols, axis=1)


def _gather_with_index(clean_source: PatchSource, centres, radius, m, rng):
    """m clean points from each ball (uniform, padded by repetition) and their indices.

    Drawn from the ball's 4m nearest clean points: where the ball holds more (both faces of a
    thin part in a dense cloud) that is a smaller disc about the centre, not the whole ball
    (`device_batches` draws from the whole ball).

    A ball with no clean point (the noisy centre drifted further than r) falls back to the
    m nearest clean points, so the loss still has a surface to aim at.
    """
    tree, pts = clean_source.full_tree, clean_source.points
    k = min(4 * m, len(pts))
    dist, idx = tree.query(centres, k=k, workers=-1)
    dist = dist.reshape(len(centres), k)
    idx = idx.reshape(len(centres), k)
    inside = dist < radius
    counts = inside.sum(axis=1)
    keys = rng.random(dist.shape)
    keys[~inside] = 2.0 + dist[~inside]           # outside the ball: nearest first, as fallback
    pick = np.argsort(keys, axis=1)[:, :m]
    use = np.take_along_axis(inside, pick, axis=1)
    chosen = np.take_along_axis(idx, pick, axis=1)
    pad_col = np.floor(rng.random((len(centres), m)) * np.maximum(counts, 1)[:, None]).astype(np.int64)
    pad = np.take_along_axis(idx, pad_col, axis=1)   # columns < count are inside the ball
    fill = (~use) & (counts[:, None] > 0)
    chosen = np.where(fill, pad, chosen)
    local = (pts[chosen] - centres[:, None, :]) / radius
    return local.astype(np.float32), chosen

"""Patch extraction and the PCA frame."""
import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from cljn_addon.core.patches import (
    PatchSource,
    bbox_diagonal,
    from_frame,
    gather_patches,
    make_patches,
    pca_frames,
    to_frame,
)


def test_frames_are_proper_rotations_and_round_trip_exactly():
    rng = np.random.default_rng(0)
    local = rng.normal(size=(50, 64, 3)) * [1.0, 0.5, 0.1]
    frames = pca_frames(local)
    assert np.allclose(np.einsum("mij,mkj->mik", frames, frames), np.eye(3), atol=1e-12)
    assert np.allclose(np.linalg.det(frames), 1.0)
    v = rng.normal(size=(50, 3))
    assert np.allclose(from_frame(to_frame(v, frames), frames), v, atol=1e-12)


def test_plane_normal_lands_on_z_and_largest_spread_on_x():
    rng = np.random.default_rng(1)
    plane = np.c_[rng.uniform(-1, 1, 500) * 1.0, rng.uniform(-1, 1, 500) * 0.5, np.zeros(500)]
    rot = Rotation.random(random_state=3).as_matrix()
    patch = (plane @ rot.T)[None]
    frame = pca_frames(patch)[0]
    assert abs(abs(frame[2] @ rot[:, 2]) - 1) < 1e-9          # z axis = plane normal
    assert abs(abs(frame[0] @ rot[:, 0]) - 1) < 1e-6          # x axis = longest extent
    in_frame = to_frame(patch, frame[None])[0]
    assert np.abs(in_frame[:, 2]).max() < 1e-9


def test_frame_sign_convention_is_rotation_equivariant():
    rng = np.random.default_rng(2)
    # A curved, asymmetric patch so every axis has a well-defined third moment.
    xy = rng.uniform(-1, 1, size=(300, 2)) * [1.0, 0.6]
    patch = np.c_[xy, 0.3 * xy[:, 0] ** 2 + 0.1 * xy[:, 1] ** 3]
    patch += [0.05, 0.02, 0.0]
    rot = Rotation.random(random_state=5).as_matrix()
    a = to_frame(patch[None], pca_frames(patch[None]))[0]
    b_src = (patch @ rot.T)[None]
    b = to_frame(b_src, pca_frames(b_src))[0]
    assert np.allclose(a, b, atol=1e-9)


def test_gather_samples_without_replacement_and_pads_small_balls():
    rng = np.random.default_rng(3)
    pts = rng.uniform(-1, 1, size=(4000, 3))
    tree = cKDTree(pts)
    centres = pts[:20]
    radius = 0.3
    patches, counts = gather_patches(pts, tree, centres, radius, 32, 512, rng)
    truth = tree.query_ball_point(centres, radius, return_length=True)
    assert np.array_equal(counts, np.minimum(truth, 512))
    assert np.all(np.linalg.norm(patches, axis=2) <= 1.0 + 1e-6)
    full = counts >= 32
    assert full.sum() >= 10
    for p in patches[full]:                                 # more in the ball than needed
        assert len(np.unique(p.round(7), axis=0)) == 32
    for p, c in zip(patches[~full], counts[~full]):        # fewer: every ball point, repeated
        assert len(np.unique(p.round(7), axis=0)) == c
    # Sparse ball: 5 points, patch of 32 holds all 5 (padded by repetition).
    few = np.r_[np.zeros((1, 3)), rng.normal(scale=0.01, size=(4, 3)), [[5.0, 5, 5]]]
    patch, count = gather_patches(few, cKDTree(few), few[:1], 0.5, 32, 128, rng)
    assert count[0] == 5
    distinct = np.unique(patch[0].round(5), axis=0)
    expected = np.unique((few[:5] / 0.5).astype(np.float32).round(5), axis=0)
    assert np.allclose(distinct, expected, atol=1e-5)


def test_patch_source_thins_dense_clouds_but_keeps_sparse_balls():
    rng = np.random.default_rng(4)
    dense = rng.uniform(0, 1, size=(200_000, 3)) * [1, 1, 0.001]
    src = PatchSource(dense, 0.05 * bbox_diagonal(dense), 64, rng)
    assert len(src.subset_points) < len(dense)
    patches, frames, counts = make_patches(src, dense[:100], rng)
    assert patches.shape == (100, 64, 3) and patches.dtype == np.float32
    assert np.median(counts) >= 64                          # thinned to ~2x the patch size
    assert np.abs(patches[:, :, 2]).max() < 0.05            # thin slab: normal on z

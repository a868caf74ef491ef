"""Metrics against hand-computed values."""
import numpy as np
from scipy.spatial import cKDTree

from cljn_addon.core.evaluation import metrics
from cljn_addon.core.evaluation.baselines import pca_normals, pca_projection_filter
from cljn_addon.core.evaluation.shapes import sample_shape, shape_mesh


def test_msae_ignores_sign_and_squares_radians():
    true = np.array([[0, 0, 1.0], [0, 0, 1.0]])
    pred = np.array([[0, 0, -1.0], [np.sin(0.3), 0, np.cos(0.3)]])
    assert abs(metrics.msae(pred, true) - 0.3 ** 2 / 2) < 1e-12


def test_chamfer_of_shifted_grid():
    a = np.array([[0.0, 0, 0], [1, 0, 0]])
    assert abs(metrics.chamfer(a, a + [0, 0.1, 0]) - 2 * 0.01) < 1e-12


def test_point2surface_matches_analytic_box_distance():
    v, f = shape_mesh("box")
    half = v.max(axis=0)
    rng = np.random.default_rng(1)
    p = rng.uniform(-0.8, 0.8, size=(3000, 3))
    q = np.abs(p) - half
    truth = np.where((q < 0).all(axis=1), -q.max(axis=1), np.linalg.norm(np.maximum(q, 0), axis=1))
    assert np.allclose(metrics.MeshDistance(v, f).distance(p), truth, atol=1e-12)


def test_sharp_feature_mask_finds_box_edges_only():
    _, clean, normals = sample_shape("box", 30000, seed=2)
    mask = metrics.sharp_feature_mask(clean, normals)
    v, _ = shape_mesh("box")
    half = v.max(axis=0)
    gap = np.sort(half - np.abs(clean), axis=1)[:, 1]   # distance to the nearest edge
    assert mask.mean() < 0.1
    assert np.all(gap[mask] < 0.03)
    assert mask[gap < 0.002].mean() > 0.95


def test_classic_baselines_beat_the_noisy_input():
    noisy, clean, normals = sample_shape("sphere", 20000, noise=0.01, seed=3)
    assert metrics.chamfer(pca_projection_filter(noisy, 60), clean) < 0.5 * metrics.chamfer(noisy, clean)
    assert metrics.msae(pca_normals(noisy, 60), normals) < 0.1


def test_outward_truth_only_for_closed_consistent_meshes():
    from cljn_addon.core.evaluation.evaluate import is_closed_and_consistent
    _, faces = shape_mesh("box")
    assert is_closed_and_consistent(faces)
    flipped = faces.copy()
    flipped[0] = flipped[0, ::-1]
    assert not is_closed_and_consistent(flipped)
    assert not is_closed_and_consistent(faces[1:])          # a hole


def test_msae_floor_normals_blend_at_an_edge_and_beat_committing_to_a_face():
    v, f = shape_mesh("box")
    sigma = 0.02
    noisy, clean, truth = sample_shape("box", 6000, noise=sigma, seed=3)
    floor = metrics.msae_floor_normals(noisy, v, f, sigma)
    # A point on an edge, far from the corners: the best guess is halfway between the faces.
    half = v.max(axis=0)
    on_edge = np.array([[half[0], half[1], 0.0]])
    n = metrics.msae_floor_normals(on_edge, v, f, sigma)[0]
    assert abs(abs(n[0]) - abs(n[1])) < 0.05 and abs(n[2]) < 0.05
    # Face centres: the face normal itself.
    centre = metrics.msae_floor_normals(np.array([[0.0, 0.0, half[2]]]), v, f, sigma)[0]
    assert abs(abs(centre[2]) - 1.0) < 1e-6
    # The floor beats the normal of the nearest surface point (committing to the likelier
    # face) and the best PCA normals on the same cloud.
    nearest_face = truth[cKDTree(clean).query(noisy)[1]]
    floor_msae = metrics.msae(floor, truth)
    assert floor_msae < metrics.msae(nearest_face, truth)
    assert floor_msae < min(metrics.msae(pca_normals(noisy, k), truth) for k in (20, 40, 80))

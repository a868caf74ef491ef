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



def test_beyond_a_box_edge_either_face_s_normal_is_a_right_sign():
    v, f = shape_mesh("box")
    half = v.max(axis=0)
    surface = metrics.MeshDistance(v, f)
    x, y = np.eye(3)[0], np.eye(3)[1]
    # Beyond the edge where the +x and +y faces meet, and off it above the +x face's middle.
    beyond = np.array([half * [1, 1, 0] + [0.1, 0.1, 0.0]] * 4)
    above = np.array([[half[0] + 0.1, 0.0, 0.0]] * 4)
    normals = np.array([x, y, -x, (x + y) / np.sqrt(2)])
    _, facing = surface.nearest(beyond)
    # nearest() returns one of the two faces meeting there, the same for every copy of the point.
    assert np.allclose(facing, x) or np.allclose(facing, y)
    assert metrics.sign_agreement(normals, facing) == 0.5            # tie broken: x or y counts wrong
    assert surface.sign_at_any_nearest_face(beyond, normals).tolist() == [True, True, False, True]
    # Off the edge the nearest face alone decides: y lies in the +x face's plane.
    assert surface.sign_at_any_nearest_face(above, normals).tolist() == [True, False, False, True]

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


def test_sign_ceiling_is_phi_of_half_the_thickness_on_a_plate_and_full_on_a_solid():
    """On a plate t thick only a point's height between the faces tells its face: no method
    can orient more than Phi(t / 2 sigma) of the plate's points (89.4% at t = 2.5 sigma)."""
    from math import erf, sqrt

    from cljn_addon.core.evaluation.shapes import box, sample_mesh

    sigma, t = 0.004, 0.01
    v, f = box((1.0, 1.0, t))
    rng = np.random.default_rng(1)
    clean, truth, _ = sample_mesh(v, f, 20000, rng)
    noisy = clean + rng.normal(scale=sigma, size=clean.shape)
    ceiling = metrics.sign_ceiling_normals(noisy, v, f, sigma)
    on_faces = np.abs(truth[:, 2]) > 0.99
    phi = 0.5 * (1 + erf(t / (2 * sigma) / sqrt(2)))
    assert abs(metrics.sign_agreement(ceiling[on_faces], truth[on_faces]) - phi) < 0.015
    # The truth itself agrees fully: the ceiling is about what a cloud tells, not the truth.
    assert metrics.sign_agreement(truth, truth) == 1.0
    # A solid box, the same noise: every face can be told.
    v, f = box((1.0, 1.0, 0.5))
    clean, truth, _ = sample_mesh(v, f, 20000, rng)
    noisy = clean + rng.normal(scale=sigma, size=clean.shape)
    assert metrics.sign_agreement(metrics.sign_ceiling_normals(noisy, v, f, sigma), truth) > 0.995

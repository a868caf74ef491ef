"""Normals of the surface each noisy point came from (`core.origin`): the posterior mean."""
import numpy as np

from cljn_addon.core.evaluation.metrics import msae, msae_floor_normals
from cljn_addon.core.origin import karcher_axes, origin_normals

SIGMA = 0.01


def _roof(n, rng):
    """Two unit squares meeting at a 90-degree ridge along y (a mesh, samples and normals)."""
    v = np.array([[-0.7, 0, 0], [0, 0, 0.7], [-0.7, 1, 0], [0, 1, 0.7], [0.7, 0, 0], [0.7, 1, 0]], float)
    f = np.array([[0, 1, 2], [2, 1, 3], [1, 4, 3], [3, 4, 5]])
    u, w = rng.random(n), rng.random(n)
    left = rng.random(n) < 0.5
    x = np.where(left, -0.7 + 0.7 * u, 0.7 * u)
    pts = np.stack([x, w, 0.7 - np.abs(x)], axis=1)
    normals = np.where(left[:, None], [-1.0, 0, 1.0], [1.0, 0, 1.0]) / np.sqrt(2)
    return v, f, pts, normals


def test_the_posterior_beats_the_nearest_face_near_an_edge_and_nears_the_floor():
    rng = np.random.default_rng(0)
    v, f, dense, dense_n = _roof(400_000, rng)
    _, _, clean, truth = _roof(20_000, rng)
    near = np.abs(clean[:, 0]) < 3 * SIGMA                 # within 3 sigma of the ridge
    noisy = clean + rng.normal(scale=SIGMA, size=clean.shape)
    ours = origin_normals(noisy, dense, dense_n, SIGMA)
    # The sharp answer: the normal of the surface point nearest the noisy point.
    sharp = np.where((noisy[:, 0] < 0)[:, None], [-1.0, 0, 1.0], [1.0, 0, 1.0]) / np.sqrt(2)
    floor = msae_floor_normals(noisy, v, f, SIGMA)
    assert msae(ours, truth, near) < 0.8 * msae(sharp, truth, near)
    assert msae(ours, truth, near) < 1.1 * msae(floor, truth, near)
    assert msae(ours, truth, ~near) < 1e-3                  # flat away from the ridge


def test_an_oriented_surface_gives_oriented_normals_and_far_points_stay_finite():
    rng = np.random.default_rng(1)
    surface = np.c_[rng.random((30_000, 2)), np.zeros(30_000)]
    surface_n = np.tile([0.0, 0.0, -1.0], (30_000, 1))
    surface_n[::5] *= -1                                   # a fifth flipped: the majority decides
    points = surface[:3000] + [0, 0, 0.005]
    points[:5, 2] = 1e6                                    # far off: weights must not underflow to 0/0
    out = origin_normals(points, surface, surface_n, 0.01)
    assert np.isfinite(out).all()
    assert np.allclose(out[5:], [0.0, 0.0, -1.0], atol=1e-6)


def test_each_point_reads_its_own_noise_where_the_noise_varies():
    """Noise 0.3% on one half of the ridge and 1.5% on the other: each point's posterior at its
    own sigma beats one sigma for all, quiet or noisy, and the noisiest points get the answer
    their sigma for all would give them (the quiet ones look among more neighbours)."""
    rng = np.random.default_rng(2)
    _, _, dense, dense_n = _roof(400_000, rng)
    _, _, clean, truth = _roof(20_000, rng)
    sigma = np.where(clean[:, 1] < 0.5, 0.003, 0.015)
    noisy = clean + rng.normal(size=clean.shape) * sigma[:, None]
    near = np.abs(clean[:, 0]) < 3 * sigma
    own = origin_normals(noisy, dense, dense_n, sigma)
    quiet_for_all = origin_normals(noisy, dense, dense_n, 0.003)
    noisy_for_all = origin_normals(noisy, dense, dense_n, 0.015)
    quiet, loud = near & (sigma == 0.003), near & (sigma == 0.015)
    assert msae(own, truth, quiet) < 0.9 * msae(noisy_for_all, truth, quiet)
    assert msae(own, truth, loud) < 0.9 * msae(quiet_for_all, truth, loud)
    assert np.allclose(own[sigma == 0.015], noisy_for_all[sigma == 0.015], atol=1e-9)


def test_karcher_axes_ignore_signs_and_weigh_the_normals():
    a, b = np.array([0.0, 0, 1]), np.array([1.0, 0, 0])
    normals = np.array([[a, -a, b]])
    axis = karcher_axes(np.array([[0.4, 0.4, 0.2]]), normals)[0]
    angle = np.degrees(np.arccos(abs(axis @ a)))
    assert abs(angle - 18.0) < 0.5          # the weighted mean angle: 0.2 x 90 degrees from a


def test_full_patch_radius_is_the_ball_one_patch_fills_between_its_floors_and_the_ceiling():
    from cljn_addon.core.infer import MIN_PATCH_RADIUS_SHARE, full_patch_radius

    rng = np.random.default_rng(0)
    plane = np.c_[rng.uniform(0, 1, (40000, 2)), np.zeros(40000)]      # 40,000 points per unit area
    expected = np.sqrt(128 / (np.pi * 40000))                           # a disc holding 128 of them
    radius = full_patch_radius(plane, 128, sigma=1e-4, ceiling=0.04)
    assert abs(radius - expected) < 0.1 * expected
    assert full_patch_radius(plane, 128, sigma=0.0175, ceiling=0.04) == 0.035      # 2 sigmas
    assert full_patch_radius(plane, 128, sigma=1e-4, ceiling=0.2) == MIN_PATCH_RADIUS_SHARE * 0.2
    assert full_patch_radius(plane, 128, sigma=1e-4, ceiling=0.01) == 0.01
    assert full_patch_radius(plane, 128, sigma=float("nan"), ceiling=0.04) == radius
    assert full_patch_radius(plane[:100], 128, sigma=1e-4, ceiling=0.04) == 0.04

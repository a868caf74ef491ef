"""Inflation and the LRMA position update."""
import numpy as np

from cljn_addon.core.evaluation.shapes import sample_shape
from cljn_addon.core.refine import height_average, inflation, lrma_update


def test_lrma_on_noisy_plane_shrinks_off_plane_error_and_keeps_in_plane_spread():
    rng = np.random.default_rng(0)
    xy = rng.uniform(-1, 1, size=(5000, 2))
    noisy = np.c_[xy, rng.normal(scale=0.02, size=5000)]
    normals = np.tile([0.0, 0.0, 1.0], (5000, 1))
    out = noisy
    for _ in range(3):
        out = lrma_update(out, normals, 20)
    assert np.abs(out[:, 2]).mean() < 0.5 * np.abs(noisy[:, 2]).mean()
    assert np.array_equal(out[:, :2], noisy[:, :2])          # moves only along the normals


def test_lrma_moves_only_along_the_normals_of_point_and_neighbours():
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(300, 3))
    normals = np.tile([1.0, 0.0, 0.0], (300, 1))
    out = lrma_update(pts, normals, 10)
    assert np.array_equal(out[:, 1:], pts[:, 1:])


def test_inflation_undoes_a_uniform_shrink():
    _, clean, normals = sample_shape("sphere", 20000, seed=2)
    shrunk = clean - 0.01 * normals                            # every point 1% inward
    restored = inflation(shrunk, clean, 100)
    before = np.abs(np.linalg.norm(shrunk, axis=1) - np.linalg.norm(clean, axis=1)).mean()
    after = np.abs(np.linalg.norm(restored, axis=1) - np.linalg.norm(clean, axis=1)).mean()
    assert after < 0.05 * before
    shift = clean + [0.02, 0.0, 0.0]                           # a rigid shift is undone exactly
    assert np.allclose(inflation(shift, clean, 100), clean, atol=1e-12)


def test_the_sheet_reach_may_differ_per_point():
    """Refinement's max_offset per point (noise that varies across a cloud): a constant array
    gives the scalar's result, and a point given no reach keeps only itself."""
    noisy, _, normals = sample_shape("sphere", 3000, noise=0.01, seed=4)
    shifted = noisy + 0.002 * normals
    for step in (lambda m: inflation(shifted, noisy, 30, normals, max_offset=m),
                 lambda m: lrma_update(noisy, normals, 20, max_offset=m)):
        assert np.array_equal(step(0.03), step(np.full(len(noisy), 0.03)))
        reach = np.full(len(noisy), 0.03)
        reach[0] = 0.0
        assert not np.allclose(step(reach)[0], step(0.03)[0])


def test_height_average_takes_the_noise_off_a_plane_along_the_normals_only():
    rng = np.random.default_rng(3)
    xy = rng.uniform(-1, 1, size=(20000, 2))
    noisy = np.c_[xy, rng.normal(scale=0.01, size=20000)]
    normals = np.tile([0.0, 0.0, 1.0], (20000, 1))
    out = height_average(noisy, normals, 0.05, 128)
    assert np.abs(out[:, 2]).std() < 0.2 * noisy[:, 2].std()
    assert np.array_equal(out[:, :2], noisy[:, :2])
    # The sign of a neighbour's normal does not matter (the passes' normals are unoriented).
    flipped = normals * np.where(rng.random(20000) < 0.5, -1.0, 1.0)[:, None]
    assert np.allclose(height_average(noisy, flipped, 0.05, 128), out)


def test_height_average_keeps_an_edge_and_each_points_own_reach():
    """A clean right-angle edge: the other face's points (normals at right angles) stay out of
    the mean, so no point moves; without that they would be pulled off their face."""
    rng = np.random.default_rng(4)
    u = rng.uniform(0, 1, size=(2, 6000, 2))
    top = np.c_[u[0, :, 0], u[0, :, 1], np.zeros(6000)]            # z = 0, normal +z
    side = np.c_[u[1, :, 0], np.zeros(6000), -u[1, :, 1]]          # y = 0, normal -y
    points = np.r_[top, side]
    normals = np.r_[np.tile([0.0, 0.0, 1.0], (6000, 1)), np.tile([0.0, -1.0, 0.0], (6000, 1))]
    out = height_average(points, normals, 0.05, 64)
    assert np.abs(out - points).max() < 1e-12
    blended = normals.copy()
    blended[:] = [0.0, -np.sqrt(0.5), np.sqrt(0.5)]                 # one normal everywhere
    assert np.abs(height_average(points, blended, 0.05, 64) - points).max() > 0.005
    # A point whose reach is zero keeps its place; the others still move.
    noisy = points + 0.005 * rng.normal(size=points.shape) * np.r_[top * 0 + [0, 0, 1], side * 0 + [0, 1, 0]]
    reach = np.full(len(points), 0.05)
    reach[:100] = 0.0
    moved = height_average(noisy, normals, reach, 64)
    assert np.array_equal(moved[:100], noisy[:100])
    assert np.abs(moved[100:6000, 2]).mean() < 0.5 * np.abs(noisy[100:6000, 2]).mean()

"""Inflation and the LRMA position update."""
import numpy as np

from cljn_addon.core.evaluation.shapes import sample_shape
from cljn_addon.core.refine import inflation, lrma_update


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

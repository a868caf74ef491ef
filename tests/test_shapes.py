"""Synthetic shapes: the thin-part eval block and the thin-part training family are closed,
consistently wound meshes of the sizes they claim."""
import numpy as np
import pytest

from cljn_addon.core.evaluation.evaluate import is_closed_and_consistent
from cljn_addon.core.evaluation.shapes import (
    SHAPES,
    THIN_SHAPES,
    extrude,
    face_normals_and_areas,
    relief_training_shape,
    sample_mesh,
    shape_mesh,
    signed_volume,
    thin_training_shape,
    triangulate_polygon,
)


def test_ear_clipping_covers_a_concave_polygon_exactly():
    l_shape = np.array([[0, 0], [2, 0], [2, 1], [1, 1], [1, 3], [0, 3]], float)
    tris = triangulate_polygon(l_shape)
    assert len(tris) == 4
    a, b, c = (l_shape[tris[:, i]] for i in range(3))
    areas = 0.5 * ((b - a)[:, 0] * (c - a)[:, 1] - (b - a)[:, 1] * (c - a)[:, 0])
    assert np.all(areas > 0) and np.isclose(areas.sum(), 4.0)


def test_extruded_concave_section_has_the_right_volume():
    v, f = extrude([[0, 0], [2, 0], [2, 1], [1, 1], [1, 3], [0, 3]], 0.5)
    assert is_closed_and_consistent(f)
    assert np.isclose(signed_volume(v, f), 4.0 * 0.5)


@pytest.mark.parametrize("name", sorted(set(THIN_SHAPES) | {"gear", "star_prism"}))
def test_eval_shapes_are_closed_and_outward(name):
    v, f = shape_mesh(name)
    assert is_closed_and_consistent(f)
    assert signed_volume(v, f) > 0
    assert np.isclose(np.linalg.norm(v.max(0) - v.min(0)), 1.0)


def test_thin_plate_is_one_and_a_half_percent_of_its_diagonal_thick():
    v, _ = shape_mesh("thin_plate")
    assert np.isclose(v[:, 2].max() - v[:, 2].min(), 0.015, atol=0.0005)


@pytest.mark.parametrize("index", range(12))
def test_thin_training_family_is_closed_and_thin(index):
    v, f = thin_training_shape(index)
    assert is_closed_and_consistent(f)
    assert signed_volume(v, f) > 0
    if index % 6 == 5:
        return                          # gears: sharp teeth, not thin walls
    # Thin: sample points and check many have an opposite-facing surface close behind them.
    rng = np.random.default_rng(0)
    pts, normals, _ = sample_mesh(v, f, 4000, rng)
    diag = np.linalg.norm(v.max(0) - v.min(0))
    from scipy.spatial import cKDTree
    tree = cKDTree(pts)
    near = tree.query_ball_point(pts, 0.06 * diag)
    opposite = [np.any(normals[idx] @ n < -0.9) for idx, n in zip(near, normals)]
    assert np.mean(opposite) > 0.3


def test_every_named_shape_builds():
    for name in SHAPES:
        v, f = shape_mesh(name)
        _, areas = face_normals_and_areas(v, f)
        assert areas.sum() > 0, name


@pytest.mark.parametrize("index", range(3))
def test_relief_training_family_is_closed_and_carved_at_the_noise_scale(index):
    v, f = relief_training_shape(index)
    assert is_closed_and_consistent(f)
    assert signed_volume(v, f) > 0
    # Relief: the radius (in the ellipsoid's own metric) varies by 0.3-3% around its mean.
    rng = np.random.default_rng(0)
    pts, _, _ = sample_mesh(v, f, 4000, rng)
    axes = (v.max(0) - v.min(0)) / 2
    r = np.linalg.norm((pts - (v.max(0) + v.min(0)) / 2) / axes, axis=1)
    spread = np.percentile(r, 95) - np.percentile(r, 5)
    assert 0.004 < spread < 0.15
    assert not np.array_equal(v, relief_training_shape(index + 1)[0])


def test_varying_noise_grows_linearly_or_in_one_step():
    from cljn_addon.core.evaluation.shapes import sample_shape_varying_noise

    noisy, clean, sigma = sample_shape_varying_noise("sphere", 4000, 0.002, 0.02, seed=1)
    x = clean[:, 0]
    assert np.corrcoef(x, sigma)[0, 1] > 0.999 and np.isclose(sigma.min(), 0.002) and np.isclose(sigma.max(), 0.02)
    _, clean, sigma = sample_shape_varying_noise("sphere", 4000, 0.002, 0.02, seed=1, profile="step")
    middle = (clean[:, 0].min() + clean[:, 0].max()) / 2
    assert np.allclose(sigma[clean[:, 0] < middle], 0.002) and np.allclose(sigma[clean[:, 0] >= middle], 0.02)
    with pytest.raises(ValueError, match="profile"):
        sample_shape_varying_noise("sphere", 100, 0.002, 0.02, profile="ramp")

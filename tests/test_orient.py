"""Orientation: signs agree with the true outward normals."""
import numpy as np
import pytest
from scipy.spatial import cKDTree

from cljn_addon.core import InputError, orient
from cljn_addon.core.evaluation.baselines import pca_normals
from cljn_addon.core.evaluation.metrics import sign_agreement, sign_ceiling_normals
from cljn_addon.core.evaluation.shapes import normalise_unit_diagonal, sample_shape, shape_mesh
from cljn_addon.core.orient import clear_view_signs, input_heights, orient_normals, visibility_votes


@pytest.mark.parametrize("name", ["sphere", "torus", "box"])
@pytest.mark.parametrize("noise", [0.0, 0.005])
def test_outward_orientation_of_estimated_normals(name, noise):
    noisy, _, truth = sample_shape(name, 20000, noise=noise, seed=7)
    unoriented = pca_normals(noisy, 60)              # arbitrary signs, blurred at edges
    oriented = orient_normals(noisy, unoriented, "outward")
    assert sign_agreement(oriented, truth) >= 0.99
    # Step 5 (the input side of points seen from both sides) leaves solids alone.
    assert np.array_equal(orient_normals(noisy, unoriented, "outward", sources=noisy), oriented)
    assert np.allclose(np.abs(oriented), np.abs(unoriented))   # signs change, nothing else


@pytest.mark.parametrize("name", ["sphere", "torus", "box", "stepped_block", "cylinder"])
def test_outward_orientation_of_sharp_normals_with_random_signs(name):
    _, clean, truth = sample_shape(name, 20000, seed=8)
    rng = np.random.default_rng(0)
    scrambled = truth * np.where(rng.random(len(truth)) < 0.5, -1.0, 1.0)[:, None]
    assert sign_agreement(orient_normals(clean, scrambled, "outward"), truth) >= 0.99


def test_viewpoint_orientation_faces_the_scanner():
    rng = np.random.default_rng(1)
    pts = np.c_[rng.uniform(-1, 1, (500, 2)), np.zeros(500)]
    normals = np.tile([0, 0, 1.0], (500, 1)) * np.where(rng.random(500) < 0.5, -1, 1)[:, None]
    out = orient_normals(pts, normals, "viewpoint", viewpoint=(0, 0, -5))
    assert np.all(out[:, 2] == -1.0)
    assert np.array_equal(orient_normals(pts, normals, "none"), normals)


def test_orientation_bad_options():
    pts = np.zeros((3, 3))
    with pytest.raises(InputError, match="viewpoint"):
        orient_normals(pts, pts, "viewpoint")
    with pytest.raises(InputError, match="unknown orientation"):
        orient_normals(pts, pts, "inward")


def test_outward_orientation_of_a_gear_with_sharp_teeth():
    noisy, _, truth = sample_shape("gear", 30000, noise=0.006, seed=8)
    rng = np.random.default_rng(0)
    scrambled = truth * np.where(rng.random(len(truth)) < 0.5, -1.0, 1.0)[:, None]
    assert sign_agreement(orient_normals(noisy, scrambled, "outward"), truth) >= 0.99


def _scrambled_truth(name, noise):
    noisy, _, truth = sample_shape(name, 30000, noise=noise, seed=8)
    rng = np.random.default_rng(0)
    return noisy, truth, truth * np.where(rng.random(len(truth)) < 0.5, -1.0, 1.0)[:, None]


def test_visibility_sees_the_outside_of_a_sphere():
    _, clean, truth = sample_shape("sphere", 20000, seed=3)
    seen, facing = visibility_votes(clean, truth)
    assert len(seen) > 0.95 * len(clean)
    assert np.all(facing > 0)                                 # every view sees the front
    signs = clear_view_signs(clean, -truth)                   # flipped normals: seen from behind
    assert np.mean(signs == -1) > 0.95 and not np.any(signs == 1)


def test_visibility_leaves_an_open_sheet_alone():
    """A flat sheet is seen from above and below alike: no clear side, so no vote."""
    rng = np.random.default_rng(2)
    pts = np.c_[rng.uniform(-1, 1, (5000, 2)), rng.normal(scale=0.002, size=5000)]
    assert np.mean(clear_view_signs(pts, np.tile([0, 0, 1.0], (5000, 1))) != 0) < 0.05


@pytest.mark.parametrize("name, noise, least", [
    ("star_prism", 0.0, 0.99), ("star_prism", 0.006, 0.95),   # before visibility: 69.9%, 69.9%
    ("thin_plate", 0.0, 0.99), ("thin_plate", 0.006, 0.85),   # 100%, 50.5%
    ("stool", 0.0, 0.99), ("stool", 0.006, 0.94),             # 100%, 34.4%
])
def test_visibility_orients_both_sides_of_thin_parts(name, noise, least):
    """The two faces of a thin tip, plate or seat share k-NN neighbourhoods; steps 1-3 alone
    joined them with one sign. Exact normals with random signs, on the clean or noisy points."""
    points, truth, scrambled = _scrambled_truth(name, noise)
    assert sign_agreement(orient_normals(points, scrambled, "outward"), truth) >= least


@pytest.mark.parametrize("name", ["star_prism", "thin_plate"])
def test_outward_orientation_of_thin_parts_reaches_its_ceiling(name):
    """At 0.6% noise a star tip or a 2.5-sigma plate has points whose face no method can tell
    (issue #12 asked for 99%: the ceiling is 97.6% and 89.2% on these clouds); orientation of
    exact normals with random signs comes within 1.5 points of it."""
    noisy, _, truth = sample_shape(name, 30000, noise=0.006, seed=8)
    rng = np.random.default_rng(0)
    scrambled = truth * np.where(rng.random(len(truth)) < 0.5, -1.0, 1.0)[:, None]
    v, f = shape_mesh(name)
    ceiling = sign_agreement(sign_ceiling_normals(noisy, normalise_unit_diagonal(v), f, 0.006), truth)
    assert ceiling < 0.99
    for sources in (None, noisy):
        assert sign_agreement(orient_normals(noisy, scrambled, "outward", sources=sources), truth) >= ceiling - 0.015


@pytest.mark.parametrize("chunk", [None, 1_000])
def test_points_turned_to_their_input_side_come_with_its_heights(chunk, monkeypatch):
    """A wall 2 sigma thick drawn into one sheet (thin-walled): step 5 turns each point to the
    side of the local input median its own input lay on (right for ~Phi(1) = 84%), and hands
    back that median and the heights' variance along the turned normal (what the seating in
    `sheets.seat_on_facing_face` reads, so it need not search the input again). Taken in
    chunks of rows (`orient.INPUT_SIDE_CHUNK`, for 10M-point clouds), the same."""
    if chunk is not None:
        monkeypatch.setattr(orient, "INPUT_SIDE_CHUNK", chunk)
    rng = np.random.default_rng(3)
    n, sigma, half = 20000, 0.01, 0.01
    xy = rng.random((n, 2))
    face = np.where(rng.random(n) < 0.5, -1.0, 1.0)
    sources = np.c_[xy, face * half + rng.normal(0, sigma, n)]
    merged = np.c_[xy, np.zeros(n)]
    scrambled = np.c_[np.zeros((n, 2)), np.where(rng.random(n) < 0.5, -1.0, 1.0)]
    out, faced = orient_normals(merged, scrambled, "outward", sources=sources, thin_walled=True, with_input_side=True)
    idx = faced.idx
    assert len(idx) > 0.5 * n
    assert np.all(np.einsum("mc,mc->m", sources[idx] - merged[idx], out[idx]) >= faced.median)
    assert 0.78 < np.mean(np.sign(out[idx, 2]) == face[idx]) < 0.9
    heights = input_heights(cKDTree(sources), sources, merged[idx], out[idx])
    np.testing.assert_allclose(faced.median, np.median(heights, axis=1), atol=1e-12)
    np.testing.assert_allclose(faced.variance, heights.var(axis=1), atol=1e-12)
    assert np.median(faced.variance) > sigma ** 2          # the two faces widen the spread
    _, none_faced = orient_normals(merged, scrambled, "outward", with_input_side=True)
    assert len(none_faced.idx) == 0


def _bell(n, rng, radius=0.25, height=0.3):
    """A one-sided shell: a cylinder's side and top, open at its base (a bust or a vase
    scanned from above and around, never from below). Points and outward normals."""
    side, cap = 2 * np.pi * radius * height, np.pi * radius ** 2
    n_side = int(n * side / (side + cap))
    t, z = rng.uniform(0, 2 * np.pi, n_side), rng.uniform(-height / 2, height / 2, n_side)
    ring = np.c_[np.cos(t), np.sin(t), np.zeros(n_side)]
    wall = np.c_[radius * ring[:, :2], z]
    r, t = radius * np.sqrt(rng.random(n - n_side)), rng.uniform(0, 2 * np.pi, n - n_side)
    top = np.c_[r * np.cos(t), r * np.sin(t), np.full(n - n_side, height / 2)]
    return np.concatenate([wall, top]), np.concatenate([ring, np.tile([0.0, 0.0, 1.0], (n - n_side, 1))])


def test_a_shell_open_at_its_base_keeps_its_outward_normals():
    """Seen through its opening, the inside of a one-sided shell is seen from both sides too,
    but mostly from one (|vote| ~0.4); step 5 once read its input side there, which on one
    surface is noise: 35% of the points turned, half of them wrong (sign 83%). It now keeps to
    regions seen about as much from either side; a star's tips still get it (the test above)."""
    rng = np.random.default_rng(0)
    clean, truth = _bell(30000, rng)
    denoised = clean + rng.normal(0, 0.002, clean.shape)
    sources = clean + rng.normal(0, 0.01, clean.shape)
    scrambled = truth * np.where(rng.random(len(truth)) < 0.5, -1.0, 1.0)[:, None]
    _, two_sided, imbalance = clear_view_signs(denoised, scrambled, with_two_sided=True)
    assert two_sided.mean() > 0.3 and np.median(imbalance[two_sided]) > 0.3   # what fooled step 5
    out, faced = orient_normals(denoised, scrambled, "outward", sources=sources, with_input_side=True)
    assert faced.closed and len(faced.idx) < 0.01 * len(clean)
    assert sign_agreement(out, truth) >= 0.995


def test_open_terrain_faces_up_and_a_flat_closed_box_still_faces_out():
    """A terrain scan has no inside (its flux is ~0): outward turns it up (+z); a flat closed
    box, whose bottom must face down, is still oriented by its flux."""
    from cljn_addon.core.evaluation.shapes import box, normalise_unit_diagonal, sample_mesh
    from cljn_addon.core.orient import orient_outward

    rng = np.random.default_rng(0)
    xy = rng.uniform(0, 200, (20000, 2))
    terrain = np.c_[xy, 2 * np.sin(xy[:, 0] / 10) + rng.normal(0, 0.01, 20000)]
    truth = np.c_[-0.2 * np.cos(xy[:, 0] / 10), np.zeros(20000), np.ones(20000)]
    truth /= np.linalg.norm(truth, axis=1, keepdims=True)
    out = orient_outward(terrain, truth * rng.choice([-1, 1], size=(20000, 1)))
    assert np.mean(out[:, 2] > 0) > 0.99

    v, f = box((2.0, 2.0, 0.2))
    v = normalise_unit_diagonal(v)
    clean, normals, _ = sample_mesh(v, f, 20000, rng)
    out = orient_outward(clean, normals * rng.choice([-1, 1], size=(20000, 1)))
    assert np.mean(np.einsum("ij,ij->i", out, normals) > 0) > 0.99


def test_an_open_scan_is_left_to_propagation():
    """One sweep of a range scanner (an open, bumpy cap) is seen from both sides almost
    everywhere; the handful of clear views must not scramble it (bun000 went to 47% agreement
    with propagation before the closed-share check)."""
    rng = np.random.default_rng(4)
    u = rng.uniform(-1, 1, (30000, 2))
    z = 0.15 * np.sin(3 * u[:, 0]) * np.cos(2 * u[:, 1]) + 0.3 * (u ** 2).sum(axis=1)
    pts = np.c_[u, z + rng.normal(scale=0.004, size=len(u))]
    grad = np.c_[-0.45 * np.cos(3 * u[:, 0]) * np.cos(2 * u[:, 1]) - 0.6 * u[:, 0],
                 0.3 * np.sin(3 * u[:, 0]) * np.sin(2 * u[:, 1]) - 0.6 * u[:, 1], np.ones(len(u))]
    truth = grad / np.linalg.norm(grad, axis=1, keepdims=True)
    scrambled = truth * np.where(rng.random(len(u)) < 0.5, -1.0, 1.0)[:, None]
    for sources in (None, pts):     # the input side of step 5 must not scramble it either
        out = orient_normals(pts, scrambled, "outward", sources=sources)
        agree = sign_agreement(out, truth)
        assert max(agree, 1 - agree) >= 0.99        # one consistent side, whichever it is

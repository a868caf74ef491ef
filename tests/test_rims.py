"""Rims: points the noise left beyond a thin part's edge take the rim's normal."""
import numpy as np
import pytest

from cljn_addon.core import denoise, load_model
from cljn_addon.core.evaluation.metrics import MeshDistance, msae, sign_agreement
from cljn_addon.core.evaluation.shapes import sample_shape, shape_mesh
from cljn_addon.core.rims import RIM_LEAN, edge_share_ahead, rim_normals


@pytest.mark.parametrize("reach, offset", [(2.0, 0.0), (3.0, 0.0), (2.0, 0.5), (4.0, -0.5)])
def test_edge_share_matches_points_scattered_across_a_blurred_edge(reach, offset):
    """The integral against a sample: a half-plane x < offset sampled uniformly, every point
    moved by unit Gaussian noise in x and y, read from the origin."""
    rng = np.random.default_rng(0)
    n = 2_000_000
    points = np.c_[rng.uniform(-12, offset, n), rng.uniform(-8, 8, n)] + rng.normal(size=(n, 2))
    near = points[np.sum(points ** 2, axis=1) <= reach ** 2]
    assert len(near) > 20_000
    assert edge_share_ahead(reach, offset) == pytest.approx(np.mean(near[:, 0] > 0), abs=0.006)


def _ideal_plate(noise, n=30_000, seed=1):
    """The thin plate's points after an ideal pass: the noise across each face removed, the
    noise along it kept (the passes move points along their normals only), and the normals a
    network gives: its big faces' (the rim's own samples take the nearer face's)."""
    noisy, clean, truth = sample_shape("thin_plate", n, noise=noise, seed=seed)
    along = (noisy - clean) - np.einsum("ij,ij->i", noisy - clean, truth)[:, None] * truth
    # A little inside the faces, as a pass leaves a wall thinner than the noise (on the face
    # planes themselves, beyond the edge, the face and the rim are equally near).
    points = (clean + along) * [1.0, 1.0, 0.9]
    return points, np.c_[np.zeros((n, 2)), np.where(clean[:, 2] < 0, -1.0, 1.0)]


def test_points_beyond_a_plate_edge_take_the_rim_normal():
    """Against the clean surface nearest each point (what shading shows): the points beyond the
    edge face the rim, the inside is left alone."""
    sigma = 0.01
    points, normals = _ideal_plate(sigma)
    rim, outward = rim_normals(points, normals, sigma)
    vertices, faces = shape_mesh("thin_plate")
    _, facing = MeshDistance(vertices, faces).nearest(points)
    half = np.abs(vertices).max(axis=0)[:2]
    inside = np.all(np.abs(points[:, :2]) < half - 4 * sigma, axis=1)
    beyond = np.any(np.abs(points[:, :2]) > half + sigma, axis=1)
    assert rim.mean() > 0.01 and not rim[inside].any()            # 2.0%
    assert rim[beyond].mean() > 0.75                                # 0.90
    # Outward, as the rim faces (96%; the rest lie within the noise of the edge).
    assert sign_agreement(outward, facing[rim]) > 0.9
    fixed = normals.copy()
    fixed[rim] = outward
    assert msae(fixed, facing) < 0.75 * msae(normals, facing)      # 0.081 against 0.126


def test_the_border_of_a_hole_in_one_sheet_is_not_a_rim():
    """The plate's top face alone, its normals all one way: its border is where the surface
    ends (a hole, a scan's edge), not a rim joining two faces; with random signs it would read
    as one, so the faces' opposed normals are what tell them apart."""
    sigma = 0.01
    points, normals = _ideal_plate(sigma)
    top = normals[:, 2] > 0.9
    rim, _ = rim_normals(points[top], normals[top], sigma)
    assert not rim.any()
    flipped = normals[top] * np.random.default_rng(0).choice([-1.0, 1.0], size=(top.sum(), 1))
    assert rim_normals(points[top], flipped, sigma)[0].mean() > 0.01


def test_no_reading_where_the_cloud_is_too_sparse_for_the_noise():
    points, normals = _ideal_plate(0.001, n=2_000)
    rim, outward = rim_normals(points, normals, 0.001)
    assert not rim.any() and outward.shape == (0, 3)


@pytest.fixture(scope="module")
def shipped():
    return load_model()


def test_the_denoise_gives_a_thin_bracket_s_rims_their_normals(shipped):
    """An L-bracket (legs 1.5 sigma thick) at 1.5%: output normals against the clean surface
    nearest each output point improve with rim normals and nothing else changes."""
    noisy, _, _ = sample_shape("l_bracket", 20_000, noise=0.015, seed=2)
    on = denoise(noisy, shipped, iterations="auto")
    off = denoise(noisy, shipped, iterations="auto", rim_normals=False)
    assert off.rim_share == 0 and 0.005 < on.rim_share < 0.1
    assert np.array_equal(on.points, off.points)
    changed = np.any(on.normals != off.normals, axis=1)
    assert changed.mean() == pytest.approx(on.rim_share)
    _, facing = MeshDistance(*shape_mesh("l_bracket")).nearest(on.points)
    assert msae(on.normals, facing) < 0.9 * msae(off.normals, facing)
    assert sign_agreement(on.normals[changed], facing[changed]) > sign_agreement(off.normals[changed], facing[changed])
    # The lean toward each point's own face: the same points, each 11 degrees off the rim's
    # normal, and nearer the clean surface's than with no lean (50K at 1.5%: 0.1403 -> 0.1388).
    kept = ~off.outliers
    rim, upright = rim_normals(off.points[kept], off.normals[kept], off.noise_sigma, lean=0.0)
    assert np.array_equal(np.flatnonzero(kept)[rim], np.flatnonzero(changed))
    tilt = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", on.normals[changed], upright), -1, 1)))
    assert np.allclose(tilt, np.degrees(np.arctan(RIM_LEAN)), atol=0.01)
    unleaned = off.normals.copy()
    unleaned[changed] = upright
    assert msae(on.normals, facing) < msae(unleaned, facing)


def test_an_open_scan_s_border_is_not_a_rim(shipped):
    """An open sheet (one sweep of a scanner) ends at its border; nothing there is a rim, so its
    normals are the network's, as with rim_normals off."""
    rng = np.random.default_rng(3)
    xy = rng.uniform(-0.5, 0.5, (12_000, 2))
    sheet = np.c_[xy, 0.1 * np.sin(3 * xy[:, 0])] + rng.normal(scale=0.01, size=(12_000, 3))
    on = denoise(sheet, shipped, iterations="auto")
    off = denoise(sheet, shipped, iterations="auto", rim_normals=False)
    assert on.rim_share == 0 and np.array_equal(on.normals, off.normals)

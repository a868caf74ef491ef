"""Two sheets in one patch (core/sheets.py): found where a thin part puts both sides in a
patch, not on one noisy sheet, and the centre's own sheet kept. (A crease can read as two
sheets too; that is why the engine uses own-sheet patches only on clouds that are thin-walled
as a whole: tests/test_noise.py.)"""
import numpy as np
from scipy.spatial import cKDTree

import cljn_addon.core.sheets as sheets
from cljn_addon.core.orient import input_heights
from cljn_addon.core.sheets import fit_two_sheets, in_faced_region, own_sheet_patches, seat_on_facing_face, split_merged_walls


def _patches(m, n, height, sigma, seed):
    """m patches of n points in the unit disc, the centre (row 0) at the origin, z = height(x, y)
    plus Gaussian noise of `sigma` (patch units)."""
    rng = np.random.default_rng(seed)
    r = np.sqrt(rng.random((m, n)))
    t = rng.random((m, n)) * 2 * np.pi
    x, y = r * np.cos(t), r * np.sin(t)
    z = height(x, y, rng) + rng.normal(scale=sigma, size=(m, n))
    pts = np.stack([x, y, z], axis=-1)
    pts[:, 0] = 0.0
    return pts


def test_two_parallel_sheets_three_sigma_apart_are_found_with_their_noise():
    sigma, gap = 0.06, 0.18                                    # 3 sigma apart, as a 1.5% plate at 0.5%
    upper = np.random.default_rng(9).random((400, 128)) < 0.5
    upper[:, 0] = False                                        # the centre lies on the lower sheet
    pts = _patches(400, 128, lambda x, y, rng: 0.1 * x * x, sigma, seed=1)
    pts[..., 2] += upper * gap
    fit = fit_two_sheets(pts)
    assert fit["two"].mean() > 0.7                             # 3 sigma apart, 128 points: ~80%
    found = fit["two"]
    assert abs(np.median(fit["sigma"][found]) / sigma - 1) < 0.15
    own = (fit["upper"][found] > 0.5) == fit["centre_upper"][found, None]
    assert np.mean(own == ~upper[found]) > 0.85
    # Own-sheet patches: every point of a two-sheet patch is one of the centre's sheet.
    out, _ = own_sheet_patches(pts, pts, np.random.default_rng(0))
    kept = out[found]
    above_middle = kept[..., 2] - 0.1 * kept[..., 0] ** 2 > gap / 2
    assert above_middle.mean() < 0.08                          # only the lower sheet's noise tail
    assert np.array_equal(out[~found], pts[~found])            # one-sheet patches untouched


def test_one_noisy_curved_sheet_is_not_split():
    pts = _patches(400, 128, lambda x, y, rng: 0.15 * x * x - 0.1 * y * y, 0.06, seed=2)
    assert fit_two_sheets(pts)["two"].mean() < 0.1


# Walls that denoising merged into one sheet (split_merged_walls).

def _wall(n, half_thickness, sigma, seed, collapse=True):
    """A square wall (z = +-half_thickness faces) sampled n times, the noisy input and a stand-in
    for the denoised cloud: every point on the mid-plane (the network's merge) or on its own
    face (a network that kept the faces apart), with a little residual noise."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-1, 1, (n, 2))
    face = np.where(rng.random(n) < 0.5, 1.0, -1.0)
    clean = np.c_[xy, face * half_thickness]
    noisy = clean + rng.normal(scale=sigma, size=clean.shape)
    out = np.c_[noisy[:, :2], (0.0 if collapse else 1.0) * clean[:, 2] + rng.normal(scale=0.1 * sigma, size=n)]
    normals = np.tile([0.0, 0.0, 1.0], (n, 1))
    return clean, noisy, out, normals, face


def _sheet_beside_wall(sheet_n, wall_n, half_thickness, wall_scale=(1.0, 1.0, 1.0), sigma=0.01):
    """One flat noisy sheet (sheet_n points, first) and a merged wall (wall_n points) beside it,
    3 units along x, its x scaled by wall_scale: (noisy, merged output, normals)."""
    _, noisy_sheet, out_sheet, normals_sheet, _ = _wall(sheet_n, 0.0, sigma, seed=10)
    _, noisy_wall, out_wall, normals_wall, _ = _wall(wall_n, half_thickness, sigma, seed=11)
    scale, beside = np.asarray(wall_scale), np.array([3.0, 0.0, 0.0])
    return (np.r_[noisy_sheet, noisy_wall * scale + beside], np.r_[out_sheet, out_wall * scale + beside],
            np.r_[normals_sheet, normals_wall])


def _face_distance(points, half_thickness):
    return np.abs(np.abs(points[:, 2]) - half_thickness).mean()


def test_a_merged_wall_thinner_than_two_sigma_is_split_back_onto_its_faces():
    sigma, half = 0.01, 0.0092                     # 1.84 sigma thick: a 1.5% plate at 0.8% noise
    clean, noisy, merged, normals, face = _wall(20000, half, sigma, seed=3)
    out, side = split_merged_walls(noisy, merged, normals)
    assert (side != 0).mean() > 0.95
    # Nearer the faces than the merged sheet (half) and than the noisy input.
    assert _face_distance(out, half) < 0.3 * _face_distance(merged, half)
    assert _face_distance(out, half) < 0.3 * _face_distance(noisy, half)
    # Faces put back ~a apart; sides are the Bayes guess: Phi(t / 2 sigma) = 82% right.
    assert abs(np.median(np.abs(out[side != 0, 2])) / half - 1) < 0.15
    assert 0.75 < np.mean(side[side != 0] == face[side != 0]) < 0.9
    # Along the sheet's normal only: x, y move by a tilt's worth, far less than z.
    assert np.abs(out[:, :2] - merged[:, :2]).max() < 0.2 * half


def test_a_merged_wall_1_2_sigma_thick_is_found_by_the_whole_cloud_test(monkeypatch):
    """A 1.5% plate at 1.2% noise: kurtosis 2.87, too close to 3 for the local pools (thousands
    of tests) but many standard errors below it over the whole cloud (one test)."""
    sigma, half = 0.01, 0.006
    clean, noisy, merged, normals, face = _wall(40000, half, sigma, seed=8)
    out, side = split_merged_walls(noisy, merged, normals)
    assert (side != 0).mean() > 0.95
    assert _face_distance(out, half) < 0.3 * _face_distance(merged, half)
    assert abs(np.median(np.abs(out[side != 0, 2])) / half - 1) < 0.15
    assert 0.68 < np.mean(side[side != 0] == face[side != 0]) < 0.78   # Phi(0.6) = 0.73
    # With the local pools' thresholds on the whole cloud too, this wall stays merged.
    monkeypatch.setattr(sheets, "SPLIT_Z_CLOUD", sheets.SPLIT_Z)
    monkeypatch.setattr(sheets, "SPLIT_MIN_R_CLOUD", sheets.SPLIT_MIN_R)
    assert not sheets.split_merged_walls(noisy, merged, normals)[1].any()


def test_a_solid_region_beside_walls_found_by_the_whole_cloud_is_left_alone(monkeypatch):
    """80% of the cloud a merged wall 1.3 sigma thick, 20% one noisy sheet: only the whole-cloud
    pool finds the two faces, and the sheet must not be split by the wall's offset."""
    noisy, out, normals = _sheet_beside_wall(8000, 32000, 0.0065)
    res, side = split_merged_walls(noisy, out, normals)
    assert (side[8000:] != 0).mean() > 0.95
    assert not side[:8000].any() and np.array_equal(res[:8000], out[:8000])
    # The local-spread gate is what keeps the sheet: without it a third of it moves.
    monkeypatch.setattr(sheets, "SPLIT_LOCAL_EXCESS", -np.inf)
    side = sheets.split_merged_walls(noisy, out, normals)[1]
    assert (side[:8000] != 0).mean() > 0.1


def test_a_few_percent_merged_is_left_alone(monkeypatch):
    """A merged wall holding 4% of the cloud, beside one clean sheet: under SPLIT_MIN_SHARE,
    so nothing moves (a half-merged thick part, as on a gear at 2% noise, is likelier there
    than a thin wall)."""
    noisy, out, normals = _sheet_beside_wall(38400, 1600, 0.0125, wall_scale=(0.2, 1.0, 1.0))   # a strip
    res, side = split_merged_walls(noisy, out, normals)
    assert not side.any() and np.array_equal(res, out)
    # The gate is what holds it: without it the strip (and only the strip) is split.
    monkeypatch.setattr(sheets, "SPLIT_MIN_SHARE", 0.0)
    side = sheets.split_merged_walls(noisy, out, normals)[1]
    assert (side[-1600:] != 0).mean() > 0.9 and not side[:-1600].any()


def test_one_noisy_sheet_and_walls_kept_apart_are_left_alone():
    sigma = 0.01
    # One noisy sheet denoised onto itself (the Gaussian heights of one face).
    _, noisy, out, normals, _ = _wall(20000, 0.0, sigma, seed=4)
    res, side = split_merged_walls(noisy, out, normals)
    assert not side.any() and np.array_equal(res, out)
    # A sheet whose noise varies 3x across the scan (a range scanner): heavy-tailed, not two faces.
    rng = np.random.default_rng(5)
    xy = rng.uniform(-1, 1, (20000, 2))
    noisy = np.c_[xy, rng.normal(size=20000) * sigma * (1 + (xy[:, 0] + 1))]
    res, side = split_merged_walls(noisy, np.c_[xy, np.zeros(20000)], normals)
    assert not side.any()
    # A wall 5 sigma thick whose faces the network kept apart: nothing merged, nothing moved.
    _, noisy, out, normals, _ = _wall(20000, 0.025, sigma, seed=6, collapse=False)
    res, side = split_merged_walls(noisy, out, normals)
    assert (side != 0).mean() < 0.02
    assert np.abs(res - out).max() < 2 * sigma


def test_a_wall_four_sigma_thick_kept_apart_is_left_alone(monkeypatch):
    """A slab 4.2 sigma thick (a gear at 2% noise) that the passes denoised onto its nearer
    face: the ~2% of points whose noise crossed the middle went to the other face, which
    flattens the heights' tails (kurtosis ~2.8), but the faces were never merged."""
    rng = np.random.default_rng(12)
    sigma, half, n = 0.01, 0.021, 20000
    xy = rng.uniform(-0.25, 0.25, (n, 2))
    noisy = np.c_[xy, np.where(rng.random(n) < 0.5, half, -half)] + rng.normal(scale=sigma, size=(n, 3))
    out = np.c_[noisy[:, :2], np.where(noisy[:, 2] >= 0, half, -half) + rng.normal(scale=0.1 * sigma, size=n)]
    normals = np.tile([0.0, 0.0, 1.0], (n, 1))
    res, side = split_merged_walls(noisy, out, normals)
    assert not side.any() and np.array_equal(res, out)
    # The other face along the normal is what tells: without looking for it, all of it splits.
    monkeypatch.setattr(sheets, "OPPOSITE_STEPS", ())
    assert (sheets.split_merged_walls(noisy, out, normals)[1] != 0).mean() > 0.9


def test_heights_stored_on_a_grid_are_not_taken_for_two_faces(monkeypatch):
    """A LAS file at 1 cm over a scan with ~1 cm of noise: the heights come in a few levels,
    flat-topped like two faces, but in bands along the surface (plane.laz: 5 distinct z)."""
    rng = np.random.default_rng(7)
    sigma, step = 0.01, 0.03
    xy = rng.uniform(-1, 1, (20000, 2))
    surface = 0.05 * xy[:, 0] + 0.03 * np.sin(3 * xy[:, 1])
    noisy = np.c_[xy, np.round((surface + rng.normal(scale=sigma, size=20000)) / step) * step]
    cleaned = np.c_[xy, surface]
    normals = np.tile([0.0, 0.0, 1.0], (20000, 1))
    _, side = split_merged_walls(noisy, cleaned, normals)
    assert not side.any()
    # The kurtosis alone would take it for two faces: it is the side test that tells.
    monkeypatch.setattr(sheets, "SPLIT_MAX_AGREEMENT", 1.01)
    assert (sheets.split_merged_walls(noisy, cleaned, normals)[1] != 0).mean() > 0.5


def _merged_tube(n, radius, half_thickness, sigma, seed):
    """A tube wall (radius +- half_thickness faces, length 1) and a stand-in for its denoised
    cloud merged onto the mid radius: (noisy, merged, outward normals)."""
    rng = np.random.default_rng(seed)
    angle, z = rng.uniform(0, 2 * np.pi, n), rng.uniform(0, 1, n)
    outward = np.c_[np.cos(angle), np.sin(angle), np.zeros(n)]
    face = np.where(rng.random(n) < 0.5, 1.0, -1.0)
    clean = (radius + face * half_thickness)[:, None] * outward + np.c_[np.zeros((n, 2)), z]
    noisy = clean + rng.normal(scale=sigma, size=clean.shape)
    merged = (radius + rng.normal(scale=0.1 * sigma, size=n))[:, None] * outward + np.c_[np.zeros((n, 2)), noisy[:, 2]]
    return noisy, merged, outward


def test_a_tightly_bent_merged_wall_keeps_the_narrow_sheet(monkeypatch):
    """A tube 6 sigma in radius, its wall 1.5 sigma thick: a sheet fitted over a point's 128
    nearest outputs cuts the bend (split 58%, faces 0.36 sigma off). Of the two scales the
    narrow one shows the faces better (flatter-topped heights) and is kept: 84%, 0.20 sigma.
    (With an opposite face at 0.3x the point's own ball and at least 8 outputs, the curved
    sheet itself read as a face from some points: 70% / 0.27 sigma, the wide sheet alone 25%.)"""
    sigma, radius, half = 0.01, 0.06, 0.0075
    noisy, merged, outward = _merged_tube(20000, radius, half, sigma, seed=3)

    def face_error(points):
        return np.abs(np.abs(np.hypot(points[:, 0], points[:, 1]) - radius) - half).mean() / sigma

    out, side = split_merged_walls(noisy, merged, outward)
    assert (side != 0).mean() > 0.75
    assert face_error(out) < 0.25 < 0.35 < face_error(merged)          # merged: 0.75 sigma off its faces
    monkeypatch.setattr(sheets, "SHEET_SCALES", (128,))
    out_wide, side_wide = split_merged_walls(noisy, merged, outward)
    assert (side_wide != 0).mean() < 0.7 and face_error(out_wide) > 1.5 * face_error(out)


def _faced_by_input_side(noisy, merged):
    """Unit normals +-z, each facing the side of the mid-plane its input lay on (orient step 5)."""
    return np.c_[np.zeros((len(merged), 2)), np.where(noisy[:, 2] >= 0, 1.0, -1.0)]


def _seat(noisy, merged, normals, rows, sigma):
    """`seat_on_facing_face` for `rows`, from the input heights orient's step 5 hands over."""
    heights = input_heights(cKDTree(noisy), noisy, merged[rows], normals[rows])
    return seat_on_facing_face(merged[rows], normals[rows], np.median(heights, axis=1), heights.var(axis=1), sigma)


def test_points_facing_their_input_side_are_seated_on_the_face_they_face():
    """A merged wall 3 sigma thick: each point goes to the face its normal faces, half the
    thickness from the input's mid-plane (a from the input's spread less the noise)."""
    sigma, half = 0.01, 0.015
    _, noisy, merged, _, _ = _wall(20000, half, sigma, seed=4)
    normals = _faced_by_input_side(noisy, merged)
    rows = np.arange(0, len(merged), 2)
    seated = _seat(noisy, merged, normals, rows, sigma)
    # (The mid-plane is a median of 48 inputs: it strays by ~0.2 sigma.)
    assert np.mean(np.sign(seated[:, 2]) == normals[rows, 2]) > 0.99
    assert abs(np.median(np.abs(seated[:, 2])) / half - 1) < 0.15
    assert _face_distance(seated, half) < 0.3 * _face_distance(merged[rows], half)
    np.testing.assert_allclose(seated[:, :2], merged[rows, :2])      # along the normal only


def test_a_wall_too_thin_to_measure_is_seated_at_least_half_a_sigma_out():
    """0.4 sigma thick: the input's spread cannot tell its faces from noise, so each point is
    put SEAT_MIN_OFFSET sigma out on its side (where the face it shades as is the nearest)."""
    sigma, half = 0.01, 0.002
    _, noisy, merged, _, _ = _wall(20000, half, sigma, seed=5)
    normals = _faced_by_input_side(noisy, merged)
    seated = _seat(noisy, merged, normals, np.arange(len(merged)), sigma)
    assert np.mean(np.sign(seated[:, 2]) == normals[:, 2]) > 0.98
    height = np.abs(seated[:, 2])
    assert np.quantile(height, 0.05) > 0.15 * sigma          # (0.24 sigma: the median strays)
    assert abs(np.median(height) / (sheets.SEAT_MIN_OFFSET * sigma) - 1) < 0.3


def test_a_region_turned_as_a_whole_is_told_from_scattered_turned_points():
    """Plane-placed points are seated only inside a region orient turned as a whole (a thin
    tip), not where turned points are scattered (relief on one surface): `in_faced_region`."""
    rng = np.random.default_rng(6)
    points = np.c_[rng.random((20000, 2)), np.zeros(20000)]
    tip = points[:, 0] < 0.3                                    # turned as a whole
    scattered = (points[:, 0] > 0.5) & (rng.random(20000) < 0.5)  # half the points, here and there
    faced = tip | scattered
    inner_tip = np.flatnonzero(points[:, 0] < 0.25)
    among_scattered = np.flatnonzero(scattered & (points[:, 0] > 0.55))
    assert in_faced_region(points, faced, inner_tip).mean() > 0.99
    assert in_faced_region(points, faced, among_scattered).mean() < 0.01
    assert len(in_faced_region(points, faced, np.zeros(0, int))) == 0

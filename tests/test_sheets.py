"""Two sheets in one patch (core/sheets.py): found where a thin part puts both sides in a
patch, not on one noisy sheet, and the centre's own sheet kept. (A crease can read as two
sheets too; that is why the engine uses own-sheet patches only on clouds that are thin-walled
as a whole: tests/test_noise.py.)"""
import numpy as np

from cljn_addon.core.sheets import fit_two_sheets, own_sheet_patches


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

"""The per-region choice between the network's result and a plane filter by Stein's unbiased
risk estimate (`core.risk`), and the quiet-ball noise it is weighted by."""
import numpy as np
import pytest

from cljn_addon.core.evaluation.baselines import pca_projection_filter
from cljn_addon.core.evaluation.shapes import sample_shape
from cljn_addon.core.noise import estimate_noise
from cljn_addon.core.patches import bbox_diagonal
from cljn_addon.core.risk import KEPT_INPUT, PROBE_SIGMAS, choose_among, choose_by_risk, fitted_normals, normal_risk, probe_offsets

SIGMA = 0.01


def relief_plane(n, seed, relief=True, relief_share=0.5, amplitude=1.5 * SIGMA, wavelength=0.1):
    """A unit square at z = 0 whose left part (relief_share of it) carries bumps (amplitude 1.5
    sigma, 0.1 across by default: the noise's own scale); noisy points, clean heights, normals +z."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0.0, 1.0, (n, 2))
    bumps = amplitude * np.sin(2 * np.pi * xy[:, 0] / wavelength) * np.sin(2 * np.pi * xy[:, 1] / wavelength)
    height = np.where(xy[:, 0] < relief_share, bumps, 0.0)
    if not relief:
        height[:] = 0.0
    clean = np.column_stack([xy, height])
    noisy = clean + rng.normal(scale=SIGMA, size=clean.shape)
    normals = np.tile([0.0, 0.0, 1.0], (n, 1))
    return noisy, clean, normals


@pytest.mark.parametrize("relief", [True, False])
def test_risk_estimate_matches_the_true_error_of_a_plane_filter(relief):
    """Without the truth, the mean SURE (less sigma^2) matches a plane filter's true mean
    squared error along the normal: within 5% of sigma^2 with a small nudge; with the engine's
    nudge it errs only high (the choice then leans to the network, today's result)."""
    noisy, clean, normals = relief_plane(20000, seed=1, relief=relief)
    for probe_sigmas, below, above in ((0.1, 0.05, 0.05), (PROBE_SIGMAS, 0.01, 0.2)):
        amplitude, offsets = probe_offsets(normals, SIGMA, seed=2, probe_sigmas=probe_sigmas)
        for k in (10, 20, 80):
            f = pca_projection_filter(noisy, k)
            fp = pca_projection_filter(noisy + offsets, k)
            risk = normal_risk(noisy, normals, f, fp, amplitude, SIGMA, probe_sigmas=probe_sigmas)
            excess = (np.mean(risk) - SIGMA ** 2 - np.mean((f[:, 2] - clean[:, 2]) ** 2)) / SIGMA ** 2
            assert -below < excess < above, (probe_sigmas, k, excess)


def test_relief_takes_the_plane_filter_and_flat_parts_keep_the_flattener():
    """A stand-in 'network' that flattens everything to z = 0 (no divergence) is right on the
    flat half and erodes the relief on the other: each region keeps the better of the two."""
    noisy, clean, normals = relief_plane(20000, seed=3)
    amplitude, offsets = probe_offsets(normals, SIGMA, seed=4)
    flat = noisy * [1.0, 1.0, 0.0]
    flat_probe = (noisy + offsets) * [1.0, 1.0, 0.0]
    positions, choice = choose_by_risk(noisy, normals, flat, flat_probe, amplitude, offsets, SIGMA)
    left = noisy[:, 0] < 0.4
    right = noisy[:, 0] > 0.6
    assert np.mean(choice[left] > 0) > 0.9
    error = lambda p, rows=slice(None): np.mean((p[rows, 2] - clean[rows, 2]) ** 2)      # noqa: E731
    # On the flat half the flattener is exact and the widest plane filter nearly so (0.01
    # sigma^2): either may win there, the small ones (0.1-0.5 sigma^2) must not.
    assert np.mean(choice[right] == 0) > 0.6
    assert error(positions, right) < 0.05 * SIGMA ** 2
    assert error(positions) < 0.8 * error(flat)
    assert error(positions) < min(error(pca_projection_filter(noisy, k)) for k in (10, 20, 40, 80))


def test_each_point_takes_the_position_of_the_candidate_its_region_chose():
    """Three candidates (exact, half-flattened, raised by 2 sigma): every output row is the
    chosen candidate's own row, in the candidates' dtype, and the raised one is never chosen."""
    noisy, clean, normals = relief_plane(8000, seed=7, relief=False)
    amplitude, offsets = probe_offsets(normals, SIGMA, seed=8)
    candidates = [(c.astype(np.float32), (c + offsets).astype(np.float32))
                  for c in (clean, 0.5 * (noisy + clean), clean + [0.0, 0.0, 2 * SIGMA])]
    positions, choice = choose_among(noisy, normals, candidates, amplitude, SIGMA)
    assert positions.dtype == np.float32 and positions.shape == noisy.shape
    assert set(np.unique(choice)) <= {0, 1}
    expected = np.stack([f for f, _ in candidates])[choice, np.arange(len(noisy))]
    assert np.array_equal(positions, expected)
    assert all(positions is not f for f, _ in candidates)


def test_a_cancel_stops_the_choice_between_plane_filters(monkeypatch):
    """The plane filters take minutes at 10M points: a cancel set while one runs stops the
    choice before the next, not after all of them."""
    import threading

    from cljn_addon.core import Cancelled, risk

    noisy, _, normals = relief_plane(2000, seed=5)
    amplitude, offsets = probe_offsets(normals, SIGMA, seed=6)
    cancel = threading.Event()
    calls = []

    def filter_then_cancel(points, k):
        calls.append(k)
        cancel.set()
        return pca_projection_filter(points, k)

    monkeypatch.setattr(risk, "pca_projection_filter", filter_then_cancel)
    with pytest.raises(Cancelled):
        choose_by_risk(noisy, normals, noisy, noisy + offsets, amplitude, offsets, SIGMA, cancel=cancel)
    assert calls == [risk.PLANE_NEIGHBOURS[0]] * 2


def test_the_probe_nudges_along_the_normals_by_half_a_sigma():
    normals = np.tile([0.0, 1.0, 0.0], (50000, 1))
    amplitude, offsets = probe_offsets(normals, SIGMA, seed=0)
    assert np.allclose(offsets[:, [0, 2]], 0.0)
    assert np.std(offsets[:, 1]) == pytest.approx(PROBE_SIGMAS * SIGMA, rel=0.02)
    assert np.allclose(offsets[:, 1], PROBE_SIGMAS * SIGMA * amplitude)


@pytest.mark.parametrize("name", ["sphere", "box"])
@pytest.mark.parametrize("sigma", [0.006, 0.01])
def test_quiet_noise_reads_the_noise_on_smooth_solids(name, sigma):
    """At the noise levels where the risk check runs (30K points: 0.84-0.93x)."""
    noisy, _, _ = sample_shape(name, 30000, noise=sigma, seed=5)
    est = estimate_noise(noisy, 0.05 * bbox_diagonal(noisy))
    assert 0.75 * sigma < est.quiet_sigma < 1.15 * sigma


def test_quiet_noise_reads_through_relief_that_the_median_takes_for_noise():
    """Relief at the noise's own scale over most of a surface reads as noise in most balls
    (the median); the quietest balls read the noise alone."""
    noisy, _, _ = relief_plane(30000, seed=6, relief_share=0.7)
    est = estimate_noise(noisy, 0.05 * bbox_diagonal(noisy))
    assert est.sigma > 1.1 * SIGMA
    assert abs(est.quiet_sigma - SIGMA) < 0.5 * abs(est.sigma - SIGMA)


def relief_normals(xy):
    """The true normals of `relief_plane`'s bumps at xy."""
    w = 2 * np.pi / 0.1
    hx = 1.5 * SIGMA * w * np.cos(w * xy[:, 0]) * np.sin(w * xy[:, 1])
    hy = 1.5 * SIGMA * w * np.sin(w * xy[:, 0]) * np.cos(w * xy[:, 1])
    n = np.column_stack([-hx, -hy, np.ones(len(xy))])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def test_where_a_plane_filter_placed_the_points_their_normals_follow_the_relief():
    """The plane filter keeps the bumps; a network that flattened them would say +z. The
    output's own planes follow the bumps, and each keeps the sign it was given."""
    from cljn_addon.core.evaluation.metrics import msae

    noisy, _, flat_normals = relief_plane(30000, seed=7, relief_share=1.0)
    placed = pca_projection_filter(noisy, 20)
    truth = relief_normals(placed[:, :2])
    rows = np.arange(0, len(placed), 3)
    given = flat_normals[rows].copy()
    given[::2] *= -1
    normals = flat_normals.copy()
    normals[rows] = given
    fitted = fitted_normals(placed, rows, normals, SIGMA)
    assert np.allclose(np.linalg.norm(fitted, axis=1), 1.0)
    assert np.all(np.einsum("ij,ij->i", fitted, given) > 0)
    assert msae(fitted, truth[rows]) < 0.5 * msae(given, truth[rows])


def test_where_no_filter_beats_the_input_the_region_keeps_it():
    """Rough relief (10 sigma high, finer than the points' spacing) on the left half, where each
    plane filter's fit tilts with the relief and does worse than the input (true error 1.1-4.1
    sigma^2 for k 10-80, the input's sigma^2), and a stand-in 'network' that lifts every point
    by 2 sigma: there the regions keep their input rows exactly; on the flat half a plane filter
    still wins."""
    noisy, clean, normals = relief_plane(20000, seed=11, amplitude=10 * SIGMA, wavelength=0.008)
    amplitude, offsets = probe_offsets(normals, SIGMA, seed=12)
    lifted = noisy + [0.0, 0.0, 2 * SIGMA]
    positions, choice = choose_by_risk(noisy, normals, lifted, lifted + offsets, amplitude, offsets, SIGMA)
    left, right = noisy[:, 0] < 0.4, noisy[:, 0] > 0.6
    assert np.mean(choice[left] == KEPT_INPUT) > 0.9
    kept = choice == KEPT_INPUT
    assert np.array_equal(positions[kept], noisy[kept])
    assert np.mean((choice[right] > 0) & (choice[right] < KEPT_INPUT)) > 0.9
    error = lambda p, rows: np.mean((p[rows, 2] - clean[rows, 2]) ** 2)      # noqa: E731
    assert error(positions, left) < 1.1 * error(noisy, left)
    assert error(positions, right) < 0.5 * error(noisy, right)

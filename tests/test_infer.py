"""denoise / estimate_normals behaviour with an untrained network, and bad input."""
import threading

import numpy as np
import pytest

from cljn_addon.core import Cancelled, InputError, build_model, denoise, estimate_normals
from cljn_addon.core.evaluation.shapes import sample_shape


@pytest.fixture(scope="module")
def tiny():
    import torch
    torch.manual_seed(0)
    return build_model("tiny").eval()


def test_keeps_count_order_finiteness_and_flags_isolated_points(tiny):
    noisy, _, _ = sample_shape("sphere", 3000, noise=0.01, seed=1)
    far = np.array([[5.0, 5.0, 5.0], [-5.0, 4.0, 0.0]])
    cloud = np.vstack([noisy[:1500], far[:1], noisy[1500:], far[1:]])
    res = denoise(cloud, tiny, iterations=2, device="cpu")
    assert res.points.shape == cloud.shape and res.normals.shape == cloud.shape
    assert np.isfinite(res.points).all() and np.isfinite(res.normals).all()
    assert np.allclose(np.linalg.norm(res.normals, axis=1), 1.0, atol=1e-5)
    assert np.flatnonzero(res.outliers).tolist() == [1500, len(cloud) - 1]
    assert np.array_equal(res.points[res.outliers], cloud[res.outliers])        # flagged, not moved
    moved = res.displacement[~res.outliers]
    assert moved.max() < 0.2                                                    # order kept: small moves
    assert np.allclose(res.displacement, np.linalg.norm(res.points - cloud, axis=1))


def test_normals_only_leaves_positions_bit_identical(tiny):
    noisy, _, _ = sample_shape("box", 2000, noise=0.005, seed=2)
    noisy = noisy.astype(np.float32)
    res = estimate_normals(noisy, tiny, device="cpu")
    assert np.array_equal(res.points.astype(np.float32), noisy)
    assert not res.displacement.any()


def test_seeded_runs_are_deterministic(tiny):
    noisy, _, _ = sample_shape("torus", 2000, noise=0.005, seed=3)
    a = denoise(noisy, tiny, iterations=1, seed=5)
    b = denoise(noisy, tiny, iterations=1, seed=5)
    assert np.array_equal(a.points, b.points)


def test_progress_reaches_one_and_cancel_stops(tiny):
    noisy, _, _ = sample_shape("sphere", 2000, noise=0.005, seed=4)
    seen = []
    denoise(noisy, tiny, iterations=2, progress=lambda f, m: seen.append(f))
    assert seen[-1] == 1.0 and all(b >= a for a, b in zip(seen, seen[1:]))
    cancel = threading.Event()
    cancel.set()
    with pytest.raises(Cancelled):
        denoise(noisy, tiny, cancel=cancel)


@pytest.mark.parametrize("mode", ["denoise", "normals only"])
def test_the_risk_check_reports_progress_and_can_be_cancelled(tiny, mode):
    """At low noise auto iterations (and normals-only mode, on its one pass's surface) run the
    passes again on a nudged input and choose by region (`risk.choose_by_risk`): the bar moves
    on through it, a cancel stops it, and it can be turned off. Normals only leaves every
    position bit-identical."""
    noisy, _, _ = sample_shape("sphere", 3000, noise=0.004, seed=4)
    run = ((lambda **kw: denoise(noisy, tiny, iterations="auto", **kw)) if mode == "denoise"
           else (lambda **kw: estimate_normals(noisy, tiny, **kw)))
    seen = []
    res = run(progress=lambda f, m: seen.append((f, m)))
    fractions = [f for f, _ in seen]
    assert fractions[-1] == 1.0 and all(b >= a for a, b in zip(fractions, fractions[1:]))
    assert any("plane filters" in m for _, m in seen)
    assert 0.0 <= res.plane_share <= 1.0
    assert res.noise_range is None                      # one noise over the sphere
    assert np.linalg.norm(res.points - noisy, axis=1).max() <= res.displacement_bound + 1e-9
    if mode == "normals only":
        assert np.array_equal(res.points, noisy)
    off = run(risk_check=False)
    assert off.plane_share == 0.0
    cancel = threading.Event()

    def progress(fraction, message):
        if "plane filters" in message:
            cancel.set()

    with pytest.raises(Cancelled):
        run(progress=progress, cancel=cancel)


def test_the_risk_check_gate_lets_three_passes_through_in_the_denoise_only(tiny):
    """The check runs where the noise read in the quietest balls plans up to
    `RISK_CHECK_MAX_PASSES` (3) passes when moving points, `NORMALS_RISK_CHECK_MAX_PASSES` (2)
    in normals-only mode: column_head at 1.1% (50K) gains from it in the denoise (Chamfer 8.80
    -> 7.43) and loses slightly in normals only (origin MSAE 0.5100 -> 0.5127)."""
    from cljn_addon.core.infer import (
        NORMALS_RISK_CHECK_MAX_PASSES,
        RISK_CHECK_MAX_PASSES,
        iterations_for_noise,
        padded_patches,
    )
    from cljn_addon.core.noise import estimate_noise
    from cljn_addon.core.patches import bbox_diagonal

    noisy, _, _ = sample_shape("sphere", 20000, noise=0.012, seed=4)
    radius = 0.05 * bbox_diagonal(noisy)
    assert not padded_patches(noisy, radius, tiny.config.points_per_patch)      # dense: the gate decides
    assert iterations_for_noise(estimate_noise(noisy, radius).quiet_sigma, radius) == 3
    assert NORMALS_RISK_CHECK_MAX_PASSES < 3 <= RISK_CHECK_MAX_PASSES
    denoised, normals_only = [], []
    denoise(noisy, tiny, iterations="auto", progress=lambda f, m: denoised.append(m))
    estimate_normals(noisy, tiny, progress=lambda f, m: normals_only.append(m))
    assert any("plane filters" in m for m in denoised)
    assert not any("plane filters" in m for m in normals_only)


def test_a_sparse_cloud_is_checked_against_plane_filters_at_any_noise(tiny):
    """Where a patch-radius ball holds fewer points than a patch (3K points), the denoise checks
    its passes even where the noise plans more than `RISK_CHECK_MAX_PASSES`; a dense cloud
    planning as many is not checked."""
    from cljn_addon.core.infer import RISK_CHECK_MAX_PASSES, iterations_for_noise, padded_patches
    from cljn_addon.core.noise import estimate_noise
    from cljn_addon.core.patches import bbox_diagonal

    for count, checked in ((3000, True), (20000, False)):
        noisy, _, _ = sample_shape("sphere", count, noise=0.018, seed=4)
        radius = 0.05 * bbox_diagonal(noisy)
        assert padded_patches(noisy, radius, tiny.config.points_per_patch) == checked
        assert iterations_for_noise(estimate_noise(noisy, radius).quiet_sigma, radius) > RISK_CHECK_MAX_PASSES
        messages = []
        res = denoise(noisy, tiny, iterations="auto", progress=lambda f, m: messages.append(m))
        assert any("plane filters" in m for m in messages) == checked
        if not checked:
            assert res.plane_share == 0


def test_cancel_during_the_wall_split_stops_it(tiny):
    """The split runs after the last pass (seconds per 100K points, minutes at 10M): a cancel
    set while it runs stops the run there, not after it."""
    noisy, _, _ = sample_shape("sphere", 3000, noise=0.005, seed=4)
    cancel = threading.Event()

    def progress(fraction, message):
        if message == "looking for merged thin walls":
            cancel.set()

    with pytest.raises(Cancelled):
        denoise(noisy, tiny, iterations=1, progress=progress, cancel=cancel)


@pytest.mark.parametrize("bad, message", [
    (np.zeros((0, 3)), "empty"),
    (np.zeros((10, 2)), r"\(N, 3\)"),
    ("points", r"\(N, 3\)"),
    (np.r_[np.random.default_rng(0).normal(size=(20, 3)), [[np.nan, 0, 0]]], "row 20"),
    (np.r_[np.random.default_rng(0).normal(size=(20, 3)), [[np.inf, 0, 0]]], "NaN or infinite"),
    (np.ones((50, 3)), "same position"),
    (np.zeros((2, 3)) + [[0, 0, 0], [1, 0, 0]], "at least 3"),
])
def test_bad_input_gets_a_clear_error(tiny, bad, message):
    with pytest.raises(InputError, match=message):
        denoise(bad, tiny)


def test_bad_options_get_clear_errors(tiny):
    pts = np.random.default_rng(0).normal(size=(100, 3))
    with pytest.raises(InputError, match="viewpoint"):
        denoise(pts, tiny, orientation="viewpoint")
    with pytest.raises(InputError, match="iterations"):
        denoise(pts, tiny, iterations=0)
    with pytest.raises(InputError, match="patch radius"):
        denoise(pts, tiny, patch_radius=-1.0)
    with pytest.raises(InputError, match="unknown device"):
        denoise(pts, tiny, device="tpu")


@pytest.mark.parametrize("kind", ["collinear", "planar", "fewer_than_patch"])
def test_degenerate_clouds_give_a_defined_result(tiny, kind):
    rng = np.random.default_rng(1)
    if kind == "collinear":
        pts = np.c_[rng.uniform(0, 1, 300), np.zeros(300), np.zeros(300)]
    elif kind == "planar":
        pts = np.c_[rng.uniform(0, 1, (300, 2)), np.zeros(300)]
    else:
        pts = rng.normal(scale=0.01, size=(10, 3))          # fewer points than a patch holds
        with pytest.raises(InputError, match="enough neighbours"):
            denoise(pts, tiny)                                # 5% of the diagonal is too small
    res = denoise(pts, tiny, iterations=1, patch_radius=0.05 if kind == "fewer_than_patch" else None)
    assert res.points.shape == pts.shape
    assert np.isfinite(res.points).all()
    assert np.allclose(np.linalg.norm(res.normals, axis=1), 1.0, atol=1e-5)
    if kind == "planar":
        assert np.abs(res.points[:, 2]).max() < 1e-3              # stays in its plane


def test_all_points_isolated_is_refused(tiny):
    pts = np.eye(3) * 100
    pts = np.r_[pts, [[0, 0, 0]]]
    with pytest.raises(InputError, match="enough neighbours"):
        denoise(pts, tiny, patch_radius=1.0)


def test_auto_iterations_report_how_many_ran(tiny):
    noisy, _, _ = sample_shape("sphere", 3000, noise=0.01, seed=1)
    # Without the risk check that may follow the passes (a cloud this sparse always gets it).
    res = denoise(noisy, tiny, iterations="auto", device="cpu", risk_check=False)
    assert 1 <= res.iterations <= 4
    again = denoise(noisy, tiny, iterations=res.iterations, device="cpu")
    # The same passes as a fixed run with as many iterations.
    assert np.array_equal(res.points, again.points)


def test_auto_iterations_stop_when_the_cloud_has_moved_by_the_noise(tiny, monkeypatch):
    """The discrepancy stop: the pass whose RMS move from the input passes STOP_MOVE_SIGMAS x
    the surface noise estimate is dropped, and what is returned is a fixed run of the passes kept.
    The risk check that may follow the passes (this sphere's quiet balls plan 3) is off here."""
    from cljn_addon.core import infer

    noisy, _, _ = sample_shape("sphere", 3000, noise=0.02, seed=1)
    monkeypatch.setattr(infer, "STOP_MOVE_SIGMAS", float("inf"))
    unstopped = denoise(noisy, tiny, iterations="auto", device="cpu", risk_check=False)
    assert unstopped.iterations > 1 and not unstopped.stopped_early
    monkeypatch.setattr(infer, "STOP_MOVE_SIGMAS", 1e-9)       # any second pass moves too far
    stopped = denoise(noisy, tiny, iterations="auto", device="cpu", risk_check=False)
    assert stopped.iterations == 1 and stopped.stopped_early
    assert np.array_equal(stopped.points, denoise(noisy, tiny, iterations=1, device="cpu").points)
    # A fixed count is never cut short.
    assert denoise(noisy, tiny, iterations=2, device="cpu").iterations == 2


def test_on_iteration_sees_every_pass_and_the_last_is_the_result(tiny):
    noisy, _, _ = sample_shape("sphere", 3000, noise=0.01, seed=1)
    seen = []
    res = denoise(noisy, tiny, iterations=3, device="cpu", on_iteration=lambda i, pts: seen.append((i, pts)))
    assert [i for i, _ in seen] == [1, 2, 3]
    assert np.array_equal(seen[-1][1], res.points)
    assert not np.array_equal(seen[0][1], seen[1][1])


def test_steps_taken_name_each_extra_step_once_and_nothing_when_none_ran():
    """The wording the command line and the extension both report (one implementation)."""
    from cljn_addon.core.infer import DenoiseResult

    empty = np.zeros((0, 3))
    plain = DenoiseResult(points=empty, normals=empty, outliers=np.zeros(0, bool),
                          displacement=np.zeros(0), seconds=0.0, iterations=1)
    assert plain.steps_taken() == []
    busy = DenoiseResult(points=empty, normals=empty, outliers=np.zeros(0, bool), displacement=np.zeros(0),
                         seconds=0.0, iterations=3, thin_walled=True, split_share=0.012, rod_share=0.25,
                         rim_share=0.031, plane_share=0.5, kept_share=0.125, noise_range=(0.00125, 0.0114),
                         scene_radius=2.75)
    steps = busy.steps_taken()
    assert len(steps) == 8
    assert steps[0].startswith("read as a scene: patches of radius 2.75")
    assert steps[1] == "noise varies across the cloud (0.00125-0.0114): each point at its own"
    assert steps[2].startswith("thin-walled")
    assert "1.2% on merged thin walls" in steps[3]
    assert "25.0% on rods" in steps[4]
    assert "3.1% beyond thin parts' edges" in steps[5]
    assert "50.0% by a plane filter" in steps[6]
    assert "12.5% left as they were" in steps[7]
    checked = DenoiseResult(points=empty, normals=empty, outliers=np.zeros(0, bool), displacement=np.zeros(0),
                            seconds=0.0, iterations=1, thin_walled=True, solid_share=0.625)
    assert checked.steps_taken()[0].startswith("read as thin-walled") and "62.5% whole-ball passes" in checked.steps_taken()[0]


@pytest.mark.parametrize("mixed_precision", [True, False])
def test_the_cpu_runs_the_network_a_cache_s_worth_of_patches_at_a_time(tiny, monkeypatch, mixed_precision):
    import torch

    from cljn_addon.core import infer
    from cljn_addon.core import model as model_module
    from cljn_addon.core.device import autocast

    calls = []
    build_net = model_module.inference_net

    def counting_net(model):
        net = build_net(model)

        def run(patches):
            calls.append(len(patches))
            return net(patches)
        return run
    monkeypatch.setattr(model_module, "inference_net", counting_net)
    predict, _, _ = infer.predictor(tiny, "cpu", mixed_precision=mixed_precision)
    step = infer.CPU_NETWORK_ROWS // tiny.config.points_per_patch
    patches = np.random.default_rng(0).normal(scale=0.3, size=(2 * step + 5, tiny.config.points_per_patch, 3))
    displacement, normals = predict(patches.astype(np.float32))
    assert calls == [step, step, 5]
    # The same outputs, in the same order, as one call on the whole batch.
    with torch.inference_mode(), autocast(torch.device("cpu"), enabled=mixed_precision):
        whole = build_net(tiny)(torch.from_numpy(patches.astype(np.float32)))
    tolerance = 1e-2 if mixed_precision else 1e-5
    np.testing.assert_allclose(displacement, whole[0].float().numpy(), atol=tolerance)
    np.testing.assert_allclose(normals, whole[1].float().numpy(), atol=tolerance)

"""Noise estimation and the displacement bound that keeps a wrong prediction from wrecking a scan."""
import numpy as np
import pytest
import torch

from cljn_addon.core import InputError, build_model, denoise, estimate_normals
from cljn_addon.core.evaluation.shapes import sample_shape, sample_shape_varying_noise
from cljn_addon.core.noise import (
    DISPLACEMENT_BOUND_SIGMAS,
    THIN_WALLED_SHARE,
    clamp_displacement,
    estimate_noise,
    estimate_noise_sigma,
    local_noise,
    surface_noise_sigma,
    varying_local_noise,
)
from cljn_addon.core.patches import bbox_diagonal


@pytest.mark.parametrize("name", ["sphere", "box", "torus"])
@pytest.mark.parametrize("sigma", [0.005, 0.01, 0.02])
def test_noise_estimate_is_close_to_the_true_sigma(name, sigma):
    noisy, _, _ = sample_shape(name, 30000, noise=sigma, seed=3)
    est = estimate_noise_sigma(noisy, 0.05 * bbox_diagonal(noisy))
    assert 0.75 * sigma < est < 1.3 * sigma


@pytest.mark.parametrize("name", ["sphere", "cylinder"])
@pytest.mark.parametrize("count", [5000, 10000])
def test_noise_estimate_holds_on_sparse_clouds(name, count):
    """Where a 5% ball holds fewer points than a fit draws, the ball widens to hold that many
    distinct points: padded with repeats it read 0.86x sigma (quiet balls 0.63x) on a 10K
    sphere, and the risk check then chose the weakest plane filter everywhere."""
    noisy, _, _ = sample_shape(name, count, noise=0.01, seed=1)
    est = estimate_noise(noisy, 0.05 * bbox_diagonal(noisy))
    assert 0.009 < est.sigma < 0.012
    assert 0.009 < est.quiet_sigma < 0.012


def test_noise_estimate_is_in_cloud_units_and_ignores_where_the_cloud_is():
    noisy, _, _ = sample_shape("box", 20000, noise=0.01, seed=4)
    base = estimate_noise_sigma(noisy, 0.05 * bbox_diagonal(noisy))
    # A georeferenced scan in metres: 40 m across, half a million metres from the origin.
    far = noisy * 40.0 + np.array([512_345.0, 5_401_234.0, 312.0])
    moved = estimate_noise_sigma(far, 0.05 * bbox_diagonal(far))
    assert np.isclose(moved, 40.0 * base, rtol=1e-3)


def test_clean_cloud_has_almost_no_noise():
    _, clean, _ = sample_shape("box", 20000, seed=5)
    assert estimate_noise_sigma(clean, 0.05) < 1e-4


def test_clamp_keeps_direction_and_caps_length():
    original = np.zeros((3, 3))
    moved = np.array([[0.1, 0, 0], [0, 3.0, 4.0], [0, 0, -0.5]])
    out = clamp_displacement(moved, original, 1.0)
    assert np.allclose(out[0], moved[0])
    assert np.allclose(out[1], [0, 0.6, 0.8])
    assert np.allclose(out[2], [0, 0, -0.5])


def test_clamp_takes_a_bound_per_point():
    original = np.zeros((2, 3))
    moved = np.array([[0, 3.0, 4.0], [0, 3.0, 4.0]])
    out = clamp_displacement(moved, original, np.array([1.0, 10.0]))
    assert np.allclose(out, [[0, 0.6, 0.8], [0, 3.0, 4.0]])


def test_local_noise_follows_noise_that_grows_across_the_cloud():
    """A sphere whose noise grows from 0.2% to 2% along x: each end's local reading is within
    20% of its own noise (the cloud's one estimate is ~1%), and the cloud reads as varying."""
    noisy, _, sigma = sample_shape_varying_noise("sphere", 30000, 0.002, 0.02, seed=3)
    radius = 0.05 * bbox_diagonal(noisy)
    estimate = estimate_noise(noisy, radius)
    read = local_noise(noisy, estimate)
    assert read.varies() and varying_local_noise(noisy, radius, estimate) is not None
    x = noisy[:, 0]
    for end in (x < np.quantile(x, 0.1), x > np.quantile(x, 0.9)):
        assert np.median(read.sigma[end]) == pytest.approx(np.median(sigma[end]), rel=0.2)


@pytest.mark.parametrize("name, noise", [("sphere", 0.006), ("star", 0.006), ("gear", 0.011), ("stepped_block", 0.02)])
def test_a_cloud_of_one_noise_does_not_read_as_varying(name, noise):
    noisy, _, _ = sample_shape(name, 30000, noise=noise, seed=2)
    radius = 0.05 * bbox_diagonal(noisy)
    assert varying_local_noise(noisy, radius, estimate_noise(noisy, radius)) is None


def test_a_gentle_gradient_reads_as_varying():
    """A sphere whose noise grows only from 0.3% to 0.9% along x: both readings see it."""
    noisy, _, _ = sample_shape_varying_noise("sphere", 20000, 0.003, 0.009, seed=3)
    radius = 0.05 * bbox_diagonal(noisy)
    assert varying_local_noise(noisy, radius, estimate_noise(noisy, radius)) is not None


@pytest.mark.parametrize("name", ["gear", "column_head"])
def test_relief_the_balls_read_as_varying_noise_is_told_apart_along_the_surface(name, request):
    """Clouds of one noise whose noise balls read it as varying: a gear at 5K points and 1.5%
    (its teeth's edges fill most balls), column_head at 20K and 0.6% (carving uneven over it)."""
    if name == "gear":
        noisy = sample_shape("gear", 5000, noise=0.015, seed=3)[0]
    else:
        noisy = request.getfixturevalue("column_head_relief")[4]
    radius = 0.05 * bbox_diagonal(noisy)
    estimate = estimate_noise(noisy, radius)
    assert local_noise(noisy, estimate).varies()           # the balls alone would take it
    assert varying_local_noise(noisy, radius, estimate) is None


def test_denoise_never_moves_a_point_beyond_the_bound():
    torch.manual_seed(0)
    noisy, _, _ = sample_shape("stepped_block", 6000, noise=0.01, seed=6)
    model = build_model("tiny").eval()          # untrained: its displacements are arbitrary
    res = denoise(noisy, model, iterations=3)
    assert 0.005 < res.noise_sigma < 0.02
    assert np.isclose(res.displacement_bound, DISPLACEMENT_BOUND_SIGMAS * res.noise_sigma)
    assert res.displacement.max() <= res.displacement_bound * (1 + 1e-9)
    tight = denoise(noisy, model, iterations=3, max_displacement=0.001)
    assert tight.displacement.max() <= 0.001 * (1 + 1e-9)
    free = denoise(noisy, model, iterations=3, max_displacement=float("inf"))
    assert free.displacement.max() > tight.displacement.max()


def test_a_given_scanner_noise_replaces_the_estimate():
    """--noise / Known Scanner Noise: the pass count, the stop, the motion bound and the
    refinement's reach follow the given sigma, not the cloud's estimate."""
    torch.manual_seed(0)
    noisy, _, _ = sample_shape("stepped_block", 6000, noise=0.01, seed=6)
    model = build_model("tiny").eval()
    estimated = denoise(noisy, model, iterations=2)
    assert 0.005 < estimated.noise_sigma < 0.02
    given = denoise(noisy, model, iterations=2, noise_sigma=0.002)
    assert given.noise_sigma == 0.002
    assert np.isclose(given.displacement_bound, DISPLACEMENT_BOUND_SIGMAS * 0.002)
    assert given.displacement.max() <= given.displacement_bound * (1 + 1e-9)
    assert estimated.displacement.max() > given.displacement_bound     # the estimate would allow more
    # auto plans passes from sigma / patch radius: 1 pass at a tiny given noise, the paper's 4 at a large one
    assert denoise(noisy, model, iterations="auto", noise_sigma=0.001).iterations == 1
    loud = denoise(noisy, model, iterations="auto", noise_sigma=0.05)
    assert loud.iterations == 4 and not loud.stopped_early      # the stop is 1.15 x 0.05: never reached here


@pytest.mark.parametrize("value", [0.0, -0.01, float("nan"), float("inf"), "loud"])
def test_a_bad_scanner_noise_is_refused(value):
    from cljn_addon.core.options import DenoiseOptions

    noisy, _, _ = sample_shape("box", 500, noise=0.01, seed=6)
    with pytest.raises(InputError, match="noise sigma must be a positive number"):
        denoise(noisy, build_model("tiny").eval(), noise_sigma=value)
    with pytest.raises(InputError, match="scanner noise must be a positive distance"):
        DenoiseOptions(noise_sigma=value)


def test_scanner_noise_reaches_the_engine_in_both_modes():
    """Moving points: the pass count, the stop, the bound; normals only: the posterior's reach."""
    from cljn_addon.core.options import DenoiseOptions

    assert DenoiseOptions(noise_sigma=0.003).engine_kwargs()["noise_sigma"] == 0.003
    assert "noise_sigma" not in DenoiseOptions().engine_kwargs()
    assert DenoiseOptions(noise_sigma=0.003, normals_only=True).engine_kwargs()["noise_sigma"] == 0.003


def test_bad_displacement_bound_is_refused():
    noisy, _, _ = sample_shape("box", 500, noise=0.01, seed=6)
    with pytest.raises(InputError, match="max displacement"):
        denoise(noisy, build_model("tiny").eval(), max_displacement=-1.0)


@pytest.mark.parametrize("sigma", [0.005, 0.008, 0.015])
def test_noise_estimate_sees_through_a_coarse_storage_grid(sigma):
    """A LAS-like cloud at 1 cm: ties made the median residual 0 (sigma^ ~ 1e-10 on a real LAZ)."""
    from cljn_addon.core.noise import coordinate_quantum

    rng = np.random.default_rng(1)
    plane = np.c_[rng.uniform(-1, 1, (30000, 2)), rng.normal(0, sigma, 30000)]
    stored = np.round(plane / 0.01) * 0.01 + [500.0, 200.0, 0.0]
    assert coordinate_quantum(plane) is None
    assert np.allclose(coordinate_quantum(stored), 0.01)
    est = estimate_noise_sigma(stored, 0.05 * bbox_diagonal(stored))
    assert 0.7 * sigma < est < 1.25 * sigma, (sigma, est)


@pytest.mark.parametrize("name", ["thin_plate", "thin_tube", "stool"])
def test_noise_of_a_thin_walled_object_is_not_read_from_its_thickness(name):
    """Walls ~2.5 sigma thick: the one-sheet fit read the thickness as noise (1.8x, 1.8x and
    2.6x the true sigma); the two-sheet fit finds the noise, and the object as thin-walled."""
    noisy, _, _ = sample_shape(name, 20000, noise=0.006, seed=1)
    est = estimate_noise(noisy, 0.05)
    assert 0.85 < est.sigma / 0.006 < 1.2
    assert est.two_sheet_share >= THIN_WALLED_SHARE


@pytest.mark.parametrize("name", ["sphere", "box", "cylinder", "stepped_block", "octahedron", "gear"])
@pytest.mark.parametrize("noise", [0.006, 0.02])
def test_solids_with_creases_are_not_thin_walled(name, noise):
    """A crease can fit two sheets in one ball; on a solid such balls stay a minority, so its
    noise estimate and its denoising are what they were."""
    noisy, _, _ = sample_shape(name, 20000, noise=noise, seed=1)
    assert estimate_noise(noisy, 0.05).two_sheet_share < THIN_WALLED_SHARE


def test_thin_walled_handling_is_reported_and_can_be_turned_off():
    noisy, _, _ = sample_shape("thin_plate", 8000, noise=0.006, seed=1)
    model = build_model("tiny").eval()
    auto = denoise(noisy, model, iterations="auto")
    assert auto.thin_walled and auto.iterations == 1
    off = denoise(noisy, model, iterations="auto", own_sheet=False)
    assert not off.thin_walled
    solid, _, _ = sample_shape("box", 8000, noise=0.006, seed=1)
    assert not denoise(solid, model, iterations="auto").thin_walled
    forced = denoise(solid, model, iterations="auto", own_sheet=True)
    assert forced.thin_walled and forced.iterations == 1 and forced.solid_share == 0.0   # forced: not checked


def test_a_thin_walled_reading_is_checked_region_by_region_against_a_solids_passes(monkeypatch):
    """Read as thin-walled with auto iterations: each region keeps the own-sheet pass or a
    solid's passes by their risk (`infer.own_sheet_or_solid`); where the own-sheet result is
    made far worse than the solid's, the solid's is taken there."""
    from cljn_addon.core import infer
    from cljn_addon.core.infer import own_sheet_or_solid

    noisy, _, truth = sample_shape("thin_plate", 8000, noise=0.006, seed=1)
    model = build_model("tiny").eval()
    auto = denoise(noisy, model, iterations="auto")
    unchecked = denoise(noisy, model, iterations="auto", risk_check=False)
    assert auto.thin_walled and unchecked.thin_walled and unchecked.solid_share == 0.0
    assert 0.0 <= auto.solid_share <= 1.0
    assert (auto.solid_share > 0) == any("whole-ball passes" in step for step in auto.steps_taken())
    # Own-sheet positions pushed 4 sigma off along the normal on one half of the plate: the
    # solid's passes must win that half (each region's risk is averaged over 1,024 points).
    sigma = 0.006
    own = noisy.copy()
    half = noisy[:, 0] > np.median(noisy[:, 0])
    own[half] += 4 * sigma * truth[half]
    _, _, solid, _ = own_sheet_or_solid(noisy, model, own, truth.astype(np.float64), sigma, 3 * sigma)
    assert solid[half].mean() > 0.9
    # Only where the noise plans at most `RISK_CHECK_MAX_PASSES` passes (1 here): below that,
    # the cloud runs as it did unchecked.
    monkeypatch.setattr(infer, "RISK_CHECK_MAX_PASSES", 0)
    gated = denoise(noisy, model, iterations="auto")
    assert gated.thin_walled and gated.solid_share == 0.0
    assert np.allclose(gated.points, unchecked.points)


def test_solid_option_turns_the_thin_walled_handling_off():
    """Solid Object / --solid: a sculpt whose relief reads as two sheets (dino at 0.6%: Chamfer
    1.751 handled as thin-walled, 1.369 as a solid) can be run as a solid."""
    from cljn_addon.core.options import DenoiseOptions

    assert DenoiseOptions(solid=True).engine_kwargs()["own_sheet"] is False
    assert "own_sheet" not in DenoiseOptions().engine_kwargs()
    assert "own_sheet" not in DenoiseOptions(solid=True, normals_only=True).engine_kwargs()
    noisy, _, _ = sample_shape("thin_plate", 8000, noise=0.006, seed=1)
    model = build_model("tiny").eval()
    auto = DenoiseOptions(iterations=1).run(noisy, model)
    solid = DenoiseOptions(iterations=1, solid=True).run(noisy, model)
    assert auto.thin_walled and not solid.thin_walled
    assert any("--solid" in step for step in auto.steps_taken())
    assert not any("thin-walled" in step for step in solid.steps_taken())
    assert not np.allclose(auto.points, solid.points)


@pytest.mark.parametrize("name", ["sphere", "box", "torus"])
@pytest.mark.parametrize("sigma", [0.005, 0.01, 0.02])
def test_surface_noise_estimate_is_close_to_the_true_sigma(name, sigma):
    noisy, _, _ = sample_shape(name, 30000, noise=sigma, seed=3)
    radius = 0.05 * bbox_diagonal(noisy)
    est = surface_noise_sigma(noisy, radius, estimate_noise_sigma(noisy, radius))
    assert 0.85 * sigma < est < 1.12 * sigma


def test_surface_noise_estimate_reads_sharp_detail_closer_than_the_ball_fit():
    """A star prism's tips and edges fill most balls of the patch radius, not most
    neighbourhoods of a dozen points."""
    noisy, _, _ = sample_shape("star_prism", 20000, noise=0.006, seed=2)
    radius = 0.05 * bbox_diagonal(noisy)
    ball = estimate_noise_sigma(noisy, radius)
    surface = surface_noise_sigma(noisy, radius, ball)
    assert surface < 0.92 * ball
    assert 0.85 * 0.006 < surface < 1.3 * 0.006


def test_surface_noise_estimate_is_in_cloud_units_and_thins_dense_clouds():
    noisy, _, _ = sample_shape("sphere", 200_000, noise=0.01, seed=4)
    far = noisy * 40.0 + np.array([512_345.0, 5_401_234.0, 312.0])
    radius = 0.05 * bbox_diagonal(far)
    est = surface_noise_sigma(far, radius, estimate_noise_sigma(far, radius))
    assert 0.85 * 0.4 < est < 1.12 * 0.4
    assert np.isnan(surface_noise_sigma(noisy[:20], 0.05, 0.01))


def test_normals_only_reads_the_noise_in_the_quietest_balls():
    """The star prism's tips and edges read as noise in the whole-cloud estimate (1.4x the truth
    at 0.6%); normals only takes the quiet balls' sigma (1.09x) as the reach of its posterior,
    which blends faces less (origin MSAE on the validation meshes 0.1298 -> 0.1283 at 0.6%)."""
    torch.manual_seed(0)
    noisy, _, _ = sample_shape("star_prism", 20000, noise=0.006, seed=3)
    model = build_model("tiny").eval()
    est = estimate_noise(noisy - noisy.mean(axis=0), 0.05 * bbox_diagonal(noisy))
    whole, quiet = est.sigma, est.quiet_sigma
    res = estimate_normals(noisy, model, risk_check=False)
    assert whole > 1.3 * 0.006
    assert res.noise_sigma == pytest.approx(quiet, rel=0.05)
    assert 0.85 * 0.006 < res.noise_sigma < 1.2 * 0.006


def test_a_scene_reads_its_noise_in_balls_of_a_patchs_points(monkeypatch):
    """300 m of street, 40K points, 2 cm of noise: a ball of 5% of the diagonal (15 m) holds
    buildings, cars and poles, and read them as 1.75 m of noise, which set the bound. In balls
    of 256 points (4.7 m: their structure still reads as 8.7 cm) the quietest balls read 2.2 cm."""
    import cljn_addon.core.noise as noise
    from cljn_addon.core.evaluation.shapes import city_street, sample_noisy

    _, _, _, noisy = sample_noisy(*city_street(300.0, 10.0), 40_000, 0.02, seed=3)
    radius = 0.05 * bbox_diagonal(noisy)
    est = estimate_noise(noisy, radius, seed=0)
    assert est.scene_radius < radius / noise.SCENE_SPAN
    assert 0.015 < est.sigma < 0.03 and est.sigma == est.quiet_sigma
    monkeypatch.setattr(noise, "SCENE_RATIO", np.inf)
    whole = estimate_noise(noisy, radius, seed=0)
    assert np.isnan(whole.scene_radius) and whole.sigma > 10 * est.sigma


def test_a_dense_object_is_not_read_as_a_scene(monkeypatch):
    """250K points on a sphere: its 5% ball spans over twice the 256-point ball, so the small
    balls are read too, but they read what the patch-radius balls read: the estimate stands."""
    import cljn_addon.core.noise as noise

    noisy, _, _ = sample_shape("sphere", 250_000, noise=0.01, seed=1)
    calls = []
    monkeypatch.setattr(noise, "_estimate", lambda *a, _f=noise._estimate: calls.append(a[1]) or _f(*a))
    est = estimate_noise(noisy, 0.05, seed=0)
    assert len(calls) == 2 and calls[1] < 0.05 / noise.SCENE_SPAN      # the small balls were read
    monkeypatch.setattr(noise, "SCENE_SPAN", np.inf)
    unchecked = estimate_noise(noisy, 0.05, seed=0)
    assert np.isnan(est.scene_radius) and est.sigma == unchecked.sigma and 0.9 < est.sigma / 0.01 < 1.15


def test_a_dense_object_whose_small_balls_read_the_noise_low_is_not_a_scene(monkeypatch):
    """200K points on a star prism at 2%: its 256-point balls are ~1.1 sigma wide, where the
    quadric follows the noise (0.43x sigma read, under half the patch balls' 1.1x). Read as a
    scene it kept 0.3x its noise and patches a sigma wide; a scene's small balls are tens of
    their sigmas wide (`SCENE_BALL_SIGMAS`), so the patch balls' reading stands."""
    import cljn_addon.core.noise as noise

    noisy, _, _ = sample_shape("star_prism", 200_000, noise=0.02, seed=0)
    radius = 0.05 * bbox_diagonal(noisy)
    est = estimate_noise(noisy, radius, seed=0)
    assert np.isnan(est.scene_radius) and 0.9 < est.sigma / 0.02 < 1.25
    monkeypatch.setattr(noise, "SCENE_BALL_SIGMAS", 0.0)
    unchecked = estimate_noise(noisy, radius, seed=0)
    assert unchecked.scene_radius < 2.0 * 0.02 and unchecked.sigma < 0.5 * 0.02

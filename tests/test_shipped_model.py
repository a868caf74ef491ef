"""The shipped default model: loads, matches its config, filters, and holds its accuracy.

Guards what the shipped model measurably does today (see MODEL_CARD.md): it removes most of
the noise and its normals are within 10% of PCA normals tuned per shape with an oracle.
Beating tuned PCA outright is the open target of the training issue.
"""

import numpy as np
import pytest

from cljn_addon.core import denoise, estimate_normals, load_model
from cljn_addon.core.evaluation.baselines import pca_normals, pca_projection_filter
from cljn_addon.core.evaluation.metrics import MeshDistance, chamfer, msae, sign_agreement
from cljn_addon.core.evaluation.shapes import sample_shape, sample_shape_varying_noise, shape_mesh
from cljn_addon.core.model import DEFAULT_WEIGHTS, config_path_for
from cljn_addon.core.noise import DISPLACEMENT_BOUND_SIGMAS


@pytest.fixture(scope="module")
def shipped():
    assert DEFAULT_WEIGHTS.exists(), f"the default model must ship at {DEFAULT_WEIGHTS}"
    return load_model()


def test_shipped_weights_match_their_config(shipped):
    assert config_path_for(DEFAULT_WEIGHTS).exists()
    assert (DEFAULT_WEIGHTS.parent / "MODEL_CARD.md").exists()
    assert DEFAULT_WEIGHTS.stat().st_size < 20 * 2 ** 20
    assert shipped.config.preset == "small"


@pytest.mark.parametrize("name, max_ratio", [("octahedron", 0.4), ("torus", 0.4), ("stepped_block", 0.7)])
def test_shipped_model_filters_and_keeps_normal_accuracy(shipped, name, max_ratio):
    noisy, clean, truth = sample_shape(name, 12000, noise=0.01, seed=11)
    res = denoise(noisy, shipped, iterations=4)
    assert chamfer(res.points, clean) < max_ratio * chamfer(noisy, clean)
    best_pca = min(msae(pca_normals(noisy, k), truth) for k in (20, 40, 60, 100))
    assert msae(res.normals, truth) < 1.1 * best_pca
    assert sign_agreement(res.normals, truth) > 0.99


def test_shipped_model_beats_pca_normals_and_the_classic_filter_on_a_cad_shape(shipped):
    noisy, clean, truth = sample_shape("octahedron", 12000, noise=0.01, seed=11)
    res = denoise(noisy, shipped, iterations=4)
    best_pca = min(msae(pca_normals(noisy, k), truth) for k in (20, 40, 60, 100))
    best_filter = min(chamfer(pca_projection_filter(noisy, k), clean) for k in (20, 40, 60, 100))
    assert msae(res.normals, truth) < best_pca
    assert chamfer(res.points, clean) < best_filter


def _plate(noise):
    from cljn_addon.core.evaluation.metrics import MeshDistance
    from cljn_addon.core.evaluation.shapes import shape_mesh

    noisy, clean, truth = sample_shape("thin_plate", 20000, noise=noise, seed=1)
    return noisy, clean, truth, MeshDistance(*shape_mesh("thin_plate"))


def test_thin_plate_faces_stay_apart_and_come_out_less_noisy_at_low_noise(shipped):
    noisy, clean, truth, dist = _plate(0.0025)          # the plate is ~6 sigma thick
    res = denoise(noisy, shipped, iterations="auto")
    assert chamfer(res.points, clean) < 0.8 * chamfer(noisy, clean)
    assert dist.distance(res.points).mean() < 0.8 * dist.distance(noisy).mean()
    top = truth[:, 2] > 0.9
    # The top face's points stay near the top face (half-thickness 0.0074), not the midplane.
    assert np.mean(res.points[top, 2]) > 0.6 * np.mean(clean[top, 2])


def test_thin_plate_is_never_worse_than_the_input_at_0_6_percent(shipped):
    """~2.5 sigma thick: found thin-walled, own-sheet patches and 2.5-sigma refinement keep the
    faces apart (before: Chamfer 11.1 against 6.5 for the input, faces pulled together)."""
    noisy, clean, truth, dist = _plate(0.006)
    res = denoise(noisy, shipped, iterations="auto")
    assert res.thin_walled
    assert chamfer(res.points, clean) < 0.9 * chamfer(noisy, clean)
    assert dist.distance(res.points).mean() < dist.distance(noisy).mean()
    top = truth[:, 2] > 0.9
    # The faces come out partly drawn together (top face at 0.53 of its height; a full
    # collapse onto the midplane gives ~0), but apart.
    assert np.mean(res.points[top, 2]) > 0.4 * np.mean(clean[top, 2])


def test_a_sculpt_read_as_thin_walled_takes_a_solids_passes_where_they_do_better(shipped):
    """dino (a training mesh) at 0.6%: its limbs and relief fill balls with two sheets, so it
    reads thin-walled; the check against a solid's passes must take them on most of it (at 50K
    points Chamfer x 1e5 1.74 -> 1.39; at this test's 20K 2.66 -> 2.56)."""
    from cljn_addon.cli.paths import DEFAULT_TRAIN_DIR
    from cljn_addon.core.evaluation.evaluate import prepare_shape
    from cljn_addon.core.formats.meshes import read_mesh

    path = DEFAULT_TRAIN_DIR / "dino.off"
    if not path.exists():
        pytest.skip(f"{path} is not here")
    _, _, clean, _ = prepare_shape(*read_mesh(path), 20000, 103)
    noisy = clean + np.random.default_rng(10).normal(scale=0.006, size=clean.shape)
    checked = denoise(noisy, shipped, iterations="auto", orientation="none")
    unchecked = denoise(noisy, shipped, iterations="auto", orientation="none", risk_check=False)
    assert checked.thin_walled and checked.solid_share > 0.5
    assert chamfer(checked.points, clean) < 0.98 * chamfer(unchecked.points, clean)


def test_thin_plate_thinner_than_two_sigma_comes_out_on_its_faces(shipped):
    """1.84 sigma thick (0.8%): no patch tells the faces apart and the network merges them into
    one sheet, further from both than the input (Chamfer 11.2 against 8.6); the split of merged
    walls (sheets.split_merged_walls) puts each point back on its own face (3.5), and its sign
    is the Bayes guess (ceiling Phi(0.92) = 82%)."""
    noisy, clean, truth, dist = _plate(0.008)
    res = denoise(noisy, shipped, iterations="auto")
    assert res.split_share > 0.8
    assert chamfer(res.points, clean) < 0.6 * chamfer(noisy, clean)
    assert dist.distance(res.points).mean() < 0.5 * dist.distance(noisy).mean()
    top = truth[:, 2] > 0.9
    assert np.mean(res.points[top, 2]) > 0.6 * np.mean(clean[top, 2])
    assert sign_agreement(res.normals, truth) > 0.75
    merged = denoise(noisy, shipped, iterations="auto", split_walls=False)
    assert merged.split_share == 0
    assert chamfer(merged.points, clean) > chamfer(noisy, clean)


def test_thin_plate_1_4_sigma_thick_is_split_by_the_whole_cloud_test(shipped):
    """1.1% noise: the faces are 1.36 sigma apart, kurtosis ~2.85; only the whole-cloud pool
    finds them (before: no split, Chamfer 11.3 against 12.4 for the input and 6.7 for the
    best plane filter)."""
    noisy, clean, truth, dist = _plate(0.011)
    res = denoise(noisy, shipped, iterations="auto")
    assert res.split_share > 0.9
    best_filter = min(chamfer(pca_projection_filter(noisy, k), clean) for k in (20, 40, 60, 100))
    assert chamfer(res.points, clean) < 0.8 * best_filter
    assert dist.distance(res.points).mean() < 0.4 * dist.distance(noisy).mean()
    top = truth[:, 2] > 0.9
    # Sides are the Bayes guess (Phi(0.68) = 75% right): the top face's mean is ~half its height.
    assert np.mean(res.points[top, 2]) > 0.35 * np.mean(clean[top, 2])


def test_walls_kept_apart_at_2_percent_are_not_split_and_merged_ones_are(shipped):
    """50K points at 2% noise. The gear (4.2 sigma thick) comes out with its faces apart, but
    the noise tails that crossed its middle flatten the heights (whole-cloud kurtosis 2.91):
    before the other face was looked for along the normal, 82% of it was split, Chamfer 6.3
    -> 14.7. The L-bracket's walls merge (29.6, input 29.8) and are split (7.9 with the wider
    merged sheet, 8.8 with 64 outputs; before the other face was looked for, not found)."""
    noisy, clean, _ = sample_shape("gear", 50000, noise=0.02, seed=1)
    res = denoise(noisy, shipped, iterations="auto")
    assert res.split_share == 0
    assert chamfer(res.points, clean) < 0.2 * chamfer(noisy, clean)             # 6.3 vs 38.6
    # Issue #12's sharp-toothed orientation shape: no flipped patch in the output's shading
    # (sign against the surface nearest each output point; the eval's "sign output").
    _, facing = MeshDistance(*shape_mesh("gear")).nearest(res.points)
    assert sign_agreement(res.normals, facing) >= 0.99
    noisy, clean, _ = sample_shape("l_bracket", 50000, noise=0.02, seed=1)
    res = denoise(noisy, shipped, iterations="auto")
    assert res.split_share > 0.6
    best_filter = min(chamfer(pca_projection_filter(noisy, k), clean) for k in (40, 60, 100, 150))
    assert chamfer(res.points, clean) < 1.1 * best_filter                        # 7.9 vs 7.9 (64-point sheet: 8.8)


def test_a_merged_seat_is_found_where_the_output_ripples(shipped):
    """The stool at 1.5% and 50K points: its seat (1.5 sigma thick) merges, but the merged
    sheet of a point's 64 nearest outputs follows the output's ripples, and the seat's two
    faces did not show (not split, Chamfer 8.5). The wider sheet (sheets.SHEET_SCALES) finds
    them: split ~50%, 4.9, below the best plane filter (5.6)."""
    noisy, clean, _ = sample_shape("stool", 50000, noise=0.015, seed=1)
    res = denoise(noisy, shipped, iterations="auto")
    assert res.split_share > 0.3
    best_filter = min(chamfer(pca_projection_filter(noisy, k), clean) for k in (40, 60, 100, 150))
    assert chamfer(res.points, clean) < best_filter                              # 4.9 vs 5.6


def test_stool_seat_and_legs_come_out_cleaner_at_0_6_percent(shipped):
    """Thin seat, thin legs (before: Chamfer 19.3 against 6.9 for the input). The legs are rods
    whose patches have no normal axis: their normals come from the legs' section (MSAE 0.366 ->
    0.235, tuned PCA 0.237; Chamfer 4.43 -> 3.94 with the legs moved along those normals)."""
    from cljn_addon.core.evaluation.metrics import MeshDistance
    from cljn_addon.core.evaluation.shapes import shape_mesh

    noisy, clean, truth = sample_shape("stool", 20000, noise=0.006, seed=1)
    res = denoise(noisy, shipped, iterations="auto")
    dist = MeshDistance(*shape_mesh("stool"))
    assert chamfer(res.points, clean) < 0.8 * chamfer(noisy, clean)
    assert dist.distance(res.points).mean() < dist.distance(noisy).mean()
    assert res.rod_share > 0.15
    best_pca = min(msae(pca_normals(noisy, k), truth) for k in (20, 40, 60, 100, 150, 200))
    assert msae(res.normals, truth) < 1.05 * best_pca
    assert sign_agreement(res.normals, truth) > 0.94


def test_denoise_beats_the_plane_filter_at_low_noise(shipped):
    noisy, clean, _ = sample_shape("stepped_block", 20000, noise=0.006, seed=3)
    res = denoise(noisy, shipped, iterations="auto")
    best_filter = min(chamfer(pca_projection_filter(noisy, k), clean) for k in (20, 40, 60, 100))
    assert chamfer(res.points, clean) < best_filter


def test_a_sparse_cloud_is_cleaned_as_well_as_the_best_plane_filter(shipped):
    """10K points at 1% (a 5% ball holds ~75): with the noise read low, the risk check took the
    10-neighbour plane filter everywhere (Chamfer 10.4 x 1e-5 against 6.7 for the best plane
    filter, 6.7 for the network alone)."""
    noisy, clean, _ = sample_shape("sphere", 10000, noise=0.01, seed=5)
    res = denoise(noisy, shipped, iterations="auto")
    best_filter = min(chamfer(pca_projection_filter(noisy, k), clean) for k in (10, 20, 40, 80))
    assert chamfer(res.points, clean) < best_filter


def test_a_sparse_thin_part_is_checked_against_plane_filters_and_never_worse_than_the_input(shipped):
    """5K points at 1.5%: a patch-radius ball holds ~40 points, its patches repeat them, and the
    four passes left the L-bracket worse than its input (Chamfer 42.9 x 1e-5 against 34.3);
    checked region by region against plane filters it comes out ahead of all of them (18.2
    against 28.5)."""
    noisy, clean, _ = sample_shape("l_bracket", 5000, noise=0.015, seed=1)
    res = denoise(noisy, shipped, iterations="auto")
    assert res.plane_share > 0.1
    best_filter = min(chamfer(pca_projection_filter(noisy, k), clean) for k in (10, 20, 40, 80))
    assert chamfer(res.points, clean) < best_filter < chamfer(noisy, clean)
    surface = MeshDistance(*shape_mesh("l_bracket"))
    assert surface.distance(res.points).mean() < surface.distance(noisy).mean()


def test_noise_that_grows_across_a_cloud_is_cleaned_where_it_is_high(shipped):
    """A sphere whose noise grows from 0.2% to 2% along x (a LiDAR's grows with range). Read as
    one noise (~1%), the bound and the passes left its noisy end under-cleaned and the risk
    check, at the quiet balls' noise, kept plane filters of 10 neighbours: Chamfer 6.6x the best
    plane filter's at 50K points. Each point's own noise, read near it, sets its bound and
    passes: the denoise must beat every plane filter, and its noisy end come out more than
    twice as near the surface as it went in."""
    noisy, clean, sigma = sample_shape_varying_noise("sphere", 20000, 0.002, 0.02, seed=3)
    res = denoise(noisy, shipped, iterations="auto")
    best_filter = min(chamfer(pca_projection_filter(noisy, k), clean) for k in (20, 40, 80, 120))
    assert chamfer(res.points, clean) < best_filter
    surface = MeshDistance(*shape_mesh("sphere"))
    high = noisy[:, 0] > np.quantile(noisy[:, 0], 0.8)
    assert surface.distance(res.points[high]).mean() < 0.5 * surface.distance(noisy[high]).mean()
    assert res.displacement_bound > 4 * res.noise_sigma     # the noisy end's bound, not the cloud's
    # Reported: the 10th-90th percentiles of the points' own noise, near the truth's.
    assert np.allclose(res.noise_range, np.quantile(sigma, [0.1, 0.9]), rtol=0.25)


def test_noise_that_grows_gently_across_a_cloud_is_not_left_to_plane_filters(shipped):
    """A sphere whose noise grows only from 0.3% to 0.9% along x. Its noise balls read 2.2-2.4x
    between the quiet and the noisy end, as uneven relief can (column_head at 20K points: 2.12x);
    read as one noise, the risk check (at the quiet end's noise) gave the whole cloud to plane
    filters of 10 neighbours: Chamfer 2.5x the best plane filter's at 50K points. Along the
    surface relief hardly counts (`noise.surface_noise_varies`), so the gradient is told apart
    and each point is cleaned at its own noise."""
    noisy, clean, _ = sample_shape_varying_noise("sphere", 20000, 0.003, 0.009, seed=3)
    res = denoise(noisy, shipped, iterations="auto")
    best_filter = min(chamfer(pca_projection_filter(noisy, k), clean) for k in (20, 40, 80, 120))
    assert res.displacement_bound > 1.2 * DISPLACEMENT_BOUND_SIGMAS * res.noise_sigma   # each point's own bound
    assert chamfer(res.points, clean) < min(1.05 * best_filter, 0.5 * chamfer(noisy, clean))


@pytest.mark.parametrize("name, low, high, profile", [("sphere", 0.002, 0.02, "linear"),
                                                      ("torus", 0.015, 0.004, "step")])
def test_normals_only_reads_each_points_own_noise_where_it_varies(shipped, name, low, high, profile):
    """Normals only on a cloud whose noise varies: a sphere's grows 0.2% -> 2% along x, a torus
    is two merged scans (1.5% and 0.4%). Read at the quietest balls' noise, the posterior
    looked only that far and the pass's patch was sized for it: at 30K points origin MSAE 0.173
    and 0.175 against tuned PCA's 0.011 and 0.024. Each point's own noise
    (`noise.varying_local_noise`) now sets its posterior's reach, the cloud's the patch: 0.0058
    and 0.0211. Both must beat every PCA k, over the cloud and its noisiest part."""
    noisy, clean, sigma = sample_shape_varying_noise(name, 20000, low, high, seed=3, profile=profile)
    truth = MeshDistance(*shape_mesh(name)).nearest(clean)[1]
    res = estimate_normals(noisy, shipped)
    assert np.array_equal(res.points, noisy) and res.noise_range is not None
    loud = sigma > np.quantile(sigma, 0.8) if profile == "linear" else sigma == max(low, high)
    for k in (20, 40, 80, 160):
        pca = pca_normals(noisy, k)
        assert msae(res.normals, truth) < msae(pca, truth)
        assert msae(res.normals[loud], truth[loud]) < msae(pca[loud], truth[loud])


def test_a_street_scene_keeps_the_wall_behind_a_parked_car(shipped):
    """Issue #12's street scan: a patch of 5% of the diagonal (~0.5 m here) is wider than the
    0.6 m gap between a car and the wall behind it. No point may be dragged across; the scene
    must come out cleaner than with the best plane filter, and the input stay covered."""
    from scipy.spatial import cKDTree

    from cljn_addon.core.evaluation.shapes import sample_noisy, street_scene

    vertices, faces = street_scene()
    noise = 0.02                                                  # 2 cm, in metres
    clean, _, face, noisy = sample_noisy(vertices, faces, 25000, noise, seed=3)
    res = denoise(noisy, shipped, iterations="auto")
    assert 0.8 * noise < res.noise_sigma < 1.3 * noise
    assert res.displacement.max() <= res.displacement_bound * (1 + 1e-9)
    wall = (face == 2) | (face == 3)                             # street_scene's faces 2-3
    behind_car = wall & (np.abs(clean[:, 0]) < 2.25) & (clean[:, 2] < 1.5)
    wall_y = vertices[faces[2, 0], 1]
    assert behind_car.sum() > 200
    off_wall = np.abs(res.points[behind_car, 1] - wall_y)
    assert off_wall.max() < 0.1 and off_wall.mean() < 0.5 * np.abs(noisy[behind_car, 1] - wall_y).mean()
    uncovered = cKDTree(res.points).query(noisy, distance_upper_bound=2.5 * noise, workers=-1)[0] > 2.5 * noise
    assert uncovered.mean() < 0.03                                 # the street scan: 41%, jet smoothing 6%
    surface = MeshDistance(vertices, faces)
    best_filter = min(surface.distance(pca_projection_filter(noisy, k)).mean() for k in (10, 20, 40))
    assert surface.distance(res.points).mean() < 0.85 * best_filter


def test_l_bracket_normals_beat_tuned_pca_and_face_outward_at_0_6_percent(shipped):
    """Thin-walled: one moving pass, then normals from a second pass on the cleaned points
    (MSAE 0.139, 0.166 without it; tuned PCA 0.193; sign 98.2%)."""
    noisy, _, truth = sample_shape("l_bracket", 20000, noise=0.006, seed=1)
    res = denoise(noisy, shipped, iterations="auto")
    assert res.thin_walled
    best_pca = min(msae(pca_normals(noisy, k), truth) for k in (20, 40, 60, 100))
    assert msae(res.normals, truth) < 0.8 * best_pca             # 0.139 vs 0.193 (k=100)
    assert sign_agreement(res.normals, truth) > 0.97


def test_auto_iterations_beat_four_passes_on_a_sharp_shape_at_low_noise(shipped):
    """At 0.6% the extra passes only round the tips of a star prism (Chamfer 3.27 after 4,
    2.60-2.82 after 1-2); auto, now the default, runs fewer."""
    noisy, clean, _ = sample_shape("star_prism", 20000, noise=0.006, seed=11)
    auto = denoise(noisy, shipped, iterations="auto")
    four = denoise(noisy, shipped, iterations=4)
    assert auto.iterations < 4
    assert chamfer(auto.points, clean) < 0.92 * chamfer(four.points, clean)


def test_relief_at_the_noise_scale_is_cleaned_as_well_as_the_best_plane_filter(shipped):
    """A sphere carved with bumps ~4 points across and at the noise's own scale (the
    procedural stand-in for column_head's carving: its clean surface alone reads ~0.5 sigma of
    noise). Each pass erodes some relief, so the network only ties the best tuned plane filter
    here (20K points at 0.6%: 4.86 against 4.87, input 7.65; with the risk check, which finds
    no region where a plane filter is clearly better, 4.95); it must not fall behind it."""
    noisy, clean, _ = sample_shape("carved_sphere", 20000, noise=0.006, seed=3)
    res = denoise(noisy, shipped, iterations="auto")
    best_filter = min(chamfer(pca_projection_filter(noisy, k), clean) for k in (10, 20, 40, 60))
    assert chamfer(res.points, clean) < 1.05 * best_filter
    assert chamfer(res.points, clean) < 0.7 * chamfer(noisy, clean)


def test_auto_iterations_keep_going_on_a_solid_at_high_noise(shipped):
    """At 2% auto runs the paper's four passes on a solid; one would leave it noisier."""
    noisy, clean, _ = sample_shape("octahedron", 12000, noise=0.02, seed=11)
    auto = denoise(noisy, shipped, iterations="auto")
    one = denoise(noisy, shipped, iterations=1)
    assert auto.iterations >= 3
    assert chamfer(auto.points, clean) < 0.9 * chamfer(one.points, clean)


@pytest.mark.parametrize("name, noise", [("stool", 0.011), ("l_bracket", 0.02)])
def test_auto_iterations_stop_once_a_thin_shape_has_moved_by_the_noise(shipped, name, noise):
    """Seat and legs 2-4 sigma thick: the noise-based count alone ran 4 passes, each drawing
    the faces together (stool at 1.1%: Chamfer 19.9 after 4 passes, 13.8 for the input, 13.0 after
    1; l_bracket at 2%: 34.9 after 4, 30.4 after the 2 auto keeps). The discrepancy stop keeps
    the passes whose RMS move stays within the noise: the result is less noisy than the input
    and than four passes. (Without the split of merged walls, which would put the faces of the
    four-pass result back apart: this tests the stop rule itself.)"""
    noisy, clean, _ = sample_shape(name, 20000, noise=noise, seed=1)
    auto = denoise(noisy, shipped, iterations="auto", split_walls=False)
    four = denoise(noisy, shipped, iterations=4, split_walls=False)
    assert auto.iterations < 4 and auto.stopped_early
    assert chamfer(auto.points, clean) < 0.97 * chamfer(noisy, clean)
    assert chamfer(auto.points, clean) < 0.9 * chamfer(four.points, clean)
    # The passes kept moved the cloud by about the noise, no more.
    rms_move = np.sqrt(np.mean(np.sum((auto.points - noisy) ** 2, axis=1)))
    assert rms_move < 1.3 * noise


@pytest.mark.parametrize("name, gain", [("thin_tube", 0.04), ("star_prism", 0.01), ("thin_plate", 0.1)])
def test_points_seen_from_both_sides_face_their_input_side(shipped, name, gain):
    """Walls and tips thinner than the noise: the denoised points of both faces lie together and
    are seen from both sides; their input positions still tell their faces apart (orient step
    5). Measured at 0.6%, 20K: tube 54.9% -> 61.8%, star prism 94.5% -> 96.5%, plate 50.2% ->
    66.6% (its faces came out as one sheet, seen from both sides everywhere like an open scan:
    step 5 runs because the object was found thin-walled); the most any method can reach there
    (metrics.sign_ceiling_normals) is 90.0%, 97.8% and 89.5%. Step 5 alone: without the split of
    merged walls, which on the plate puts the faces apart and sets the same signs itself (86.6%;
    test_thin_plate_thinner_than_two_sigma_comes_out_on_its_faces)."""
    from cljn_addon.core.evaluation.metrics import sign_ceiling_normals
    from cljn_addon.core.evaluation.shapes import normalise_unit_diagonal, shape_mesh
    from cljn_addon.core.orient import orient_normals

    noisy, _, truth = sample_shape(name, 20000, noise=0.006, seed=5)
    res = denoise(noisy, shipped, iterations="auto", split_walls=False)
    without_input_side = orient_normals(res.points, res.normals, "outward")
    v, f = shape_mesh(name)
    ceiling = sign_agreement(sign_ceiling_normals(noisy, normalise_unit_diagonal(v), f, 0.006), truth)
    assert sign_agreement(without_input_side, truth) + gain < sign_agreement(res.normals, truth) <= ceiling


def test_relief_the_estimate_reads_as_noise_is_kept_by_the_risk_check(shipped, column_head_relief):
    """column_head's carving is relief at the noise's own scale (its clean surface alone reads
    0.5 sigma of 0.6% noise): the estimate reads it as noise (1.5x) and the passes erode it,
    leaving the cloud worse than the input (20K points: Chamfer 9.59 against 9.07). The risk
    check hands those regions to a plane filter (`risk.choose_by_risk`): 6.96, the best tuned
    plane filter's 6.98. Given the scanner's noise, auto runs one pass and checks it: 6.85.
    There the normals are the output's own planes (`risk.fitted_normals`): output MSAE 0.570
    with the passes' normals, 0.452 with the check; the best plane filter then PCA normals
    (filter and normals each over 10-60 neighbours, tuned on the truth) 0.452."""
    from cljn_addon.core.evaluation.metrics import MeshDistance

    v, f, clean, _, noisy = column_head_relief
    passes_only = denoise(noisy, shipped, iterations="auto", risk_check=False)
    blind = denoise(noisy, shipped, iterations="auto")
    given = denoise(noisy, shipped, iterations="auto", noise_sigma=0.006)
    best_filter = min(chamfer(pca_projection_filter(noisy, k), clean) for k in (10, 20, 40, 60))
    assert blind.noise_sigma > 1.3 * 0.006
    assert chamfer(passes_only.points, clean) > chamfer(noisy, clean)      # the erosion the check is for
    assert blind.plane_share > 0.5 and passes_only.plane_share == 0.0
    assert chamfer(blind.points, clean) < min(0.8 * chamfer(noisy, clean), 1.05 * best_filter)
    surface = MeshDistance(v, f)
    assert surface.distance(blind.points).mean() < surface.distance(passes_only.points).mean()
    assert given.iterations == 1 and given.noise_sigma == 0.006
    out_msae = lambda res: msae(res.normals, surface.nearest(res.points)[1])      # noqa: E731
    assert out_msae(blind) < 0.85 * out_msae(passes_only)
    assert out_msae(blind) < 1.05 * min(msae(pca_normals(p, k), surface.nearest(p)[1])
                                        for p in (pca_projection_filter(noisy, kf) for kf in (10, 20))
                                        for k in (10, 20, 40, 60))
    assert chamfer(given.points, clean) < min(0.8 * chamfer(noisy, clean), 1.05 * best_filter)


def test_normals_only_on_relief_checks_its_surface_against_plane_filters(shipped, column_head_relief):
    """Normals only at low noise checks the surface of its one pass the same way, and takes the
    normals there from the output's own planes before the posterior: column_head at 20K points
    and 0.6%, origin MSAE 0.476 -> 0.468, tuned PCA's best 0.472 (k 40); 50K, the eval's
    cloud: 0.450 -> 0.430 against 0.438. Positions stay bit-identical."""
    _, _, clean, truth, noisy = column_head_relief
    checked = estimate_normals(noisy, shipped)
    unchecked = estimate_normals(noisy, shipped, risk_check=False)
    assert checked.plane_share > 0.5 and np.array_equal(checked.points, noisy)
    assert msae(checked.normals, truth) < 0.99 * msae(unchecked.normals, truth)
    assert msae(checked.normals, truth) < min(msae(pca_normals(noisy, k), truth) for k in (20, 40, 60, 100))


def test_the_risk_check_leaves_sharp_solids_to_the_network(shipped):
    """A star prism at 0.6%: plane filters round its edges and tips, the network keeps them
    (20K points: 2.91 against the best plane filter's 3.30); with the check the result is
    within 3% of the passes' own."""
    noisy, clean, _ = sample_shape("star", 20000, noise=0.006, seed=4)
    checked = denoise(noisy, shipped, iterations="auto")
    passes_only = denoise(noisy, shipped, iterations="auto", risk_check=False)
    best_filter = min(chamfer(pca_projection_filter(noisy, k), clean) for k in (10, 20, 40, 60))
    assert chamfer(passes_only.points, clean) < 0.95 * best_filter
    assert chamfer(checked.points, clean) < 1.03 * chamfer(passes_only.points, clean)


def test_walls_kept_apart_where_a_probe_holds_few_points_are_not_split(shipped):
    """An L-bracket 3.7 sigma thick at 0.8% and 50K points: the passes keep its faces apart,
    and the probe ball along the normal holds only ~8 outputs. Asking a face for 8 of them
    missed the far face on most points: 42% was split onto the wrong faces (Chamfer 3.04 ->
    3.78); 0.4x of what the point's own ball holds, at least 3, finds it. Run as a solid
    (`own_sheet=False`): the default reads it as thin-walled and runs these passes as one of
    its four runs (`infer.own_sheet_or_solid`), which would only add time here."""
    noisy, clean, truth = sample_shape("l_bracket", 50000, noise=0.008, seed=2)
    res = denoise(noisy, shipped, iterations="auto", own_sheet=False)
    assert res.split_share < 0.02
    assert chamfer(res.points, clean) < 0.7 * chamfer(noisy, clean)
    assert sign_agreement(res.normals, truth) > 0.9


def test_normals_only_on_a_dense_cloud_fills_each_patch_and_beats_the_model_radius(shipped, monkeypatch):
    """Normals only at 50K points: the pass's patch shrinks towards the ball that holds one
    patch's points (`infer.full_patch_radius`: 3.5% of the diagonal here, not 5%); the posterior
    averages out its variance and its lower bias stays (the eval's stool at 1.1%: 0.289 vs 0.323)."""
    from cljn_addon.core import infer

    noisy, _, truth = sample_shape("stool", 50000, noise=0.011, seed=3)
    finer = estimate_normals(noisy, shipped)
    monkeypatch.setattr(infer, "full_patch_radius", lambda points, per_patch, sigma, ceiling, seed=0: ceiling)
    model_radius = estimate_normals(noisy, shipped)
    assert np.array_equal(finer.points, noisy)
    assert msae(finer.normals, truth) < 0.95 * msae(model_radius.normals, truth)


@pytest.mark.parametrize("name, noise", [("stepped_block", 0.006), ("octahedron", 0.01)])
def test_normals_only_mode_beats_tuned_pca_on_sharp_shapes(shipped, name, noise):
    """Normals only: the posterior mean normal over the pass's filtered points (`core.origin`)
    at each input point, positions untouched (12K points: 0.0760 vs PCA k40 0.0809; 0.1024 vs
    k100 0.1055)."""
    noisy, _, truth = sample_shape(name, 12000, noise=noise, seed=5)
    res = estimate_normals(noisy, shipped)
    assert np.array_equal(res.points, noisy)
    best_pca = min(msae(pca_normals(noisy, k), truth) for k in (20, 40, 60, 100, 150, 200))
    assert msae(res.normals, truth) < best_pca
    assert sign_agreement(res.normals, truth) > 0.99


def test_star_prism_tips_shade_the_way_they_face(shipped, monkeypatch):
    """Issue #12's thin orientation shape: the last ~15% of the star prism's tips are under ~2.7
    sigma thick; the passes draw their faces into one sheet there, too few points to split
    (`sheets.split_merged_walls`), and orientation turns each to its input side, so about half
    of them sat nearer the face they do not face (sign output 96.0% at 0.6%, 30K points). Seated
    on the face they face (`sheets.seat_on_facing_face`): 99.1%, and nearer the surface."""
    import cljn_addon.core.infer as infer

    noisy, _, _ = sample_shape("star_prism", 20000, noise=0.006, seed=8)
    surface = MeshDistance(*shape_mesh("star_prism"))
    seated = denoise(noisy, shipped, iterations="auto")
    monkeypatch.setattr(infer, "seat_on_facing_face", lambda points, normals, median, variance, sigma: points)
    unseated = denoise(noisy, shipped, iterations="auto")
    (d_seated, n_seated), (d_unseated, n_unseated) = surface.nearest(seated.points), surface.nearest(unseated.points)
    assert sign_agreement(seated.normals, n_seated) >= 0.985
    assert sign_agreement(seated.normals, n_seated) > sign_agreement(unseated.normals, n_unseated) + 0.015
    assert d_seated.mean() <= d_unseated.mean()
    assert seated.displacement.max() <= seated.displacement_bound * (1 + 1e-9)


def test_star_prism_tips_placed_by_a_plane_filter_are_seated_too(shipped, monkeypatch):
    """At 1.1% (30K points) the risk check puts 4% of the star prism, its tips, on a plane
    filter's surface: their mid-plane. Turned to their input side but left there, half shaded
    the way they do not face (sign output 98.3%). Inside a region turned as a whole they are
    seated like the rest (`sheets.in_faced_region`): 98.7%."""
    import cljn_addon.core.infer as infer

    noisy, _, _ = sample_shape("star_prism", 30000, noise=0.011, seed=8)
    surface = MeshDistance(*shape_mesh("star_prism"))
    # The seating alone: rim normals (`test_rims.py`) change both runs' normals at the tips.
    seated = denoise(noisy, shipped, iterations="auto", rim_normals=False)
    assert seated.plane_share > 0.02
    monkeypatch.setattr(infer, "in_faced_region", lambda points, faced, rows: np.zeros(len(rows), bool))
    left = denoise(noisy, shipped, iterations="auto", rim_normals=False)
    (d_seated, n_seated), (d_left, n_left) = surface.nearest(seated.points), surface.nearest(left.points)
    assert sign_agreement(seated.normals, n_seated) > sign_agreement(left.normals, n_left) + 0.003
    assert sign_agreement(seated.normals, n_seated) >= 0.985
    # Seating costs the mean distance little: under 1.01x on earlier sessions' machines, 1.014x
    # (0.002160 against 0.002130) on an AMD EPYC with avx512_bf16, the same code (24e483e as
    # aee24b1); the likeliest cause, the network's bf16 rounding, which differs from CPU to CPU.
    assert d_seated.mean() <= d_left.mean() * 1.02
    assert seated.displacement.max() <= seated.displacement_bound * (1 + 1e-9)


def test_a_sparse_street_300_m_long_is_not_wrecked(shipped):
    """300 m of street in 40K points (a 5% patch is 15 m: buildings, cars and poles at once) read
    as 1.75 m of noise: the bound let points move 5.25 m and P2S went from 1.60 cm to 23.9 cm.
    Read as a scene (`noise.SCENE_SPAN`), its patches are 4.7 m balls and its noise the quiet
    balls' 2.2 cm: no point moves beyond 3.5 sigma of the true noise. There the network still
    did worse than the input (P2S 2.54 cm); the risk check now offers the input itself, and
    nearly every region keeps it: P2S within 1% of the input's (1.605 against 1.600 cm)."""
    from cljn_addon.core.evaluation.shapes import city_street, sample_noisy

    vertices, faces = city_street(300.0, 10.0)
    _, _, _, noisy = sample_noisy(vertices, faces, 40_000, 0.02, seed=3)
    res = denoise(noisy, shipped, iterations="auto")
    assert 0.015 < res.noise_sigma < 0.03
    assert np.linalg.norm(res.points - noisy, axis=1).max() < 3.5 * 0.02
    assert res.kept_share > 0.9 and any("left as they were" in step for step in res.steps_taken())
    assert np.mean(res.displacement == 0.0) >= res.kept_share       # kept exactly, none seated after
    assert np.isfinite(res.scene_radius) and res.steps_taken()[0].startswith("read as a scene")
    surface = MeshDistance(vertices, faces)
    assert surface.distance(res.points).mean() < 1.01 * surface.distance(noisy).mean()


def test_heights_averaged_after_the_passes_bring_a_solid_nearer_its_surface_at_high_noise(shipped):
    """smooth_heights (off by default until the eval has run with it at every level): the
    passes leave part of a 2% noise; averaged along the normals the output lies nearer."""
    noisy, clean, _ = sample_shape("octahedron", 20000, 0.02, seed=21)
    plain = denoise(noisy, shipped, iterations="auto", orientation="none")
    averaged = denoise(noisy, shipped, iterations="auto", orientation="none", smooth_heights=True)
    assert chamfer(averaged.points, clean) < 0.9 * chamfer(plain.points, clean)
    assert np.linalg.norm(averaged.points - noisy, axis=1).max() <= averaged.displacement_bound * (1 + 1e-9)

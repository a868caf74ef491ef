"""Iterative inference: filter positions and estimate normals in one learned pass per step.

Each iteration (METHOD.md, Inference): patches around every point -> network ->
p' = p + r R^T d; Taubin-like inflation over 100 neighbours; LRMA update over 20. Then the
normals are oriented consistently (ours; the paper's are unoriented).
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from scipy.spatial import cKDTree

from .config import INFLATION_NEIGHBOURS, LRMA_NEIGHBOURS, MIN_BALL_POINTS, ORIENTATIONS
from .errors import Cancelled, InputError, positive_number
from .noise import (
    DISPLACEMENT_BOUND_SIGMAS,
    THIN_WALLED_SHARE,
    clamp_displacement,
    estimate_noise,
    surface_noise_sigma,
    varying_local_noise,
)
from .orient import orient_normals
from .origin import median_count_within, origin_normals
from .patches import PatchSource, bbox_diagonal, framed_patches, from_frame
from .refine import HEIGHT_AVERAGE_SIGMAS, height_average, inflation, lrma_update
from .rims import rim_normals as rim_outward_normals
from .risk import KEPT_INPUT, choose_among, choose_by_risk, fitted_normals, probe_offsets
from .rods import RodNormals, section_radius
from .sheets import in_faced_region, seat_on_facing_face, split_merged_walls

ACTIVATION_BUDGET = 100_000_000   # floats per forward chunk: bounds memory on any cloud size
# On the CPU the network runs a chunk this many patch points at a time: each layer's output
# (4096 x 512 bf16, 4 MB) then stays in cache, where a whole chunk's (200K x 512) streams
# through memory once per layer and once more per ReLU. Small preset, 2 cores, bf16: 5,600 ->
# 11,700 patches/s, the outputs the same to the last bit (fp32, for CPUs without bf16: 3,300
# -> 4,600 patches/s, outputs within float rounding). Calls of 64-160 patches ran up to 14,700/s
# in bf16 but rounded a few outputs a bf16 step differently.
CPU_NETWORK_ROWS = 4096


@dataclass
class DenoiseResult:
    points: np.ndarray        # (N, 3) float64, same order as the input
    normals: np.ndarray       # (N, 3) float32, unit length, oriented as asked
    outliers: np.ndarray      # (N,) bool: too few neighbours; these points were not moved
    displacement: np.ndarray  # (N,) float64: distance each point moved
    seconds: float
    iterations: int
    noise_sigma: float = float("nan")        # scanner noise, estimated or as given (cloud units)
    displacement_bound: float = float("inf")  # no point moved further than this
    thin_walled: bool = False                # handled as a thin-walled object (own-sheet patches)
    solid_share: float = 0.0                 # of a thin-walled object, the share whole-ball passes placed
    split_share: float = 0.0                 # share of points put back on their own face of a merged thin wall
    # (N,) int8: +1 / -1 where a point was put back on the face its normal points to / from, else 0
    wall_side: np.ndarray | None = None
    stopped_early: bool = False              # auto iterations stopped: points had moved as far as the noise
    rod_share: float = 0.0                   # share of points on rods, normals from the rod's section
    plane_share: float = 0.0                 # share of points a plane filter placed (`risk`): relief kept
    kept_share: float = 0.0                  # share of points left where they were: no filter beat the input (`risk`)
    rim_share: float = 0.0                   # share of points beyond a thin part's edge, given its rim's normal
    ran_on: str = ""                         # device and backend, e.g. "cpu (numpy)"
    # Where the noise varies across the cloud and each point was handled at its own
    # (`noise.varying_local_noise`): the 10th and 90th percentiles of the points' noise; else None.
    noise_range: tuple[float, float] | None = None
    # Read as a scene (`noise.SCENE_SPAN`): the radius of the balls its noise was read in, which
    # were its patches (cloud units); else nan.
    scene_radius: float = float("nan")

    def steps_taken(self) -> list[str]:
        """What the engine did beyond the passes, in words, for the command line and the
        extension's report (one wording for both); empty when nothing applied."""
        steps = []
        if np.isfinite(self.scene_radius):
            steps.append(f"read as a scene: patches of radius {self.scene_radius:.3g}, where a ball holds one surface")
        if self.noise_range is not None:
            low, high = self.noise_range
            steps.append(f"noise varies across the cloud ({low:.3g}-{high:.3g}): each point at its own")
        if self.thin_walled and self.solid_share > 0:
            steps.append(f"read as thin-walled: own-side patches, and on {self.solid_share:.1%} whole-ball passes, "
                         "which did better there (if it is solid, Solid Object or --solid is faster)")
        elif self.thin_walled:
            steps.append("thin-walled (own-side patches; if it is not, Solid Object or --solid)")
        if self.split_share > 0:
            steps.append(f"{self.split_share:.1%} on merged thin walls put back on their own face")
        if self.rod_share > 0:
            steps.append(f"{self.rod_share:.1%} on rods (normals from the rod's section)")
        if self.rim_share > 0:
            steps.append(f"{self.rim_share:.1%} beyond thin parts' edges (normals of their rims)")
        if self.plane_share > 0:
            steps.append(f"{self.plane_share:.1%} by a plane filter where it beat the network (relief kept)")
        if self.kept_share > 0:
            steps.append(f"{self.kept_share:.1%} left as they were, where no filter beat the input")
        return steps


def validate_points(points) -> np.ndarray:
    """(N, 3) float64 copy of the input, or an InputError that says what is wrong."""
    try:
        arr = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError("points must be an (N, 3) array of numbers") from None
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InputError(f"points must be an (N, 3) array of x, y, z; got shape {arr.shape}")
    if len(arr) == 0:
        raise InputError("the point cloud is empty")
    bad = ~np.isfinite(arr).all(axis=1)
    if bad.any():
        rows = np.flatnonzero(bad)
        raise InputError(f"{len(rows)} point(s) have NaN or infinite coordinates (first at row {rows[0]}); "
                         "remove or fix them first")
    if len(arr) < MIN_BALL_POINTS:
        raise InputError(f"the cloud has {len(arr)} point(s); at least {MIN_BALL_POINTS} are needed")
    if bbox_diagonal(arr) == 0.0:
        raise InputError("all points are at the same position; there is no surface to fit")
    return arr.copy()


def find_outliers(points, radius):
    """Points whose ball (self included) holds fewer than MIN_BALL_POINTS points."""
    dist, _ = cKDTree(points).query(points, k=MIN_BALL_POINTS, distance_upper_bound=radius, workers=-1)
    return ~np.isfinite(dist.reshape(len(points), -1)).all(axis=1)


def _chunk_size(model):
    cfg = model.config
    return max(64, ACTIVATION_BUDGET // (cfg.points_per_patch * max(cfg.encoder_channels)))


def predictor(model, device="auto", mixed_precision=True):
    """(predict, patches per chunk, where it runs) for a torch CLJNNet or a numpy_net.NumpyNet.
    predict: (B, n, 3) float32 patches -> (displacement, unit normal) arrays in the patch frame.
    torch is imported only for a torch model; mixed_precision=False keeps it in float32."""
    if getattr(model, "backend", "torch") == "numpy":
        if (device or "auto").lower() not in ("auto", "cpu"):
            raise InputError(f"the numpy backend runs on the CPU only (device {device!r} asked for); "
                             "choose the torch backend for a GPU")
        return model, model.chunk_size(), "cpu (numpy)"
    import torch

    from .device import autocast, pick_device
    from .model import inference_net

    dev = pick_device(device)
    net = inference_net(model.to(dev).eval())

    # A GPU takes the whole chunk in one call; a CPU a cache's worth at a time.
    step = max(1, CPU_NETWORK_ROWS // model.config.points_per_patch) if dev.type == "cpu" else None

    def predict(patches):
        with torch.inference_mode(), autocast(dev, enabled=mixed_precision):
            x = torch.from_numpy(patches).to(dev)
            size = step or max(len(x), 1)
            parts = [net(x[i:i + size]) for i in range(0, len(x), size)] or [net(x)]
            d, n = (torch.cat(outputs) for outputs in zip(*parts))
        return d.float().cpu().numpy(), n.float().cpu().numpy()

    return predict, _chunk_size(model), f"{dev.type} (torch)"


class NetworkPass(NamedTuple):
    displacement: np.ndarray  # (N, 3) world units
    normals: np.ndarray       # (N, 3) unit, sign arbitrary
    rod_section: np.ndarray   # (N,) RMS radius of the rod's section where the patch held one, else 0


def network_pass(predict, chunk, points, radius, rng, points_per_patch, report=None, cancel=None,
                 own_sheet=False) -> NetworkPass:
    """Displacement (world units) and unit normal for every point, from its patch
    (own_sheet: see `patches.make_patches`), and which patches had no normal axis."""
    source = PatchSource(points, radius, points_per_patch, rng)
    disp = np.empty_like(points)
    normals = np.empty_like(points)
    section = np.zeros(len(points))
    for start in range(0, len(points), chunk):
        if cancel is not None and cancel.is_set():
            raise Cancelled("cancelled")
        stop = min(start + chunk, len(points))
        local, _ = source.gather(points[start:stop], rng)
        section[start:stop] = section_radius(local) * radius  # the whole ball, before own-sheet patches
        patches, frames = framed_patches(local, rng, own_sheet)
        d, n = predict(patches)
        disp[start:stop] = from_frame(np.asarray(d, np.float64), frames) * radius
        normals[start:stop] = from_frame(np.asarray(n, np.float64), frames)
        if report is not None:
            report(stop / len(points))
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    return NetworkPass(disp, normals, section)


# Inflation and LRMA neighbours further than this many noise sigmas from a point's tangent
# plane count as the other side of a thin part. 2.5 cost normal accuracy on sparse curved
# clouds (curvature reads as offset); 4 keeps a plate ~6 sigma thick apart.
REFINE_SHEET_SIGMAS = 4.0
# On a thin-walled object (walls 2-3 sigma thick) 4 sigma still reaches the far side; its
# surfaces are mostly flat, so curvature does not read as offset there.
THIN_REFINE_SHEET_SIGMAS = 2.5
AUTO_SIGMA_PER_ITERATION = 0.075   # noise sigma / patch radius handled per iteration
MAX_AUTO_ITERATIONS = 4
# iterations='auto' at low noise also checks its result region by region against plane filters
# (`risk.choose_by_risk`): one more run of its passes on a nudged input, so only where the noise
# read in the quietest balls plans at most this many passes (relief inflates the plain estimate
# and with it the passes: column_head at 0.8% runs 3). At 3 the eval's column_head at 1.1%
# (50K) gets the check: Chamfer 8.80 -> 7.43 (plane filter 6.33), output MSAE ~0.56 -> 0.535;
# every other cloud at 1.1% keeps the network's result within 0.02 in Chamfer.
RISK_CHECK_MAX_PASSES = 3
# Normals only stops at 2: its posterior already averages over the noise, and the checked
# surface did not help it at 1.1% (column_head origin MSAE 0.5100 unchecked, 0.5127 checked).
NORMALS_RISK_CHECK_MAX_PASSES = 2
# iterations='auto' also stops early, keeping the passes before the first one whose RMS move
# from the input passes this many noise sigmas (`noise.surface_noise_sigma`): by then it moves
# points the noise did not (thin parts pulled together, detail eroded). A clean solid's RMS
# move levels off at 0.95-0.99 sigma; 1.15 leaves room for the estimate reading low (down to
# 0.88x at 2%). Mean Chamfer over the best pass count's (tools/iteration_study.py): 1.091 ->
# 1.053 on the 48 clouds it was chosen on, 1.164 -> 1.107 on 21 fresh ones; no cloud worse.
STOP_MOVE_SIGMAS = 1.15
NOISE_RANGE_QUANTILES = (0.1, 0.9)   # the noise range reported where it varies


def iterations_for_noise(sigma, radius):
    """Iterations for iterations='auto': as many as the noise needs, from 1 at sigma = 0.4%
    of the bbox diagonal (with the 5% patch radius) to the paper's 4 from 1.5% up. More passes
    at low noise only move points the noise did not: they clump points and pull thin parts
    together."""
    if not (np.isfinite(sigma) and radius > 0):
        return MAX_AUTO_ITERATIONS
    return int(passes_for_local_noise(sigma, radius))


def passes_for_local_noise(sigmas, radius):
    """`iterations_for_noise` of each point's own noise (`noise.local_noise`), as an array."""
    return np.clip(np.round(np.asarray(sigmas) / radius / AUTO_SIGMA_PER_ITERATION), 1, MAX_AUTO_ITERATIONS).astype(int)


def auto_iteration_count(sigma, radius, thin_walled):
    """Passes iterations='auto' plans before its stop: one on a thin-walled object (see `_run`),
    else `iterations_for_noise`."""
    return 1 if thin_walled else iterations_for_noise(sigma, radius)


def auto_stop_move(points, radius, sigma, seed=0):
    """RMS move from the input past which iterations='auto' drops a pass: `STOP_MOVE_SIGMAS`
    x the noise read along the surface (`noise.surface_noise_sigma`); inf when it cannot be read."""
    stop = STOP_MOVE_SIGMAS * surface_noise_sigma(points, radius, sigma, seed=seed)
    return stop if np.isfinite(stop) else float("inf")


# Normals only: the pass's patch never shrinks below this many noise sigmas (the training put
# noise up to half the patch radius: 2.5% of the diagonal with a 5% radius), nor below this
# share of the ceiling (a thin part's two faces both fill the ball; at the 128-point ball, 2.8%
# of the diagonal at 50K points, the L-bracket's origin MSAE went 0.083 -> 0.120 at 0.6%).
MIN_PATCH_RADIUS_SIGMAS = 2.0
MIN_PATCH_RADIUS_SHARE = 0.7
FULL_PATCH_SAMPLE = 4000


# A sparse cloud is checked at any noise: where a patch-radius ball holds fewer points than a
# patch, the patches repeat points, which the training never showed (its clouds held 100K
# points). Auto passes on 5K points at 1.5%, Chamfer x 1e5 (input / best plane filter / passes
# / checked): l_bracket 34.3 / 28.5 / 42.9 / 18.2, stepped_block 47.2 / 24.2 / 27.7 / 24.6;
# a sphere, a gear and a thin plate within 0.1-1.0 of the unchecked passes.
def padded_patches(points, radius, points_per_patch, seed=0) -> bool:
    """Whether a ball of `radius` holds fewer than `points_per_patch` points (the median)."""
    return median_count_within(cKDTree(points), points, radius, 0, points_per_patch, seed) < points_per_patch


def full_patch_radius(points, points_per_patch, sigma, ceiling, seed=0):
    """Normals only: the patch radius of its one pass, the median distance at which a ball holds
    one patch's points (the patch then sees its whole ball, not a subsample), no smaller than
    `MIN_PATCH_RADIUS_SIGMAS` noise sigmas or `MIN_PATCH_RADIUS_SHARE` of the ceiling (the
    model's or the user's radius), no larger than the ceiling. The posterior over the 3-sigma
    ball (`origin.origin_normals`) averages out the extra variance of the smaller patch; its
    lower bias is what is left (50K points: 3.5% against 5% of the diagonal; README, "Normals
    only: a patch the size of its points"). At 12K points the ball is wider than 5%: no change."""
    n = len(points)
    if n <= points_per_patch:
        return ceiling
    rng = np.random.default_rng(seed)
    sample = points[rng.choice(n, min(n, FULL_PATCH_SAMPLE), replace=False)]
    dist, _ = cKDTree(points).query(sample, k=[points_per_patch], workers=-1)
    floor = MIN_PATCH_RADIUS_SHARE * ceiling
    if np.isfinite(sigma) and sigma > 0:
        floor = max(floor, MIN_PATCH_RADIUS_SIGMAS * sigma)
    return float(min(max(np.median(dist), floor), ceiling))


def own_sheet_or_solid(points, model, own_sheet_points, normals, sigma, bound, seed=0, cancel=None,
                       progress=None, **options):
    """Per region, a thin-walled object's own-sheet pass (`own_sheet_points`, `normals`) or a
    solid's passes (whole-ball patches, as many as the noise needs), whichever Stein's unbiased
    risk estimate puts nearer the surface along `normals` (`risk.choose_among`). A sculpt's
    limbs, ribs and relief fill balls with two sheets as a wall does (dino at 0.6%, 50K points:
    two-sheet share 0.39, Chamfer x 1e5 1.74 by the own-sheet pass, 1.42 by a solid's two), but
    there a solid's passes do better; on a wall 2-3 sigma thick they pull the faces together,
    but where the walls split after them (`sheets.split_merged_walls`, as the own-sheet pass's
    are before the choice) they often do better there too (l_bracket at 0.6%: 2.22 own-sheet,
    1.80 solid). Both runs are repeated on the input nudged along `normals` for the divergence
    (`risk.probe_offsets`): four in all.

    points: the input (N, 3), in the frame of `own_sheet_points`. progress(start, width): a
    callback for a part of the bar, or None. options: `_run`'s patch, device and refinement
    settings. Returns (positions (N, 3), normals (N, 3), solid (N,) bool: the solid's chosen, the
    solid's `wall_side` (N,) along the returned normals).
    """
    common = dict(move_points=True, orientation="none", seed=seed, noise_sigma=sigma,
                  risk_check=False, rim_normals=False, cancel=cancel, **options)
    parts = progress or (lambda start, width: None)
    solid = _run(points, model, "auto", own_sheet=False, progress=parts(0.2, 0.35), **common)
    amplitude, offsets = probe_offsets(normals, sigma, seed=seed + 2)
    probe = points + offsets
    own_probe = _run(probe, model, 1, own_sheet=True, max_displacement=bound, normals_pass=False,
                     progress=parts(0.55, 0.15), **common)
    solid_probe = _run(probe, model, solid.iterations, own_sheet=False, max_displacement=bound,
                       normals_pass=False, progress=parts(0.7, 0.25), **common)
    positions, choice = choose_among(points, normals, [(own_sheet_points, own_probe.points),
                                                       (solid.points, solid_probe.points)],
                                     amplitude, sigma, seed=seed, cancel=cancel)
    chosen = choice == 1
    solid_normals = solid.normals.astype(np.float64)
    turned = np.einsum("ij,ij->i", solid_normals, normals) < 0
    solid_normals[turned] *= -1
    side = np.where(turned, -solid.wall_side, solid.wall_side).astype(np.int8)
    return positions, np.where(chosen[:, None], solid_normals, normals), chosen, side


def denoise(points, model, iterations=4, **options):
    """Filter a noisy cloud and estimate oriented normals (options: see `_run`)."""
    return _run(points, model, iterations, move_points=True, **options)


def estimate_normals(points, model, **options):
    """Normals only, positions untouched (bit-identical): one network pass, then at each input
    point the normal of the surface it was sampled from (`origin.origin_normals`: the posterior
    mean over the pass's filtered points within the noise of the point; at low noise that
    surface is first checked against plane filters, as the denoise's is: see `_run`)."""
    options.pop("iterations", None)
    return _run(points, model, 1, move_points=False, **options)


def _run(points, model, iterations, *, move_points, patch_radius=None, patch_radius_fraction=None,
         points_per_patch=None, orientation="outward", viewpoint=None,
         device="auto", progress=None, cancel=None, seed=0, refine=True, max_displacement=None,
         normal_motion_only=True, own_sheet="auto", split_walls=True, on_iteration=None, noise_sigma=None,
         rod_normals=True, risk_check=True, rim_normals=True, varying_noise=None, normals_pass=True,
         smooth_heights=False):
    """The engine behind `denoise` (move_points=True) and `estimate_normals` (False).

    points: (N, 3) array, any units. patch_radius: absolute radius; otherwise
    patch_radius_fraction (default: the model's, 5%) of the bbox diagonal, recomputed each
    iteration. move_points=False: one pass, positions returned bit-identical, normals of the
    surface each input point came from (`origin.origin_normals`); its pass takes the radius as
    a ceiling and uses the ball that holds one patch's points when that is smaller
    (`full_patch_radius`). orientation:
    'outward', 'viewpoint' (needs viewpoint=(x, y, z)) or 'none'. progress(fraction, message)
    is called as work proceeds; setting `cancel` (a threading.Event) raises Cancelled.
    refine=False skips inflation and the LRMA update (the network output alone).
    max_displacement: no point ends further than this from where it was (cloud units); by
    default 3 x the noise sigma estimated from the cloud (`noise.estimate_noise`), so a
    network that is wrong somewhere can under-clean there but not drag points away; pass
    float("inf") for the unbounded paper behaviour. iterations='auto' (the default of the
    panel, the command line and DenoiseOptions): from the estimated noise
    (`iterations_for_noise`), stopping early once the RMS move from the input would pass
    `STOP_MOVE_SIGMAS` noise sigmas (the discrepancy principle). normal_motion_only (ours, default): each iteration keeps
    only the component of the network's displacement along its normal (the paper adds the whole
    vector; sliding along the surface removes no noise and clumps points). own_sheet (ours):
    'auto' (default) handles a thin-walled object (`noise.estimate_noise`: many balls straddle
    both sides of a thin part) with own-sheet patches (`patches.make_patches`) and refinement
    that keeps to 2.5 rather than 4 sigma of each point's tangent plane (and one pass with
    iterations='auto'); False turns that off (a solid), True handles any cloud so.
    split_walls (ours, default True): where the passes merged the two faces of a wall thinner
    than the noise into one sheet, put each point back on the face on its own side
    (`sheets.split_merged_walls`; with outward orientation its normal faces that side); and
    where a wall or tip is too thin to split, the points outward orientation turned to their
    input side go onto the face they face (`sheets.seat_on_facing_face`; where a plane filter
    placed them, only inside a region turned as a whole: `sheets.in_faced_region`).
    on_iteration(iteration, points): called after each moving pass with the whole cloud as it
    then stands (input coordinates and order), for studies such as tools/iteration_study.py.
    rod_normals (ours, default True): where a pass's patch held a rod's whole cross-section (a
    chair leg, a pole: `rods.section_radius`), the network's normal has no axis to follow; the
    normal comes from the rod's section in the input instead (`rods.section_normals`), and the
    pass moves the point along it. rod_share in the result: the share of points whose final
    normal came from a section.
    noise_sigma: the scanner's noise (standard deviation, cloud units) when the user knows it;
    it replaces both estimates (`noise.estimate_noise` for the pass count, the motion bound and
    the refinement's reach; `noise.surface_noise_sigma` for the stop). A surface with relief at
    the noise's own scale reads as noise to any estimate (column_head at 0.6%: 1.45-1.64x), and
    then auto runs passes that erode it. In normals-only mode it is the reach of each point's
    surface posterior. None (default): estimated from the cloud (normals only: the noise read in
    the quietest balls, less swayed by relief; where it varies, each point's own).
    rim_normals (ours, default True): with outward orientation, on a closed object (seen from
    outside) or a thin-walled one, the points the noise left beyond the edge of a thin part (the
    passes move points only along their normals) lie nearest its rim, a face thinner than the
    noise; they take the rim's outward normal (`rims.rim_normals`). rim_share in the result:
    their share.
    risk_check (ours, default True): with iterations='auto', at low noise (the noise read in the
    quietest balls plans at most `RISK_CHECK_MAX_PASSES` passes; normals only,
    `NORMALS_RISK_CHECK_MAX_PASSES`) or, moving, on a sparse cloud (`padded_patches`), and not
    thin-walled, each region keeps the network's result or a plane filter's, whichever Stein's
    unbiased risk estimate puts nearer the surface
    (`risk.choose_by_risk`; the noise read in the quietest balls, or noise_sigma when given):
    relief at the noise's own scale, which the passes erode, is kept; there the normals are the
    output's own planes (`risk.fitted_normals`). It costs one more run of the passes. Normals
    only checks the surface its one pass filtered in the same way, at the same noise, before
    the posterior. plane_share in the result: the share of points a plane filter placed.
    Where neither beats the input itself, the region keeps its input (kept_share in the result;
    the normals there are the network's).
    On a cloud read as thin-walled (own_sheet='auto') with iterations='auto', at the same low
    noise, the check is between its own-sheet pass and a solid's passes instead
    (`own_sheet_or_solid`): a sculpt's limbs and relief also fill balls with two sheets.
    solid_share in the result: the share of points the solid's passes placed.
    Noise that changes across the cloud (ours; a LiDAR's grows with range): with
    iterations='auto', no max_displacement or noise_sigma given, and not thin-walled, where the
    noise read near each point varies across the cloud, by the noise balls' reading and by the
    surface's (`noise.varying_local_noise`), each point gets the bound, the passes (the cloud
    runs the most any point needs; a point stops moving after its own) and the refinement reach
    of its own noise, the stop compares moves with it, and the risk check reads it. Normals
    only (no noise_sigma given, not two-sheeted): each point's posterior and the risk check
    read its own noise; the pass's patch, the cloud's.
    varying_noise: that reading (`noise.LocalNoise`, per point of `points`), given to the risk
    check's second run; displacement_bound in the result is then the largest point's.
    normals_pass=False: no pass for the normals after the last moving one (the risk checks'
    runs on a nudged input need only the positions).
    smooth_heights (ours, default False for now): after the passes (not own-sheet ones), each
    point moves along its normal to the mean height of the points within
    `refine.HEIGHT_AVERAGE_SIGMAS` noise sigmas (its own, where the noise varies) whose normals
    agree with its own (`refine.height_average`): the passes leave part of the noise. Before the
    risk check, so its nudged run and its choice judge the averaged result. Off until the eval
    has run with it at every level (README, "Heights averaged after the passes").
    """
    t0 = time.time()
    given = validate_points(points)
    # Work relative to the bounding-box centre (float64): a georeferenced scan far from the
    # origin denoises like the same scan at the origin, and float32 patches keep their precision.
    centre = (given.min(axis=0) + given.max(axis=0)) / 2.0
    original = given - centre
    if orientation not in ORIENTATIONS:
        raise InputError(f"unknown orientation {orientation!r}; choose one of {', '.join(ORIENTATIONS)}")
    if orientation == "viewpoint" and viewpoint is None:
        raise InputError("orientation 'viewpoint' needs a viewpoint (x, y, z)")
    auto_iterations = move_points and iterations == "auto"
    if not auto_iterations:
        try:
            iterations = int(iterations) if move_points else 1
        except (TypeError, ValueError):
            raise InputError(f"iterations must be a whole number or 'auto', got {iterations!r}") from None
        if iterations < 1:
            raise InputError(f"iterations must be at least 1, got {iterations}")
    if noise_sigma is not None:
        noise_sigma = positive_number(noise_sigma, "noise sigma must be a positive number, got {!r}")
    if patch_radius is not None and not (np.isfinite(patch_radius) and patch_radius > 0):
        raise InputError(f"patch radius must be a positive number, got {patch_radius!r}")
    fraction = patch_radius_fraction or model.config.patch_radius_fraction
    if not 0 < fraction < 1:
        raise InputError(f"patch radius fraction must be between 0 and 1, got {fraction!r}")
    predict, chunk, ran_on = predictor(model, device)
    points_per_patch = points_per_patch or model.config.points_per_patch
    rng = np.random.default_rng(seed)

    span = [1.0]     # the share of the bar the passes take (half when the risk check follows)

    def report(fraction_done, message):
        if progress is not None:
            scaled = fraction_done * span[0] if fraction_done < 0.95 else fraction_done
            progress(min(max(scaled, 0.0), 1.0), message)

    radius0 = patch_radius or fraction * bbox_diagonal(original)
    outliers = find_outliers(original, radius0)
    inliers = np.flatnonzero(~outliers)
    if len(inliers) < MIN_BALL_POINTS:
        raise InputError("no point has enough neighbours within the patch radius; "
                         "raise the patch radius or check the cloud's units")
    current = original[inliers].copy()
    sigma = float("nan")
    bound = max_displacement
    if bound is not None and not bound > 0:
        raise InputError(f"max displacement must be a positive number, got {max_displacement!r}")
    thin_walled = two_sheets = False
    quiet_sigma = scene_radius = float("nan")
    if varying_noise is not None:          # given per point of `points`: keep the inliers'
        varying_noise = type(varying_noise)(*(np.asarray(field)[inliers] for field in varying_noise))
    # Normals only needs sigma (the posterior's reach) and, for its risk check, the quiet sigma
    # and how thin-walled it is; moving, also the bound and the passes (from a given sigma too)
    # and, with own_sheet='auto', how thin-walled it is (the risk checks' runs give both).
    if (noise_sigma is None or risk_check) if not move_points else (
            own_sheet == "auto" or noise_sigma is None and (bound is None or auto_iterations)):
        report(0.0, "estimating the noise level")
        estimate = estimate_noise(current, radius0, seed=seed)
        sigma, quiet_sigma = estimate.sigma, estimate.quiet_sigma
        if np.isfinite(estimate.scene_radius) and patch_radius is None:
            # A scene (`noise.SCENE_SPAN`): 5% of its extent holds cars, walls and poles at
            # once, a patch the network never saw; its patches are the balls its noise was
            # read in (a 150 m street, 100K points, 2 cm noise: P2S 1.60 cm in, 5.67 cm out
            # with 7.7 m patches and 10.3 cm read there; 1.50 cm with 2.8 m patches and 1.98 cm).
            fraction *= estimate.scene_radius / radius0
            radius0 = scene_radius = estimate.scene_radius
        two_sheets = estimate.two_sheet_share >= THIN_WALLED_SHARE
        # Normals only keeps whole-ball patches on thin walls (stool at 0.6%, 50K: MSAE 0.208,
        # 0.220 with own-sheet patches).
        thin_walled = move_points and two_sheets and own_sheet is not False
        if noise_sigma is None and (auto_iterations and max_displacement is None and not thin_walled
                                    or not move_points and not two_sheets):
            varying_noise = varying_local_noise(current, radius0, estimate, seed=seed)
    local = varying_noise
    if noise_sigma is not None:
        sigma = quiet_sigma = float(noise_sigma)
    elif not move_points and local is None and np.isfinite(quiet_sigma) and quiet_sigma > 0:
        # Normals only reads the noise in the quietest balls: relief at the noise's scale reads
        # as noise in the whole-cloud estimate (column_head at 0.6%: 1.62x the truth, the quiet
        # balls 1.08x; the other solids 0.98-1.15x against 1.01-1.19x), and a posterior that
        # reaches too far blends faces. Origin MSAE on the validation meshes, 0.6-2%:
        # 0.1298 / 0.1552 / 0.1878 / 0.2311 / 0.2827 -> 0.1283 / 0.1537 / 0.1864 / 0.2303 / 0.2829.
        # Where the noise varies (`local`), each point's posterior reads its own noise and the
        # pass's patch the cloud's: at the quiet balls' noise, a sphere whose noise grows 0.2% ->
        # 2% got origin MSAE 0.173 (tuned PCA 0.011); now 0.0058. Sized for its noisiest tenth
        # instead, the patch changed it by 2% at most on five such clouds.
        sigma = quiet_sigma
    # A cloud read thin-walled is checked against a solid's passes (`own_sheet_or_solid`), at
    # the noise the plane-filter check covers too: measured at 0.6-1.1% (the eval's thin shapes
    # read thin-walled up to 1.1%); more passes would make the four runs dearer still, untested.
    check_solid = (move_points and auto_iterations and risk_check and own_sheet == "auto" and thin_walled
                   and np.isfinite(sigma) and sigma > 0
                   and iterations_for_noise(sigma, radius0) <= RISK_CHECK_MAX_PASSES)
    if own_sheet is True and move_points:
        thin_walled = True
    if own_sheet == "auto":
        own_sheet = thin_walled
    if bound is None:
        bound = DISPLACEMENT_BOUND_SIGMAS * sigma
    point_bound = bound if local is None else DISPLACEMENT_BOUND_SIGMAS * local.sigma
    if auto_iterations:
        # A thin-walled object gets one pass: own-sheet patches catch ~60% of the patches that
        # straddle a wall 2.5 sigma thick, each pass draws the faces a little together, and
        # passes compound (l_bracket at 1.1%: Chamfer 14.8 after 3 passes, 9.6 after 1).
        iterations = auto_iteration_count(sigma, radius0, thin_walled)
    point_passes = None
    if local is not None:
        # Each point moves in as many passes as its own noise needs; the cloud runs the most.
        point_passes = passes_for_local_noise(local.sigma, radius0)
        if auto_iterations:
            iterations = int(point_passes.max())
    risk_check = (risk_check and (auto_iterations or not move_points) and not (thin_walled if move_points else two_sheets)
                  and np.isfinite(quiet_sigma) and quiet_sigma > 0
                  and (iterations_for_noise(quiet_sigma, radius0)
                       <= (RISK_CHECK_MAX_PASSES if move_points else NORMALS_RISK_CHECK_MAX_PASSES)
                       or move_points and padded_patches(current, radius0, points_per_patch, seed=seed)))
    if risk_check:
        span[0] = 0.5
    elif check_solid:
        span[0] = 0.2
    stop_move = float("inf")
    if auto_iterations and iterations > 1:
        if local is not None:
            stop_move = STOP_MOVE_SIGMAS * sigma      # moves are read against each point's own noise
        elif noise_sigma is not None:
            stop_move = STOP_MOVE_SIGMAS * sigma
        else:
            report(0.0, "estimating the noise level along the surface")
            stop_move = auto_stop_move(current, radius0, sigma, seed=seed)
    stopped_early = False
    # Inflation and LRMA leave out neighbours further than this from a point's tangent plane
    # (the other side of a thin part); unknown noise (a bound given by the caller): the paper's.
    sheet_sigmas = THIN_REFINE_SHEET_SIGMAS if thin_walled else REFINE_SHEET_SIGMAS
    sheet_offset = (sheet_sigmas * (sigma if local is None else local.sigma)
                    if (max_displacement is None or auto_iterations or noise_sigma is not None)
                    and np.isfinite(sigma) and sigma > 0 else None)
    normals = None
    rod_fits = RodNormals(original[inliers], radius0, seed=seed + 1, cancel=cancel) if rod_normals else None
    rods = np.zeros(len(current), bool)
    rod_sigma = [sigma]

    def on_rods(normals, section):
        """Where the pass's patch held a rod's whole section (no normal axis): the section's
        normal (`rods.RodNormals`), in place; the rows as a bool mask."""
        if rod_fits is None or not section.any():
            return np.zeros(len(section), bool)
        if not np.isfinite(rod_sigma[0]):      # a bound given with own_sheet=False
            rod_sigma[0] = estimate_noise(current, radius0, seed=seed).sigma
        return rod_fits.apply(normals, section, rod_sigma[0])

    for it in range(iterations):
        radius = patch_radius or fraction * bbox_diagonal(current)
        if not move_points:
            radius = full_patch_radius(current, points_per_patch, sigma, radius, seed=seed)
        base = it / iterations

        def net_report(f, it=it, base=base):
            report(base + 0.85 * f / iterations, f"iteration {it + 1}/{iterations}: network {int(f * 100)}%")

        disp, new_normals, section = network_pass(predict, chunk, current, radius, rng, points_per_patch,
                                                  net_report, cancel, own_sheet)
        if normals is not None:
            # Keep the sign of the previous iteration's normal (the network's is unoriented).
            flip = np.einsum("ij,ij->i", new_normals, normals) < 0
            new_normals[flip] *= -1
        normals = new_normals
        # Before the motion: a rod's points then move along their section's normal.
        rods = on_rods(normals, section)
        if normal_motion_only:
            # Only the component along the normal: sliding along the surface removes no noise
            # and, at low noise, clumps points.
            disp = np.einsum("ij,ij->i", disp, normals)[:, None] * normals
        filtered = current + disp
        if refine:
            report(base + 0.9 / iterations, f"iteration {it + 1}/{iterations}: refining")
            filtered = inflation(filtered, current, INFLATION_NEIGHBOURS, normals, max_offset=sheet_offset)
            filtered = lrma_update(filtered, normals, LRMA_NEIGHBOURS, max_offset=sheet_offset)
        if cancel is not None and cancel.is_set():
            raise Cancelled("cancelled")
        moved = clamp_displacement(filtered, original[inliers], point_bound)
        if point_passes is not None:
            done = point_passes <= it
            moved[done] = current[done]
        if not move_points:
            # Normals only: the filtered points stand for the surface the normals come from.
            surface = moved
            break
        move = np.sum((moved - original[inliers]) ** 2, axis=1)
        if local is not None:
            # Each point's move against its own noise (the surface estimate reads a mixture:
            # a sphere whose noise grows from 0.2% to 2% across it, 0.82x the balls' median).
            move = move * (sigma / local.sigma) ** 2
        if it > 0 and np.sqrt(np.mean(move)) > stop_move:
            # Moved further than the noise: keep the previous pass. This pass's normals were
            # taken on exactly those points, so no normals pass is needed.
            iterations, stopped_early = it, True
            break
        current = moved
        if on_iteration is not None:
            now = given.copy()
            now[inliers] = current + centre
            on_iteration(it + 1, now)
    if (move_points and normals_pass and not stopped_early
            and (thin_walled or (auto_iterations and iterations < MAX_AUTO_ITERATIONS))):
        # The last moving pass took its normals on the points before it; a pass on the cleaned
        # points gives better ones (l_bracket at 0.6%: MSAE 0.166 -> 0.139; stool 0.420 -> 0.368),
        # and costs less than the passes auto iterations left out.
        _, new_normals, section = network_pass(predict, chunk, current, radius, rng, points_per_patch, None, cancel,
                                               own_sheet)
        new_normals[np.einsum("ij,ij->i", new_normals, normals) < 0] *= -1
        normals = new_normals
        rods = on_rods(normals, section)

    if move_points and smooth_heights and not own_sheet and np.isfinite(sigma) and sigma > 0:
        # Own-sheet passes are left as they are: a wall's two faces have agreeing normals.
        report(0.94, "averaging heights along the normals")
        reach = HEIGHT_AVERAGE_SIGMAS * (sigma if local is None else local.sigma)
        current = clamp_displacement(height_average(current, normals, reach, seed=seed), original[inliers],
                                     point_bound)
    plane_share = kept_share = 0.0
    plane_placed = np.zeros(len(current), bool)   # placed by a plane filter (the risk check)
    kept_input = np.zeros(len(current), bool)     # left at the input (the risk check)
    if risk_check:
        # The same passes (same seed, pass count, radius, sigma, bound) on the input nudged
        # along the normals give the network's divergence for the risk estimate. Normals only:
        # its one pass filtered the surface its normals come from; that surface is checked
        # (its heights not averaged: the nudged run's are not either).
        risk_sigma = quiet_sigma if local is None else local.sigma
        amplitude, offsets = probe_offsets(normals, risk_sigma, seed=seed + 2)
        probe = _run(original[inliers] + offsets, model, iterations, move_points=True,
                     patch_radius=patch_radius if move_points else radius,
                     patch_radius_fraction=fraction, points_per_patch=points_per_patch, orientation="none",
                     device=device, cancel=cancel, seed=seed, refine=refine, max_displacement=bound,
                     normal_motion_only=normal_motion_only, own_sheet=False, split_walls=False,
                     noise_sigma=sigma, rod_normals=rod_normals, risk_check=False, varying_noise=local,
                     smooth_heights=smooth_heights and move_points, progress=None if progress is None else
                     lambda f, m: progress(0.5 + 0.45 * min(f, 1.0), f"checking against plane filters: {m}"))
        if cancel is not None and cancel.is_set():
            raise Cancelled("cancelled")
        report(0.95, "checking against plane filters: choosing by region")
        # The probe ran centred on its own bounding box; its points come back in our frame.
        chosen, choice = choose_by_risk(original[inliers], normals, current if move_points else surface,
                                        probe.points, amplitude, offsets, risk_sigma, seed=seed, cancel=cancel)
        chosen = clamp_displacement(chosen, original[inliers], point_bound)
        plane_placed = (choice > 0) & (choice != KEPT_INPUT)
        # There the normal is the output's own plane; a rod's keeps its section's. Where the
        # input was kept, the network's normal: it was read from the same input patches.
        planar = np.flatnonzero(plane_placed & ~rods)
        if len(planar):
            normals[planar] = fitted_normals(chosen, planar, normals, float(np.median(risk_sigma)), seed=seed)
        if move_points:
            current = chosen
        else:
            surface = chosen
        plane_share = float(np.mean(plane_placed))
        kept_input = choice == KEPT_INPUT
        kept_share = float(np.mean(kept_input))
    if not move_points:
        report(0.95, "normals of the surface each point came from")
        normals = origin_normals(current, surface, normals, sigma if local is None else local.sigma,
                                 seed=seed, cancel=cancel)
    side = np.zeros(len(current), np.int8)
    if move_points and split_walls:
        report(0.9 if check_solid else 0.95, "looking for merged thin walls")
        split, side = split_merged_walls(original[inliers], current, normals, seed=seed, cancel=cancel)
        side[kept_input] = 0               # the input kept is no merged wall: it stays
        split[kept_input] = current[kept_input]
        if side.any():
            current = clamp_displacement(split, original[inliers], point_bound)
    solid_share = 0.0
    if check_solid:
        def sub_progress(start, width):
            return None if progress is None else (
                lambda f, m: progress(start + width * min(f, 1.0), f"checking against a solid's passes: {m}"))
        current, normals, solid, solid_side = own_sheet_or_solid(
            original[inliers], model, current, normals, sigma, bound, seed=seed, cancel=cancel,
            progress=sub_progress, patch_radius=patch_radius, patch_radius_fraction=fraction,
            points_per_patch=points_per_patch, device=device, refine=refine,
            normal_motion_only=normal_motion_only, rod_normals=rod_normals, split_walls=split_walls,
            smooth_heights=smooth_heights)
        # `rods` stays: the solid's run took its rods' normals from their sections too.
        side[solid] = solid_side[solid]      # the solid's run split its own walls
        solid_share = float(np.mean(solid))
    out_points = given.copy()          # unmoved points (outliers, normals only) bit-identical
    if move_points:
        out_points[inliers] = current + centre
        out_points[inliers[kept_input]] = given[inliers[kept_input]]   # bit-identical, not re-centred
    all_normals = np.empty_like(original)
    all_normals[inliers] = normals
    if outliers.any():
        # Outliers keep their position; they borrow the normal of the nearest inlier.
        _, near = cKDTree(out_points[inliers]).query(out_points[outliers], workers=-1)
        all_normals[outliers] = normals[near]
    report(0.97, "orienting normals")
    if viewpoint is not None and np.shape(viewpoint) == (3,):
        viewpoint = np.asarray(viewpoint, np.float64) - centre
    all_normals, faced = orient_normals(out_points - centre, all_normals, orientation, viewpoint, sources=original,
                                        thin_walled=thin_walled, with_input_side=True)
    if orientation == "outward" and side.any():
        # A point put back on one face of a wall faces away from the other: the Bayes sign
        # (its input lay on that side of the merged sheet).
        rows = np.flatnonzero(side)
        want = side[rows, None] * normals[rows]
        flip = np.einsum("ij,ij->i", all_normals[inliers[rows]], want) < 0
        all_normals[inliers[rows[flip]]] *= -1
    if move_points and split_walls and len(faced.idx) and np.isfinite(sigma):
        # Points of unsplit walls thinner than the noise now face their input side; they go
        # to that face so that their shading and position agree (`sheets.seat_on_facing_face`).
        # Where a plane filter placed them, only inside a region turned as a whole (a thin tip);
        # scattered turned points there are relief on one surface (column_head at 0.6%, where
        # 98% of the points orientation turned by their input side were placed so: all seated,
        # Chamfer 4.09 -> 4.16). Where the input was kept, nothing was filtered to seat.
        row_of = np.full(len(original), -1)
        row_of[inliers] = np.arange(len(inliers))
        rows = row_of[faced.idx]
        keep = np.flatnonzero(rows >= 0)
        keep = keep[(side[rows[keep]] == 0) & ~kept_input[rows[keep]]]
        on_plane = np.flatnonzero(plane_placed[rows[keep]])
        if len(on_plane):
            turned = np.zeros(len(current), bool)
            turned[rows[keep]] = True
            inside = in_faced_region(current, turned, rows[keep[on_plane]])
            keep = np.delete(keep, on_plane[~inside])
        if len(keep):
            rows = rows[keep]
            seated = seat_on_facing_face(current[rows], all_normals[faced.idx[keep]], faced.median[keep],
                                         faced.variance[keep], sigma)
            out_points[inliers[rows]] = clamp_displacement(
                seated, original[inliers[rows]], point_bound if local is None else point_bound[rows]) + centre
    rim_share = 0.0
    # Outward normals of closed or thin-walled objects only: the test reads a rim's two faces
    # from normals facing apart, and an open scan's border is where the scan ends, not a rim
    # (bun000, plane.laz and the vegetation scan read as open: `orient.SEEN_CLOSED_SHARE`).
    if (move_points and rim_normals and orientation == "outward" and (thin_walled or faced.closed)
            and np.isfinite(sigma) and sigma > 0):
        report(0.98, "normals at the rims of thin parts")
        rim, outward = rim_outward_normals(out_points[inliers] - centre, all_normals[inliers], sigma, cancel=cancel)
        all_normals[inliers[rim]] = outward
        rim_share = float(np.mean(rim))
    all_normals /= np.linalg.norm(all_normals, axis=1, keepdims=True)
    displacement = np.linalg.norm(out_points - given, axis=1)
    wall_side = np.zeros(len(given), np.int8)
    wall_side[inliers] = side
    report(1.0, "done")
    return DenoiseResult(points=out_points, normals=all_normals.astype(np.float32), outliers=outliers,
                         displacement=displacement, seconds=time.time() - t0, iterations=iterations,
                         noise_sigma=sigma, ran_on=ran_on,
                         displacement_bound=float(np.max(point_bound)) if move_points else float("inf"),
                         thin_walled=thin_walled, solid_share=solid_share,
                         stopped_early=stopped_early, split_share=float(np.mean(side != 0)) if len(side) else 0.0,
                         wall_side=wall_side,
                         rod_share=float(np.mean(rods)) if len(rods) else 0.0, plane_share=plane_share,
                         kept_share=kept_share, scene_radius=scene_radius,
                         rim_share=rim_share,
                         noise_range=None if local is None else tuple(float(q) for q in
                                                                    np.quantile(local.sigma, NOISE_RANGE_QUANTILES)))

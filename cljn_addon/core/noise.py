"""Noise level of a cloud, estimated from the cloud itself.

Used to bound how far denoising may move a point: whatever the network predicts (for
example on a thin part whose two sides share a patch, or a wall a few centimetres behind a
car), no point leaves a ball of a few sigma around where it was scanned, so a failure can
under-clean but never wreck the scan.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.spatial import cKDTree

from .patches import PatchSource, make_patches, pca_frames
from .sheets import MAD_TO_SIGMA, fit_two_sheets, quadric_design

NOISE_SAMPLE = 4_000           # patches the estimate is taken over (random centres)
NOISE_PATCH_POINTS = 256
DISPLACEMENT_BOUND_SIGMAS = 3.0
SHEET_FIT_ROUNDS = 4
MIN_FIT_POINTS = 16
FIT_BALL_POINTS = 100
SHEET_SIGMAS = 2.5             # points within this many sigma of the fit are the centre's sheet
TRUNCATED_MAD = 0.9766         # median |x| of a Gaussian cut at 2.5 sigma, over 0.6745 sigma
QUANTUM_SAMPLE = 20_000        # coordinates per axis looked at to find a storage grid
TWO_SHEET_KURTOSIS = 2.6       # flat-topped one-sheet residuals: two sides, not a crease
THIN_WALLED_SHARE = 0.35       # share of balls across two sides that makes a thin-walled object
# Relief at the noise's own scale reads as noise in every ball it fills (column_head at 0.6%:
# the median reads 1.61x sigma); the noise does not change from ball to ball, the relief does,
# so the quietest balls read the noise alone. The 10th percentile of the balls' sigmas reads
# 0.88-0.89x sigma on a smooth solid (cylinder, icosahedron at 0.6%; 50K points): scaled back.
QUIET_QUANTILE = 0.10
QUIET_SCALE = 1.12
# A scene's patch-radius ball (5% of a 150 m street is 7.7 m) holds cars, walls and poles at
# once: a quadric cannot follow them, and the structure reads as noise (2 cm of noise read as
# 9.1 cm there, 76 cm at 300 m), which then sets the bound and the passes. Where that ball spans
# more than `SCENE_SPAN` times the ball of `NOISE_PATCH_POINTS` points, the noise is read in the
# small balls too, and stands where the patch-radius balls read over `SCENE_RATIO` times it.
# Objects read 1.0-1.6x (relief at the noise's scale: column_head), and the eval's 50K-point
# clouds do not reach the span at all.
SCENE_SPAN = 2.0
SCENE_RATIO = 2.0
# A dense object's small balls are only a few sigmas wide, and there the quadric follows the
# noise and reads it low (a sphere of 400K points at 2%: balls 1.1 sigma wide read 0.42x sigma,
# 0.6x at 1.4 sigma, 0.91x at 3.7), so the patch balls' reading looked like structure and the
# object was read as a scene with 0.17-0.61x its noise. A scene's small balls are wide against
# the noise they read (streets of 40K-1M points: 27-122x); objects of 200K-1M points 2.3-2.8x.
SCENE_BALL_SIGMAS = 8.0
SURFACE_NEIGHBOURS = 12        # neighbours along the surface each point is compared with
SURFACE_REACH_SIGMAS = 5.0     # how far off the surface (in pilot sigmas) those neighbours are looked for
SURFACE_CANDIDATES = 1000      # nearest points searched for them


def coordinate_quantum(points, sample=QUANTUM_SAMPLE, seed=0):
    """(3,) grid step of coordinates stored on a grid (LAS/LAZ integers x scale), or None.

    Only a grid coarse enough to tie many coordinates counts (fewer distinct values than half
    the sample on some axis): that is when the median residual of a fit is 0 and the noise
    estimate needs dithering.
    """
    pts = np.asarray(points, np.float64)
    rng = np.random.default_rng(seed)
    vals = pts[rng.choice(len(pts), size=min(sample, len(pts)), replace=False)]
    steps, tied = [], False
    for axis in range(3):
        v = np.unique(vals[:, axis])
        if len(v) < 2:
            return None
        gaps = np.diff(v)
        step = float(gaps[gaps > 1e-9 * (v[-1] - v[0])].min())
        on_grid = np.abs((v - v[0]) / step - np.round((v - v[0]) / step)) < 1e-3
        if on_grid.mean() < 0.99:
            return None
        steps.append(step)
        tied |= len(v) < 0.5 * len(vals)
    return np.array(steps) if tied else None


class NoiseEstimate(NamedTuple):
    sigma: float          # scanner noise, in the cloud's units
    two_sheet_share: float  # share of the balls that straddle both sides of a thin part
    quiet_sigma: float = float("nan")  # the noise read in the quietest balls (`QUIET_QUANTILE`)
    ball_centres: np.ndarray | None = None  # (B, 3) the balls' centres, for `local_noise`
    ball_sigmas: np.ndarray | None = None   # (B,) the noise each ball read
    scene_radius: float = float("nan")      # a scene's: the radius of the balls it was read in


def estimate_noise_sigma(points, radius, sample=NOISE_SAMPLE, seed=0) -> float:
    """Robust sigma of the scanner noise, in the cloud's units (see `estimate_noise`)."""
    return estimate_noise(points, radius, sample, seed).sigma


def estimate_noise(points, radius, sample=NOISE_SAMPLE, seed=0) -> NoiseEstimate:
    """Robust sigma of the scanner noise, and how thin-walled the cloud is.

    In balls of the patch radius around random points, a quadric height field is fitted in
    each ball's PCA frame (so curvature does not count as noise), robustly: starting from the
    half of the ball nearest the centre's height and refitting on the points within 2.5
    sigma, so that the far side of a thin part (a plate, a wall, a car in front of a wall)
    does not count as noise either. Sigma is the median over balls of the scaled median
    absolute residual. Where the two sides of a part are only 2-3 sigma apart that fit cannot
    tell them apart; each ball is also fitted with two parallel sheets (`sheets.fit_two_sheets`),
    and on a thin-walled object (many such balls) their shared sigma is used in those balls.

    Coordinates stored on a coarse grid (a LAS file at 1 cm) tie so often that the median
    residual is 0: they are dithered by a uniform step of the grid first and the dither's
    variance (step^2 / 12) taken off again.
    """
    pts = np.asarray(points, np.float64)
    if len(pts) < 10 or not radius > 0:
        return NoiseEstimate(0.0, 0.0, 0.0)
    rng = np.random.default_rng(seed)
    quantum = coordinate_quantum(pts, seed=seed)
    if quantum is not None:
        pts = pts + rng.uniform(-0.5, 0.5, pts.shape) * quantum
        dithered, share, quiet, centres, balls, scene = _estimate_at_scale(pts, radius, sample, rng)
        dither = np.mean(quantum ** 2) / 12.0
        return NoiseEstimate(float(np.sqrt(max(dithered ** 2 - dither, 0.0))), share,
                             float(np.sqrt(max(quiet ** 2 - dither, 0.0))), centres,
                             None if balls is None else np.sqrt(np.maximum(balls ** 2 - dither, 0.0)), scene)
    return NoiseEstimate(*_estimate_at_scale(pts, radius, sample, rng))


def _estimate_at_scale(pts, radius, sample, rng):
    """`_estimate` in balls of `radius`, or in balls of `NOISE_PATCH_POINTS` points where the
    cloud is a scene (`SCENE_SPAN`, `SCENE_RATIO`, `SCENE_BALL_SIGMAS`); last, those balls' radius on a scene, else nan."""
    *estimate, local_radius = _estimate(pts, radius, sample, rng)
    if local_radius * SCENE_SPAN < radius:
        *local, _ = _estimate(pts, local_radius, sample, rng)
        if local[0] > 0 and estimate[0] > SCENE_RATIO * local[0] and local_radius >= SCENE_BALL_SIGMAS * local[0]:
            # Where the scene is sparse those balls span metres and hold structure too (300 m
            # of street, 40K points: 8.7 cm read for 2 cm); its quietest balls (open ground, a
            # wall) hold one surface each, and read the noise (2.2 cm).
            local[0] = local[2]
            return (*local, local_radius)
    return (*estimate, float("nan"))


def _estimate(pts, radius, sample, rng):
    """(sigma, share of two-sheet balls, quiet sigma, ball centres, ball sigmas, and the
    median radius of a ball that holds `NOISE_PATCH_POINTS` points)."""
    centres = pts[rng.choice(len(pts), size=min(sample, len(pts)), replace=False)]
    # A sparse cloud gets wider balls. Whether its balls hold two sheets is read where a ball
    # holds `FIT_BALL_POINTS`; its noise where a ball holds as many distinct points as the fit
    # draws (`NOISE_PATCH_POINTS`): a ball padded with repeats of its points reads low (a 10K
    # sphere at 1%: 0.86x sigma, the quietest balls 0.63x; with distinct points 0.98x, 0.95x),
    # while a ball that wide no longer sees a thin wall's two sheets (a cup at 5K points).
    counts = [min(FIT_BALL_POINTS, len(pts) - 1), min(NOISE_PATCH_POINTS, len(pts) - 1)]
    reach, _ = cKDTree(pts).query(centres[:500], k=[c + 1 for c in counts], workers=-1)
    local_radius = float(np.median(reach[:, 1]))
    share_radius, sigma_radius = (max(float(radius), float(r)) for r in np.median(reach, axis=0))
    fits = _ball_fits(pts, share_radius, centres, rng)
    if fits is None:
        return 0.0, 0.0, 0.0, None, None, local_radius
    scale, two, two_sigma, fitted = fits
    share = float(two.mean())
    fit_radius = share_radius
    if sigma_radius > share_radius:
        wide = _ball_fits(pts, sigma_radius, centres, rng)
        if wide is not None:
            (scale, two, two_sigma, fitted), fit_radius = wide, sigma_radius
    # A ball across a part ~2-3 sigma thick: the robust fit cannot tell the two sides apart
    # and reads the part's thickness as noise; the two-sheet mixture can. Only where such
    # balls are common (a thin-walled object): at high noise a few balls of any shape split
    # their noise in two and would pull the estimate down.
    if share >= THIN_WALLED_SHARE:
        scale[two] = np.minimum(scale[two], two_sigma[two])
    quiet = QUIET_SCALE * float(np.quantile(scale, QUIET_QUANTILE))
    return (float(np.median(scale) * fit_radius), share, quiet * fit_radius, centres[fitted], scale * fit_radius,
            local_radius)


def _ball_fits(pts, radius, centres, rng):
    """Per ball of `radius` round `centres` that holds enough points: (robust quadric sigma,
    whether two parallel sheets fit it better, their shared sigma), in radius units, and which
    centres those balls are (a bool mask); None if no ball holds enough points."""
    source = PatchSource(pts, radius, NOISE_PATCH_POINTS, rng)
    local, _, counts = make_patches(source, centres, rng)
    dense = counts >= MIN_FIT_POINTS
    local = local[dense].astype(np.float64)
    distinct = np.minimum(counts[dense], NOISE_PATCH_POINTS)     # the rest is padding
    if len(local) == 0:
        return None
    z = local[..., 2]
    design = quadric_design(local)
    # Start from the half of the ball nearest the centre's own height, so that where a thin
    # part puts its other side in the ball the fit locks onto the centre's side.
    keep = np.abs(z) <= np.median(np.abs(z), axis=1, keepdims=True)
    for _ in range(SHEET_FIT_ROUNDS):
        w = keep.astype(np.float64)
        normal_eq = np.einsum("mn,mni,mnj->mij", w, design, design) + 1e-9 * np.eye(6)
        coef = np.linalg.solve(normal_eq, np.einsum("mn,mni,mn->mi", w, design, z)[..., None])[..., 0]
        residual = np.abs(z - np.einsum("mni,mi->mn", design, coef))
        kept = np.where(keep, residual, np.nan)
        scale = MAD_TO_SIGMA * np.nanmedian(kept, axis=1, keepdims=True) / TRUNCATED_MAD
        keep = residual <= SHEET_SIGMAS * scale
    # Six fitted coefficients take six degrees of freedom from the distinct kept points.
    used = distinct * keep.mean(axis=1)
    scale = scale[:, 0] * np.sqrt(used / np.maximum(used - 6.0, 1.0))
    fit = fit_two_sheets(local)
    two = fit["two"] & (fit["kurtosis"] < TWO_SHEET_KURTOSIS)
    return scale, two, fit["sigma"], dense


def surface_noise_sigma(points, radius, pilot_sigma, sample=NOISE_SAMPLE, seed=0) -> float:
    """Noise sigma from how far points sit off a plane through their nearest neighbours
    along the surface: a second estimate, for deciding when a cloud has moved enough.

    Each sampled point is compared with the plane fitted to its `SURFACE_NEIGHBOURS` nearest
    neighbours by distance in its tangent plane (the PCA frame of its patch-radius ball), at
    any height up to `SURFACE_REACH_SIGMAS` pilot sigmas: chosen by tangential distance, the
    neighbours' heights are not truncated the way a ball's are. The residual, scaled by the
    fit's leverage, is N(0, sigma^2) wherever the surface is smooth over a few point
    spacings, so creases and fine detail, which take a few percent of those tiny
    neighbourhoods but most balls of the patch radius, hardly bias the median: on detail and
    creases at 0.6% (star_smooth, star prism, column_head) it reads 1.03-1.47x sigma where
    `estimate_noise` reads 1.17-1.50x, on solids at 2% 0.88-0.96x (0.86-0.93x). It reads high
    where another face lies within its reach (thin prisms at 2%: up to 2x) and does not
    separate the two sides of a thin part (a plate at 0.6%: 1.68x), so thin-walled objects
    keep `estimate_noise`. Dense clouds are thinned at random first (the noise statistics
    do not change) so that the candidate search reaches the whole height range.
    """
    offsets = surface_offsets(points, radius, pilot_sigma, sample, seed)
    if offsets is None:
        return float("nan")
    return float(MAD_TO_SIGMA * np.median(np.abs(offsets[1])))


def surface_offsets(points, radius, pilot_sigma, sample=NOISE_SAMPLE, seed=0):
    """(sampled points, each one's height off the plane of its neighbours along the surface,
    in units whose spread is the noise sigma): `surface_noise_sigma` before its median; None
    where too few points are there to read it."""
    pts = np.asarray(points, np.float64)
    k = SURFACE_NEIGHBOURS
    if len(pts) < 4 * k or not radius > 0:
        return None
    rng = np.random.default_rng(seed)
    pilot = pilot_sigma if np.isfinite(pilot_sigma) and pilot_sigma > 0 else 0.0
    reach = max(SURFACE_REACH_SIGMAS * pilot, 0.3 * float(radius))
    tree = cKDTree(pts)
    probe = pts[rng.choice(len(pts), size=min(256, len(pts)), replace=False)]
    crowd = float(np.mean(tree.query_ball_point(probe, reach, return_length=True, workers=-1)))
    if crowd > SURFACE_CANDIDATES / 2:
        keep = max(int(len(pts) * SURFACE_CANDIDATES / 2 / crowd), 8 * k)
        pts = pts[rng.choice(len(pts), size=keep, replace=False)]
    picked = rng.choice(len(pts), size=min(sample, len(pts)), replace=False)
    centres = pts[picked]
    source = PatchSource(pts, radius, NOISE_PATCH_POINTS, rng)
    frames = pca_frames(source.gather(centres, rng)[0])
    dist, idx = source.full_tree.query(centres, k=min(SURFACE_CANDIDATES, len(pts)), distance_upper_bound=reach, workers=-1)
    valid = np.isfinite(dist) & (idx != picked[:, None])
    idx = np.where(valid, idx, 0)
    local = np.einsum("mij,mnj->mni", frames, pts[idx] - centres[:, None])
    tangential = np.where(valid, np.hypot(local[..., 0], local[..., 1]), np.inf)
    nearest = np.argsort(tangential, axis=1)[:, :k]
    enough = np.isfinite(np.take_along_axis(tangential, nearest, axis=1)).all(axis=1)
    if not enough.any():
        return None
    nb = np.take_along_axis(local, nearest[..., None], axis=1)[enough]
    design = np.concatenate([np.ones(nb.shape[:2] + (1,)), nb[..., :2]], axis=2)
    inverse = np.linalg.inv(np.einsum("mni,mnj->mij", design, design) + 1e-12 * np.eye(3))
    offset = np.einsum("mj,mnj,mn->m", inverse[:, 0], design, nb[..., 2])    # the plane's height at the centre
    # The centre sits at height 0; its residual has variance sigma^2 (1 + leverage).
    return centres[enough], offset / np.sqrt(1.0 + inverse[:, 0, 0])


def clamp_displacement(moved, original, bound):
    """Pull every point back to within `bound` (a number, or one per point) of its original
    position (same direction)."""
    delta = moved - original
    dist = np.linalg.norm(delta, axis=1)
    bound = np.broadcast_to(bound, dist.shape)
    over = dist > bound
    if not over.any():
        return moved
    out = moved.copy()
    out[over] = original[over] + delta[over] * (bound[over] / dist[over])[:, None]
    return out


# A scan's noise can change across it (a LiDAR's grows with range; merged scans differ). Each
# point's own noise is read over the `LOCAL_BALLS` balls nearest it: their median, and their
# quiet quantile as the whole cloud's (balls read edges, relief and a thin part's two faces as
# noise too; over many balls one such ball does not set it).
LOCAL_BALLS = 128
# The noise varies across a cloud when two readings agree. The balls: the 90th percentile of
# the points' local quiet noise reads this many times the 10th (the quiet quantile: edges and
# relief raise a region's median more than its quietest balls). A sphere whose noise grows from
# 0.2% to 2% across it reads 4.84x, a torus 0.3% to 1.5% 3.23x, a sphere 0.3% to 0.9% 2.17x,
# a star prism 0.2% to 2% 2.28x; the eval's clouds that are not thin-walled at most 1.76x
# (column_head at 0.6%). But relief at the noise's scale, uneven over a shape, reads as varying
# noise too: column_head at 20K points and 0.6% reads 2.12x, a gear at 5K points and 1.5%
# (its teeth's edges in most balls) 2.15x.
VARYING_NOISE_RATIO = 2.0
# Along the surface (`surface_offsets`: each point against the plane of its 12 neighbours,
# which relief hardly bends), the same percentiles of each point's local noise (over the
# `LOCAL_SURFACE_SAMPLES` samples nearest it) must read this many times apart as well: the
# clouds above that vary read 1.81-3.71x (the star prism the lowest), column_head 1.40x, the
# gear 1.30x. Alone this reading is no test: where faces come within its reach it reads high
# (column_head at 2%: 1.79x, where the balls read 1.21x).
VARYING_SURFACE_RATIO = 1.65
LOCAL_SURFACE_SAMPLES = 256


class LocalNoise(NamedTuple):
    sigma: np.ndarray     # (N,) the median of the sigmas the nearest balls read
    quiet: np.ndarray     # (N,) their quiet sigma (`QUIET_QUANTILE`, `QUIET_SCALE`)

    def varies(self) -> bool:
        """Whether the balls read noise that changes across the cloud (`VARYING_NOISE_RATIO`);
        `varying_local_noise` asks the surface as well."""
        low, high = np.quantile(self.quiet, [0.1, 0.9])
        return bool(high > VARYING_NOISE_RATIO * low)


def local_noise(points, estimate, balls=LOCAL_BALLS):
    """The noise near each point of `points` (`LocalNoise`), read by the `balls` balls of
    `estimate` (`estimate_noise`) nearest the point's nearest ball; None without balls."""
    if estimate.ball_centres is None or len(estimate.ball_centres) == 0:
        return None
    centres = np.asarray(estimate.ball_centres, np.float64)
    tree = cKDTree(centres)
    k = min(balls, len(centres))
    _, idx = tree.query(centres, k=k, workers=-1)
    near = np.asarray(estimate.ball_sigmas)[np.asarray(idx).reshape(len(centres), k)]
    median = np.median(near, axis=1)
    quiet = QUIET_SCALE * np.quantile(near, QUIET_QUANTILE, axis=1)
    _, nearest = tree.query(np.asarray(points, np.float64), workers=-1)
    return LocalNoise(median[nearest], quiet[nearest])


def surface_noise_varies(points, radius, pilot_sigma, seed=0) -> bool:
    """Whether the noise read along the surface near each point (`surface_offsets`, over the
    `LOCAL_SURFACE_SAMPLES` samples nearest it) changes across the cloud by
    `VARYING_SURFACE_RATIO` between its 10th and 90th percentiles."""
    read = surface_offsets(points, radius, pilot_sigma, seed=seed)
    if read is None or len(read[0]) < LOCAL_SURFACE_SAMPLES:
        return False
    samples, offsets = read
    tree = cKDTree(samples)
    _, idx = tree.query(samples, k=LOCAL_SURFACE_SAMPLES, workers=-1)
    spread = np.median(np.abs(offsets)[idx], axis=1)
    _, nearest = tree.query(np.asarray(points, np.float64), workers=-1)
    low, high = np.quantile(spread[nearest], [0.1, 0.9])
    return bool(high > VARYING_SURFACE_RATIO * low)


def varying_local_noise(points, radius, estimate, seed=0):
    """The noise near each point (`local_noise`) where it changes across the cloud by both
    readings (`LocalNoise.varies`, `surface_noise_varies`); None on a cloud of one noise."""
    read = local_noise(points, estimate)
    if read is None or not read.varies():
        return None
    return read if surface_noise_varies(points, radius, estimate.sigma, seed=seed) else None

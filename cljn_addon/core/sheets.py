"""Two sheets in one patch: find them, and keep the centre point's own.

A patch of 5% of the diagonal around a point on a wall, a plate or a tube holds both sides of
the part. The network never saw such patches in training (one surface per patch), and left
with both it pulls the two sides together. Here each patch is fitted, in its PCA frame, with
two parallel quadric height fields z = q(x, y) and z = q(x, y) + h under Gaussian noise of one
shared sigma (a two-component mixture, fitted by EM, vectorised over patches). Where the
mixture explains the patch much better than one quadric, its sheets lie apart by more than
their noise and over the same footprint (not side by side, as at a crease), the patch is a
two-sheet patch, and the points of the other sheet are replaced by points of the centre's own
sheet before the network sees it. A crease can still pass for two sheets; the engine uses
this only on objects that are thin-walled as a whole (`noise.estimate_noise`).
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .errors import Cancelled

EM_ROUNDS = 12
MIN_SHARE = 0.15           # each sheet holds at least this share of the patch
MIN_GAP_SIGMAS = 2.0       # sheets at least this many noise sigmas apart
MIN_TOTAL_GAIN = 6.0       # log-likelihood gain of the mixture over one quadric (nats)
MAX_FOOTPRINT_SHIFT = 0.5  # centroids of the two sheets apart by at most this x their xy spread


def quadric_design(local):
    """(M, n, 6) design of the height field z = a x^2 + b xy + c y^2 + d x + e y + f."""
    x, y = local[..., 0], local[..., 1]
    return np.stack([x * x, x * y, y * y, x, y, np.ones_like(x)], axis=-1)


def fit_two_sheets(local, rounds=EM_ROUNDS):
    """Fit one and two parallel quadric sheets to each patch (points in their PCA frame).

    local: (M, n, 3) patch points, the centre at the origin, z along the rough normal.
    Returns a dict of (M,) arrays: two (bool: two sheets found), sigma (the mixture's noise, in
    patch units), kurtosis (of the one-quadric residuals), centre_upper (the centre lies
    nearer the sheet q + h); and (M, n) `upper`, each point's probability of lying on q + h.
    """
    x = np.asarray(local, np.float64)
    m, n, _ = x.shape
    z = x[..., 2]
    design = quadric_design(x)
    gram = np.einsum("mni,mnj->mij", design, design)
    rhs_q = np.einsum("mni,mn->mi", design, z)
    coef = np.linalg.solve(gram + 1e-9 * np.eye(6), rhs_q[..., None])[..., 0]
    r1 = z - np.einsum("mni,mi->mn", design, coef)
    var1 = np.maximum(np.mean(r1 ** 2, axis=1), 1e-18)
    # Two sheets make the one-sheet residuals flat-topped (kurtosis 2.3 for sheets 2.5 sigma
    # apart; one Gaussian sheet 3); a crease misfit by one quadric makes them heavy-tailed.
    kurtosis = np.mean(r1 ** 4, axis=1) / var1 ** 2
    # Start from the split by the sign of the one-sheet residual.
    upper = (r1 > 0).astype(np.float64)
    for _ in range(rounds):
        # M-step of the mixture: q and h minimise sum (1-g)(z-q)^2 + g(z-q-h)^2 (g = upper).
        lhs = np.zeros((m, 7, 7))
        lhs[:, :6, :6] = gram
        cross = np.einsum("mni,mn->mi", design, upper)
        lhs[:, :6, 6] = cross
        lhs[:, 6, :6] = cross
        lhs[:, 6, 6] = upper.sum(axis=1)
        lhs += 1e-9 * np.eye(7)
        rhs = np.concatenate([rhs_q, (upper * z).sum(axis=1, keepdims=True)], axis=1)
        coef2 = np.linalg.solve(lhs, rhs[..., None])[..., 0]
        r_low = z - np.einsum("mni,mi->mn", design, coef2[:, :6])
        h = coef2[:, 6:7]
        r_up = r_low - h
        share = np.clip(upper.mean(axis=1, keepdims=True), 0.02, 0.98)
        var = np.maximum(np.mean((1 - upper) * r_low ** 2 + upper * r_up ** 2, axis=1, keepdims=True), 1e-18)
        logit = np.log(share / (1 - share)) + (r_low ** 2 - r_up ** 2) / (2 * var)
        upper = 1.0 / (1.0 + np.exp(-np.clip(logit, -50, 50)))
    share = np.clip(upper.mean(axis=1, keepdims=True), 1e-6, 1 - 1e-6)
    lik = ((1 - share) * np.exp(-r_low ** 2 / (2 * var)) + share * np.exp(-r_up ** 2 / (2 * var))) / np.sqrt(var)
    ll2 = np.mean(np.log(np.maximum(lik, 1e-300)), axis=1)
    ll1 = -0.5 * np.log(var1) - 0.5
    gain = ll2 - ll1
    sigma = np.sqrt(var[:, 0])
    gap = np.abs(h[:, 0]) / sigma
    small = np.minimum(share[:, 0], 1 - share[:, 0])
    # Two faces meeting at a crease also fit two offset quadrics better than one, but side by
    # side; the two sides of a thin part lie over the same footprint.
    xy = x[..., :2]
    w_up = upper / np.maximum(upper.sum(axis=1, keepdims=True), 1e-9)
    w_low = (1 - upper) / np.maximum((1 - upper).sum(axis=1, keepdims=True), 1e-9)
    apart = np.linalg.norm(np.einsum("mn,mnc->mc", w_up, xy) - np.einsum("mn,mnc->mc", w_low, xy), axis=1)
    spread = np.sqrt(np.mean(np.sum((xy - xy.mean(axis=1, keepdims=True)) ** 2, axis=-1), axis=1) / 2)
    footprint = apart / np.maximum(spread, 1e-12)
    # A crease seen from above its edge is a V: one fitted sheet near the edge line, the
    # other out on the arms. The sides of a thin part are both present near the centre and
    # out at the rim alike.
    r = np.linalg.norm(xy, axis=-1)
    inner = r <= np.median(r, axis=1, keepdims=True)
    share_in = (upper * inner).sum(axis=1) / np.maximum(inner.sum(axis=1), 1)
    share_out = (upper * ~inner).sum(axis=1) / np.maximum((~inner).sum(axis=1), 1)
    footprint = np.maximum(footprint, np.abs(share_in - share_out) / 0.5)
    two = ((gain * n > MIN_TOTAL_GAIN) & (gap > MIN_GAP_SIGMAS) & (small > MIN_SHARE)
           & (footprint < MAX_FOOTPRINT_SHIFT))
    # The centre (origin) belongs to the sheet whose height at (0, 0) is nearer to 0.
    q0 = coef2[:, 5]
    centre_upper = np.abs(q0 + h[:, 0]) < np.abs(q0)
    return dict(two=two, sigma=sigma, kurtosis=kurtosis, centre_upper=centre_upper, upper=upper)


def own_sheet_patches(local, framed, rng):
    """local: (M, n, 3) patches (any rotation); framed: the same in their PCA frames.

    Returns (patches, fit): in patches found to hold two sheets, the points of the sheet the
    centre is not on are replaced by random points of the centre's sheet; other patches come
    back unchanged.
    """
    fit = fit_two_sheets(framed)
    out = np.array(local, copy=True)
    rows = np.flatnonzero(fit["two"])
    if len(rows) == 0:
        return out, fit
    own = (fit["upper"][rows] > 0.5) == fit["centre_upper"][rows, None]
    n = local.shape[1]
    # For each slot off the centre's sheet, a random point of it: own points ranked first.
    order = np.argsort(rng.random((len(rows), n)) + (~own) * 2.0, axis=1)
    count = np.maximum(own.sum(axis=1), 1)
    rank = np.floor(rng.random((len(rows), n)) * count[:, None]).astype(np.int64)
    src = np.where(own, np.arange(n)[None, :], np.take_along_axis(order, rank, axis=1))
    out[rows] = np.take_along_axis(np.asarray(local)[rows], src[..., None], axis=1)
    return out, fit


# Walls merged by denoising: put each point back on its own face.
#
# Where a wall is under ~2.5 noise sigmas thick no patch tells its faces apart (above), and
# the network draws them into one sheet at the mid-surface: further from either face than
# the noisy input was (a 1.5% plate at 0.8% noise: Chamfer 10.3 against 6.5). A patch of 128
# points cannot see the two faces, but many patches together can: about the merged sheet,
# the input heights of one noisy sheet are Gaussian (kurtosis 3) and those of two faces +-a
# are flat-topped (kurtosis 3 - 2 r^2, r = a^2 / variance; 2.58 for a wall 1.84 sigma
# thick). Pooled over thousands of points that difference is many standard errors
# (sqrt(24 / n)), and where the denoised sheet is much thinner than the input's two faces
# are apart, the faces were merged: each point goes to the face on its own side of the
# sheet, a from the local input spread. Its side is also the likeliest outward sign.
SPLIT_POOLS = (1_500, 5_000, 50_000)  # pooled points per test, smallest first; the last is a random sample
SPLIT_CENTRES = 1_500                 # pool centres (each point belongs to its nearest)
SPLIT_Z = 4.0                         # flat-topped by this many standard errors of the kurtosis
SPLIT_MIN_R = 0.3                     # and a^2 >= 0.3 x the height variance (faces >= 1.3 sigma apart)
# The whole-cloud pool is one test, not thousands, so it may be laxer: walls ~1.3 sigma thick
# (r 0.25-0.3) pass there at 20K points, while single sheets stay above kurtosis 2.95 (r < 0.16).
SPLIT_Z_CLOUD = 3.0
SPLIT_MIN_R_CLOUD = 0.2
SPLIT_LOCAL_EXCESS = 0.15             # found by the whole cloud alone: split where local a^2 > 0.15 x noise var
SPLIT_COLLAPSE = 0.8                  # merged: the output's local height spread < 0.8 a
# The merged sheet's point and normal: centroid and PCA normal of a point's nearest outputs,
# at two scales; the one whose input heights are the most flat-topped (the two faces show
# best) is used. The output keeps low-frequency ripples that follow the input's noise, and a
# small neighbourhood's sheet follows them: 64 outputs of the stool's seat at 1.5% and 50K
# points span ~1 sigma, the normal tilts 14 degrees on average and the seat's two faces hide
# (kurtosis 2.95, 2.74 expected; not split, Chamfer 8.46; with 128: 4.88). A wider one does
# not follow a wall's real bends: the open box at 20K points and 0.6% splits 87% with 64
# (Chamfer 6.93), 43% with 128 (8.14). Picking the flatter-topped heights chose the better
# scale on every thin cloud checked at 20K and 50K points but one (5.91 against 5.89).
SHEET_SCALES = (64, 128)
SIDE_POOL = 64                        # nearest outputs among which the side neighbours are found
SHEET_CHUNK = 25_000                  # rows per chunk of the sheet fits (up to 128 x 3 floats each)
LOCAL_NEIGHBOURS = 200                # the local face offset a: input spread over this many
SIDE_NEIGHBOURS = 8                   # nearest along the sheet whose sides are compared
SPLIT_MAX_AGREEMENT = 0.54            # two faces: neighbours on the point's own side 50% of the time (scans: 0.61)
SPLIT_MIN_SHARE = 0.05                # split only where >= 5% of the cloud merged (see below)
# A wall a few sigma thick whose faces the passes kept apart (a gear 4 sigma thick at 2%
# noise) has flat-topped heights too: the noise tails that crossed to the nearer face land in
# the shoulders (whole-cloud kurtosis 2.91, z 4.3 at 50K points); the fourth moment feels
# that up to faces ~8 sigma apart. Such a wall's other face shows in the output along the
# normal; a merged wall has none. Points with output 1.25-9.25 height standard deviations
# along their normal, either way, are left out of the tests and the split.
OPPOSITE_STEPS = np.arange(2.25, 8.3, 1.0)   # probe ball centres along the normal (overlapping)
OPPOSITE_PROBE = 1.0                   # probe ball radius
# A face: a probe holds OPPOSITE_FACE_SHARE of the outputs that the same ball around the point
# holds, and at least OPPOSITE_MIN_POINTS. A partly merged wall's other face (~1 sd away: a
# plate at 0.6% after one pass) reaches the nearest probe with its tail only; counted at 3
# points whatever the ball held, that tail left the plate unsplit (Chamfer 2.35 -> 3.00). A
# fixed floor of 8 was too many where the ball itself holds ~8 (an L-bracket 3.7 sigma thick at
# 0.8% and 50K points: its kept-apart walls went unseen, 34% was split, Chamfer 3.14 -> 3.68,
# sign 95% -> 80%). At 0.5x the stool's merged seat at 1.5% went unsplit (legs under the seat
# read as a far face: Chamfer 4.91 -> 8.54); 0.3x with a floor of 3 missed the L-bracket's far
# face at 0.6% (7% split, 2.37 -> 2.47).
OPPOSITE_FACE_SHARE = 0.4
OPPOSITE_MIN_POINTS = 3
OPPOSITE_SAMPLE = 50_000               # points probed; the rest take their nearest probed point's answer
MIN_POOL_SHARE = 0.25                  # a local pool tested only if this share of it is usable
SPLIT_CHUNK = 50_000                  # points per neighbour query (bounds memory)
MAD_TO_SIGMA = 1.4826                 # median |x| of a Gaussian is 0.6745 sigma (also noise.py's)


def _chunks(count, cancel=None, size=None):
    """Slices of `size` (SPLIT_CHUNK) rows; setting `cancel` (a threading.Event) stops between them."""
    size = size or SPLIT_CHUNK
    for start in range(0, count, size):
        if cancel is not None and cancel.is_set():
            raise Cancelled("cancelled")
        yield slice(start, min(start + size, count))


def _neighbours(tree, points, k):
    """(M, k) indices of each point's k nearest, nearest first."""
    return np.asarray(tree.query(points, k=min(k, tree.n), workers=-1)[1]).reshape(len(points), -1)


def _sheet_fits(p, q, tree, scales, cancel=None):
    """Per scale k: (centroid, PCA normal) of each point's k nearest outputs and the input's
    height over them; one neighbour query at the largest k serves every scale (nearest first)."""
    fits = [(np.empty_like(q), np.empty_like(q), np.empty(len(q))) for _ in scales]
    for part in _chunks(len(q), cancel, SHEET_CHUNK):
        nearest = q[_neighbours(tree, q[part], max(scales))]
        for k, (sheet, axis, height) in zip(scales, fits):
            nb = nearest[:, :k]
            sheet[part] = nb.mean(axis=1)
            d = nb - sheet[part, None]
            axis[part] = np.linalg.eigh(np.matmul(d.transpose(0, 2, 1), d))[1][:, :, 0]
            height[part] = np.einsum("ij,ij->i", p[part] - sheet[part], axis[part])
    return fits


def _kurtosis(x):
    x = x - x.mean()
    return float(np.mean(x ** 4) / max(np.mean(x ** 2) ** 2, 1e-300))


def _merged_sheet(p, q, tree, cancel=None):
    """Per point: the merged sheet's centroid and PCA normal over its nearest outputs (of the
    SHEET_SCALES, the one whose input heights are the most flat-topped), the input's height
    over it, and the share of its SIDE_NEIGHBOURS nearest along the sheet (among its SIDE_POOL
    nearest outputs) whose input lay on the same side of it."""
    fits = _sheet_fits(p, q, tree, SHEET_SCALES, cancel)
    sheet, axis, height = min(fits, key=lambda fit: _kurtosis(fit[2]))
    same = np.empty(len(q))
    for part in _chunks(len(q), cancel, SHEET_CHUNK):
        idx = _neighbours(tree, q[part], SIDE_POOL)
        n = axis[part]
        t = q[idx] - q[part, None]
        t -= np.einsum("mkj,mj->mk", t, n)[..., None] * n[:, None]
        order = np.argsort(np.einsum("mkj,mkj->mk", t, t), axis=1)[:, 1:SIDE_NEIGHBOURS + 1]
        beside = np.take_along_axis(idx, order, axis=1)
        # Heights over each neighbour's own sheet point: the sheet's shape cancels.
        up = np.einsum("mkj,mkj->mk", p[beside] - sheet[part, None], n[:, None]) >= 0
        same[part] = (up == (height[part] >= 0)[:, None]).mean(axis=1)
    return sheet, axis, height, same


def _opposite_face(q, tree, axis, spread, rng, cancel=None):
    """(N,) bool: points with another output face OPPOSITE_STEPS x spread away along their
    sheet's normal `axis`, either way (a wall the passes kept apart): a probe ball holding
    OPPOSITE_FACE_SHARE of what the same ball around the point holds. Probed on a random
    sample of OPPOSITE_SAMPLE points: such walls span many points."""
    probed = np.sort(rng.choice(len(q), size=min(OPPOSITE_SAMPLE, len(q)), replace=False))
    opposite = np.zeros(len(probed), bool)
    for part in _chunks(len(probed), cancel):
        centre, along = q[probed[part]], spread * axis[probed[part]]
        own = np.asarray(tree.query_ball_point(centre, OPPOSITE_PROBE * spread, return_length=True, workers=-1))
        least = np.maximum(OPPOSITE_FACE_SHARE * own, OPPOSITE_MIN_POINTS)
        for step in OPPOSITE_STEPS:
            for way in (1.0, -1.0):
                count = tree.query_ball_point(centre + (way * step) * along, OPPOSITE_PROBE * spread,
                                              return_length=True, workers=-1)
                opposite[part] |= np.asarray(count) >= least
    if len(probed) == len(q):
        return opposite
    return opposite[np.asarray(cKDTree(q[probed]).query(q, workers=-1)[1])]


def _flat_topped(q, tree, height, same, usable, rng):
    """(centres, found, noise variance, by_whole): pool centres where the input heights of the
    usable points are flat-topped and their sides mixed along the sheet (two faces), tested on
    pools of SPLIT_POOLS points, smallest first; by_whole marks those only the whole-cloud
    pool found."""
    centres = rng.choice(len(q), size=min(SPLIT_CENTRES, len(q)), replace=False)
    found = np.zeros(len(centres), bool)
    by_whole = np.zeros(len(centres), bool)
    noise_var = np.zeros(len(centres))
    candidates = np.flatnonzero(usable)
    for pool in SPLIT_POOLS:
        whole = pool >= len(q) or pool == SPLIT_POOLS[-1]
        if whole:
            # The whole cloud's usable points (or a random sample of them) as one pool.
            members = rng.choice(candidates, size=min(pool, len(candidates)), replace=False)[None, :]
        else:
            members = _neighbours(tree, q[centres], pool)
        w = usable[members].astype(np.float64)
        count = np.maximum(w.sum(axis=1), 1.0)
        h = height[members]
        h = h - (np.sum(w * h, axis=1) / count)[:, None]
        m2 = np.maximum(np.sum(w * h ** 2, axis=1) / count, 1e-150)
        kurtosis = np.sum(w * h ** 4, axis=1) / count / m2 ** 2
        z = (3.0 - kurtosis) / np.sqrt(24.0 / count)
        r = np.sqrt(np.clip(3.0 - kurtosis, 0.0, None) / 2.0)
        # Two faces are sampled independently: along the sheet, a point's nearest neighbours
        # lie on its side half the time. Heights stored on a grid (a LAS file at 1 cm, a range
        # scanner's depth steps) are flat-topped too, but in bands: neighbours agree (0.61).
        mixed = (np.sum(w * same[members], axis=1) / count < SPLIT_MAX_AGREEMENT) & (
            count >= MIN_POOL_SHARE * members.shape[1])
        least_z, least_r = (SPLIT_Z_CLOUD, SPLIT_MIN_R_CLOUD) if whole else (SPLIT_Z, SPLIT_MIN_R)
        new = np.broadcast_to((z > least_z) & (r > least_r) & mixed, found.shape) & ~found
        noise_var[new] = np.broadcast_to(m2 * (1.0 - r), found.shape)[new]
        found |= new
        by_whole |= new & whole
        if whole or found.all():
            break
    return centres, found, noise_var, by_whole


def split_merged_walls(original, denoised, normals, seed=0, cancel=None):
    """Faces of thin walls that denoising merged into one sheet, set apart again.

    original, denoised: (N, 3) the input and the denoised positions of the same points;
    normals: (N, 3) unit normals of the denoised points (any sign). Returns (points, side):
    the positions with merged walls split, and side (N,) int8: +1 / -1 for a split point
    (its face lies that way along its normal), 0 elsewhere (left as it was). Setting `cancel`
    (a threading.Event) raises Cancelled between chunks of SPLIT_CHUNK points.
    """
    p = np.asarray(original, np.float64)
    q = np.asarray(denoised, np.float64)
    side = np.zeros(len(q), np.int8)
    if len(q) < SPLIT_POOLS[0]:
        return q, side
    rng = np.random.default_rng(seed)
    tree = cKDTree(q)
    # Heights square to the merged sheet (a tilt of 10 degrees mixes in ~0.4 sigma of
    # tangential offset and hides the two faces): its PCA normal, not the network's.
    sheet, n, height_in, same = _merged_sheet(p, q, tree, cancel)
    facing = np.where(np.einsum("ij,ij->i", n, normals) < 0, -1, 1).astype(np.int8)  # sides reported along `normals`
    height_out = np.einsum("ij,ij->i", q - sheet, n)
    # Walls whose faces the passes kept apart are no evidence of merged ones (OPPOSITE_STEPS).
    spread = MAD_TO_SIGMA * float(np.median(np.abs(height_in - np.median(height_in))))   # robust sd
    usable = ~_opposite_face(q, tree, n, spread, rng, cancel)
    if usable.sum() < SPLIT_POOLS[0]:
        return q, side
    centres, found, noise_var, by_whole = _flat_topped(q, tree, height_in, same, usable, rng)
    if not found.any():
        return q, side
    nearest = np.asarray(cKDTree(q[centres]).query(q, workers=-1)[1])
    rows = np.flatnonzero(found[nearest] & usable)
    # Per point of a two-face region: the faces' mid height and offset a from the local input
    # spread (less the pool's noise), and whether the output merged them there.
    mid, offset = np.zeros(len(q)), np.zeros(len(q))
    merged = np.zeros(len(q), bool)
    for part in _chunks(len(rows), cancel):
        r = rows[part]
        local = _neighbours(tree, q[r], LOCAL_NEIGHBOURS)
        h_loc = height_in[local]
        mid[r] = h_loc.mean(axis=1)
        offset[r] = np.sqrt(np.clip(h_loc.var(axis=1) - noise_var[nearest[r]], 0.0, None))
        merged[r] = height_out[local].var(axis=1) < (SPLIT_COLLAPSE * offset[r]) ** 2
    # The whole cloud's test says only that two faces lie somewhere in it. Where it alone
    # found them, the input spread must exceed the noise there too, or a solid region beside
    # thin walls would be split by their offset. One point's spread over 200 heights scatters
    # by ~10% of the variance; averaged again over its 200 neighbours, by ~4%.
    wide_rows = rows[by_whole[nearest[rows]] & merged[rows]]
    excess = np.zeros(len(q))
    excess[rows] = offset[rows] ** 2 / np.maximum(noise_var[nearest[rows]], 1e-300)
    for part in _chunks(len(wide_rows), cancel):
        r = wide_rows[part]
        merged[r] = excess[_neighbours(tree, q[r], LOCAL_NEIGHBOURS)].mean(axis=1) > SPLIT_LOCAL_EXCESS
    rows = rows[merged[rows]]
    # Thin-walled parts merge over much of an object (70-100% of the thin shapes' points); a
    # few percent is a thick part the passes half merged (a gear's faces 4 sigma apart at 2%
    # noise: 3% split, Chamfer 8.7 -> 9.4), where a local mid and offset are less sure.
    if len(rows) < SPLIT_MIN_SHARE * len(q):
        return q, side
    up = np.where(height_in[rows] >= mid[rows], 1, -1).astype(np.int8)
    out = q.copy()
    out[rows] += ((mid[rows] + up * offset[rows]) - height_out[rows])[:, None] * n[rows]
    side[rows] = up * facing[rows]
    return out, side


# Tips and walls thinner than the noise that the split leaves (too few points merged, or faces
# closer than it can tell apart: the last ~15% of a star prism's tips) still face their input
# side after orientation, but their points sit near the mid-plane, so about half of them shade
# the wrong way (the face nearest a point is not the one it faces). Each goes to the face it
# faces: the local input mid-plane plus the half-thickness a (the input's height spread less
# the noise), at least SEAT_MIN_OFFSET noise sigmas, since below ~1 sigma the spread cannot
# tell a from zero (and on a dense cloud the nearest inputs, within ~2 sigma, narrow it: there
# the floor decides). Star prism at 30K points, true sigma, floor 0 / 0.25 / 0.5 / 0.75 sigma:
# sign output 96.0 / 98.1 / 99.0 / 99.2% at 0.6% noise (P2S 1.22 / 1.19 / 1.17 / 1.18e-3,
# 1.26 unseated), 93.1 / 97.2 / 98.5 / 98.9% at 1.1% (P2S 2.20 / 2.13 / 2.11 / 2.21, 2.20),
# 91.2 / 96.5 / 98.0 / 98.4% at 2% (P2S 4.06 / 4.09 / 4.37 / 4.94, 4.06).
SEAT_MIN_OFFSET = 0.5
# Where a plane filter placed a turned point (`risk.choose_by_risk`), it is seated only inside a
# region of turned points: at least this share of its FACED_REGION_NEIGHBOURS nearest outputs
# were turned too. A thin tip is turned as a whole (star prism at 1.1%: median share 1.0, lower
# quartile 0.93); relief at the noise's scale turns scattered points (column_head at 0.6%:
# median 0.53, 90th percentile 0.77), where seating moved points off its one surface.
FACED_REGION_SHARE = 0.85
FACED_REGION_NEIGHBOURS = 30


def seat_on_facing_face(points, normals, median, variance, sigma):
    """`points` (M, 3) that orient's step 5 turned to their input side, moved along their
    oriented `normals` onto the face they face: the `median` height of their nearest inputs
    (the median the side was read against) plus the half-thickness, from the `variance` of
    those heights less the noise's (both from `orient.InputSide`). Returns the new positions;
    the caller bounds the motion."""
    half = np.sqrt(np.clip(variance - sigma ** 2, 0.0, None))
    return points + (median + np.maximum(half, SEAT_MIN_OFFSET * sigma))[:, None] * normals


def in_faced_region(points, faced, rows, share=FACED_REGION_SHARE, k=FACED_REGION_NEIGHBOURS):
    """Bool per `rows`: at least `share` of that point's k nearest `points` are `faced` (a bool
    mask over `points`, the points orient's step 5 turned to their input side)."""
    rows = np.asarray(rows)
    if not len(rows):
        return np.zeros(0, bool)
    near = _neighbours(cKDTree(points), points[rows], k)
    return faced[near].mean(axis=1) >= share

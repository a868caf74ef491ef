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

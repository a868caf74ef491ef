"""Per region, the network's result, a classic plane filter's or the input itself, whichever
Stein's unbiased risk estimate (SURE) says lies nearer the surface.

For Gaussian noise of sigma along a point's normal n, the squared error of any filter f along
n is estimated without the truth: (n.(f(y) - y))^2 - sigma^2 + 2 sigma^2 d(n.f)/d(n.y). The
derivative (the filter's divergence) comes from one more run on the input nudged along each
normal by a random amount (Monte Carlo SURE). Each estimate is noisy; averaged over a point's
`RISK_NEIGHBOURS` nearest it tells which filter does better in that region. On relief at the
noise's own scale (column_head at 0.6%) the network erodes and a small plane filter keeps it;
on smooth parts and sharp edges the network stays. Where a plane filter placed the points, the
normal is the plane fitted to the output there (`fitted_normals`): the network's normal is the
one of the surface it eroded. Where no filter beats the input (its risk is sigma^2: a sparse
scene whose patches and neighbourhoods span several surfaces), the region keeps its input.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .errors import Cancelled
from .origin import median_count_within
from .planes import local_planes, pca_projection_filter

PLANE_NEIGHBOURS = (10, 20, 40, 80)   # the plane filters offered beside the network
KEPT_INPUT = len(PLANE_NEIGHBOURS) + 1   # the choice that keeps the input, after the plane filters
# The nudge's scale, in noise sigmas. Nearest-neighbour sets switch as points move, so a
# finite nudge overstates a plane filter's divergence (unit square at 1%, 20K points, k 20:
# risk 0.12 sigma^2 over the truth at 0.5 sigma, 0.014 at 0.1): the choice leans to the network,
# today's result. A smaller nudge is lost in the network's bf16 rounding of its patches.
PROBE_SIGMAS = 0.5
RISK_NEIGHBOURS = 1024                 # points each region's risk is averaged over
RISK_CENTRES = 8_000                   # regions: the choice is made at this many sampled points
CHUNK = 1_000
# Where a plane filter placed the points, their normal is the PCA plane of the output's points
# within this many noise sigmas (the median count, within `FIT_NEIGHBOURS`): a normal needs a
# wider fit than a position. column_head at 0.6%, output MSAE: 50K points, 0.486 with the
# network's normals, 0.430 from the chosen filter's own plane, 0.412 from 3 sigmas (~40
# points; 20 0.427, 80 0.426); 20K, 0.570 network, 0.476 from 3 sigmas (~20), 0.452 from 40.
FIT_SIGMAS = 3.0
FIT_NEIGHBOURS = (40, 256)


def probe_offsets(normals, sigma, seed=0, probe_sigmas=PROBE_SIGMAS):
    """(amplitudes (N,), offsets (N, 3)): the nudge along each normal for the divergence."""
    amplitude = np.random.default_rng(seed).normal(size=len(normals))
    return amplitude, (probe_sigmas * sigma * amplitude)[:, None] * normals


def normal_risk(noisy, normals, filtered, filtered_probe, amplitude, sigma, probe_sigmas=PROBE_SIGMAS):
    """(N,) SURE of each point's squared error along its normal, up to the common -sigma^2."""
    along = np.einsum("ij,ij->i", filtered - noisy, normals)
    divergence = amplitude * np.einsum("ij,ij->i", filtered_probe - filtered, normals) / (probe_sigmas * sigma)
    return along ** 2 + 2.0 * sigma ** 2 * divergence


def regional_choice(points, risks, seed=0, cancel=None):
    """(N,) index of the least mean risk over each region (`RISK_NEIGHBOURS` nearest of a
    sampled centre); every point takes its nearest centre's choice. risks: (C, N)."""
    n = points.shape[0]
    k = min(RISK_NEIGHBOURS, n)
    rng = np.random.default_rng(seed)
    centres = np.sort(rng.choice(n, min(n, RISK_CENTRES), replace=False))
    tree = cKDTree(points)
    best = np.empty(len(centres), np.int64)
    for s in range(0, len(centres), CHUNK):
        if cancel is not None and cancel.is_set():
            raise Cancelled("cancelled")
        _, idx = tree.query(points[centres[s:s + CHUNK]], k=k, workers=-1)
        idx = idx.reshape(len(idx), k)
        best[s:s + CHUNK] = np.argmin(risks[:, idx].mean(axis=2), axis=0)
    _, nearest = cKDTree(points[centres]).query(points, workers=-1)
    return best[nearest]


def choose_by_risk(noisy, normals, network, network_probe, amplitude, offsets, sigma, seed=0, cancel=None):
    """(positions (N, 3), choice (N,): 0 the network's, i the i-th plane filter's of
    `PLANE_NEIGHBOURS`, `KEPT_INPUT` the input's). amplitude, offsets: the nudge
    (`probe_offsets`) network_probe ran on."""
    probe = noisy + offsets

    def candidates():
        yield network, network_probe
        for k in PLANE_NEIGHBOURS:
            # Each filter pair takes minutes at 10M points: a cancel stops between them.
            if cancel is not None and cancel.is_set():
                raise Cancelled("cancelled")
            yield pca_projection_filter(noisy, k), pca_projection_filter(probe, k)
        # Never worse than the input where the risk can tell: f(y) = y, its risk sigma^2.
        yield noisy, probe

    return choose_among(noisy, normals, candidates(), amplitude, sigma, seed=seed, cancel=cancel)


def choose_among(noisy, normals, candidates, amplitude, sigma, seed=0, cancel=None):
    """(positions (N, 3), choice (N,)): per region, the candidate of least mean risk along the
    normals. candidates: (filtered, filtered on the nudged input) pairs (`probe_offsets`' nudge),
    a list or a generator: each nudged run is dropped once its risk is taken."""
    # At 10M points each (N, 3) array is 240 MB: hold one nudged run at a time, and gather the
    # chosen rows candidate by candidate rather than from a stack of all of them.
    filtered, risks = [], []
    for f, fp in candidates:
        risks.append(normal_risk(noisy, normals, f, fp, amplitude, sigma))
        filtered.append(f)
    choice = regional_choice(noisy, np.stack(risks), seed=seed, cancel=cancel)
    positions = np.array(filtered[0], dtype=np.result_type(*filtered))
    for index, f in enumerate(filtered[1:], start=1):
        rows = choice == index
        positions[rows] = f[rows]
    return positions, choice


def fitted_normals(points, rows, normals, sigma, seed=0):
    """(len(rows), 3) unit normals at points[rows]: the PCA plane of the points within
    `FIT_SIGMAS` sigma (as a neighbour count: the median there), signed as `normals[rows]`."""
    tree = cKDTree(points)
    k = median_count_within(tree, points, FIT_SIGMAS * sigma, *FIT_NEIGHBOURS, seed=seed)
    fitted = local_planes(points, points[rows], k, tree=tree)[1]
    fitted[np.einsum("ij,ij->i", fitted, normals[rows]) < 0] *= -1
    return fitted

"""Rods: parts thinner than the patch in two directions (chair legs, poles, branches, cables).

A ball of the patch radius on a rod holds its whole cross-section. About the ball's mean its
two smaller spreads are then nearly equal and well below the largest (along the rod): the
patch's PCA frame has no normal axis, and the network, trained on surfaces, answers with a
normal at a random angle around the rod (the stool's square legs at 0.6% noise, 50K points:
MSAE 0.94 where tuned PCA gives 0.38). There the normal comes from the rod's cross-section
instead: the input points of the ball seen along the rod's axis, and a line fitted to those
near the point in that view. Every point of the ball along the rod's length helps the fit, so it
needs no neighbourhood size tuned to the noise (the legs: 0.34).
"""
from __future__ import annotations

import numpy as np

from .errors import Cancelled
from .patches import PatchSource

# Rod-like patch (the network's 128-point patch, spreads about its mean): smallest / middle
# above ROD_ROUNDNESS (no normal axis) and middle / largest below ROD_ELONGATION (a noisy plate's
# ball is round in the plane, a plate's edge is not round across). Chosen on eval clouds at 0.6%,
# 50K points: the stool's legs (the cross-section fit there: MSAE 0.375 -> 0.234), star_smooth's
# arms (0.0609 -> 0.0561); the other validation meshes hold almost no such patch.
ROD_ROUNDNESS = 0.6
ROD_ELONGATION = 0.6
# The section's RMS radius must pass this many noise sigmas: seen along a narrower rod, the
# points near the centre spread more with the noise than along the outline, and the fitted line
# follows the noise. Where the noise dominates a ball, a noisy plate's edge can read as a rod
# (its section radius stays below ~1.65 sigma); the stool's legs at 0.6% are ~3.5 sigma, and at
# 2% (~1 sigma) the fit made their output normals worse (MSAE 0.266 -> 0.290).
MIN_SECTION_SIGMAS = 2.0
SECTION_POINTS = 500     # input points per ball for the cross-section fit
# The line is fitted to the points within SECTION_REACH x the section's RMS radius of the point,
# and within SECTION_REACH_SIGMAS noise sigmas where the noise is known: on a square rod 15
# sigma wide the whole radius reaches round the corners (MSAE 0.250; 0.212 within 5 sigma).
SECTION_REACH = 1.0
SECTION_REACH_SIGMAS = 5.0
SECTION_CHUNK = 20_000   # balls per batch (bounds memory: 20K x 500 x 3 floats)


def _covariance(points):
    """(M, 3, 3) covariance of each (M, n, 3) set about its own mean (float64; batched matmul)."""
    x = np.asarray(points)
    mean = x.mean(axis=1)
    cov = np.matmul(x.transpose(0, 2, 1), x) / x.shape[1] - mean[:, :, None] * mean[:, None, :]
    return cov.astype(np.float64) + np.eye(3) * 1e-12


def section_radius(patches) -> np.ndarray:
    """(M,) RMS radius of the rod's section (patch units) where an (M, n, 3) patch has no normal
    axis because it holds a rod's section; 0 where it does not."""
    if len(patches) == 0:
        return np.zeros(0)
    # Per pass on every patch: float32 sums are enough for the ratios.
    w = np.linalg.eigvalsh(_covariance(np.asarray(patches, np.float32)))
    rod = (w[:, 0] > ROD_ROUNDNESS * w[:, 1]) & (w[:, 1] < ROD_ELONGATION * w[:, 2])
    return np.where(rod, np.sqrt(np.maximum(w[:, 0] + w[:, 1], 0.0)), 0.0)  # eigvalsh: -1e-9 on a flat patch


def resolved_rods(section, sigma) -> np.ndarray:
    """(N,) bool: rods (`section_radius`, cloud units) whose section the noise sigma leaves resolved."""
    return np.asarray(section) > MIN_SECTION_SIGMAS * sigma


def section_normals(cloud, centres, radius, rng, n=SECTION_POINTS, cancel=None, sigma=None):
    """(M, 3) unit normals (sign arbitrary) at `centres` on rods of `cloud`, from the cross-section.

    The ball of `radius` around each centre, seen along its longest spread (the rod's axis),
    shows the rod's outline; a line through the points near the centre in that view (see
    SECTION_REACH; `sigma`: the noise, if known) gives the normal (perpendicular to the line
    and to the axis)."""
    centres = np.asarray(centres, np.float64)
    normals = np.empty_like(centres)
    if len(centres) == 0:
        return normals
    source = PatchSource(cloud, radius, n, rng)
    for start in range(0, len(centres), SECTION_CHUNK):
        if cancel is not None and cancel.is_set():
            raise Cancelled("cancelled")
        local, _ = source.gather(centres[start:start + SECTION_CHUNK], rng)
        x = local.astype(np.float64)
        w, v = np.linalg.eigh(_covariance(x))
        axis = v[:, :, 2]
        # The view along the axis, relative to the centre.
        seen = x - np.einsum("mni,mi->mn", x, axis)[:, :, None] * axis[:, None, :]
        reach = SECTION_REACH * np.sqrt(w[:, 0] + w[:, 1])
        if sigma is not None and np.isfinite(sigma):
            reach = np.minimum(reach, SECTION_REACH_SIGMAS * sigma / radius)
        near = (np.linalg.norm(seen, axis=2) <= reach[:, None]).astype(np.float64)
        mean = np.einsum("mn,mni->mi", near, seen) / np.maximum(near.sum(axis=1), 1.0)[:, None]
        spread = (seen - mean[:, None]) * np.sqrt(near)[:, :, None]
        cov = np.einsum("mni,mnj->mij", spread, spread)
        # The axis has no spread in the view; the middle eigenvector is the section's normal.
        cov += np.einsum("mi,mj->mij", axis, axis) * (np.trace(cov, axis1=1, axis2=2) + 1e-12)[:, None, None]
        normals[start:start + len(x)] = np.linalg.eigh(cov)[1][:, :, 0]
    return normals


class RodNormals:
    """Section normals on a cloud's rods for the engine's passes: each point's fit reads only the
    input cloud, so it is made once, the first time a pass finds the point on a rod."""

    def __init__(self, cloud, radius, seed=0, cancel=None):
        self.cloud = np.asarray(cloud, np.float64)
        self.radius = float(radius)
        self.rng = np.random.default_rng(seed)      # its own stream: the passes' sampling is unchanged
        self.cancel = cancel
        self.fitted = np.full(self.cloud.shape, np.nan)

    def apply(self, normals, section, sigma) -> np.ndarray:
        """Replace `normals` (in place, signs kept) where `section` (`section_radius`, cloud
        units) shows a rod the noise leaves resolved; returns those rows as a bool mask."""
        rows = resolved_rods(section, sigma)
        todo = np.flatnonzero(rows & np.isnan(self.fitted[:, 0]))
        if len(todo):
            self.fitted[todo] = section_normals(self.cloud, self.cloud[todo], self.radius, self.rng,
                                                cancel=self.cancel, sigma=sigma)
        fit = self.fitted[rows]
        flip = np.einsum("ij,ij->i", fit, normals[rows]) < 0
        fit[flip] *= -1
        normals[rows] = fit
        return rows

"""Consistent normal orientation (the paper's normals are unoriented; ours are not).

Outward, for closed shapes, in the manner of Hoppe et al. but robust to noise and to sharp
CAD edges:
1. Smooth regions: k-NN edges whose normals agree within ~25 degrees (up to sign, and with
   the reflection test of step 2 agreeing on that sign) link points into regions; inside a
   region the sign is carried over a minimum spanning tree of
   1 - |n_i . n_j| (Hoppe's propagation, reliable where the normal turns gradually).
2. Across regions (sharp edges), a single edge says little on noisy data, so every k-NN
   edge between two regions votes: n_i reflected across the plane bisecting the edge is the
   normal a surface through both points would have at p_j (this stays decisive across
   90-degree edges, where the plain dot product is zero). Regions are joined along a
   spanning tree of the most confident votes.
3. Each connected piece is turned outward by its flux (the sum of n . (p - centroid), positive
   for outward normals on a closed surface). An open piece whose flux is ambiguous and which
   is a flat height field (a terrain or street scan) is turned to face up (+z) instead.
4. Visibility (ours): the cloud is looked at from many directions through a coarse depth
   buffer; a point clearly seen from one side only faces that side, and the points never
   clearly seen follow their clearly seen neighbours. This fixes what steps 1-3 cannot: the
   two faces of a thin tip, spike or seat, whose neighbourhoods mix both sides. Points seen
   from both sides (an open sheet, a terrain) cast no clear vote, and a cloud with few clear
   votes (an open scan) is left to steps 1-3 entirely.
5. Walls thinner than the noise (ours, when the input positions are given): on a closed
   object, a point seen from both sides among neighbours mostly seen from both sides lies on
   a wall whose two faces were drawn together (or never told apart); on a thin-walled object
   (two sheets found by the noise estimate) also when the cloud looks open. Only its own input
   position still says which face it was sampled from: it faces the side of the local median
   of the input it lay on. On a wall t thick that is right for Phi(t / 2 sigma) of the points,
   which is also the most any method can reach (`evaluation.metrics.sign_ceiling_normals`).
   Not thin-walled, only where the region is seen about as much from either side (a thin tip):
   the inside of a one-sided shell seen through its opening (a bust open at its base) is seen
   from both sides too, but mostly from outside, and there the input side is noise.
   The denoise then puts each such point on the face it faces (`sheets.seat_on_facing_face`),
   so that its shading and its position agree.

Viewpoint: each normal is turned to face the given scanner/camera position.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import breadth_first_order, connected_components, minimum_spanning_tree
from scipy.spatial import cKDTree

from .config import ORIENTATIONS
from .errors import InputError

SMOOTH_COS = 0.9
# An open piece (a terrain or street scan) has no inside, so its flux says nothing: when the
# flux is this small a share of its magnitude, and the piece is a flat height field (most
# normals within ~45 degrees of vertical, height under 30% of its width), it faces up (+z).
AMBIGUOUS_FLUX = 0.3
HEIGHT_FIELD_SHARE = 0.6
HEIGHT_FIELD_FLATNESS = 0.3
# Visibility: orthographic views from directions spread over the sphere, depth-buffer cells of
# a few point spacings (one noisy surface still hides what lies behind it), and a point counts
# as seen when it lies within one cell of the front of its cell.
VIEW_DIRECTIONS = 48
VIEW_CELL_SPACINGS = 3.0
VISIBILITY_SAMPLE = 500_000     # most points looked at (a sample of bigger clouds)
CLEAR_VOTE = 0.5                # |sum n.v| / sum |n.v| over a point's views: clearly one-sided
# The vote is used only when at least this share of the points is clearly seen from one side:
# closed objects 0.76-0.96 (thin ones included), open scans 0-0.16.
SEEN_CLOSED_SHARE = 0.5
# Step 5: a point seen from both sides takes its input side when at least this share of its
# TWO_SIDED_NEIGHBOURS nearest points is seen from both sides too (2-4% of a box's points are,
# scattered along concave edges, where the input side is noise: 0.5 keeps them out); the
# local median of the input is taken over its INPUT_SIDE_NEIGHBOURS nearest input points.
TWO_SIDED_NEIGHBOURS = 30
TWO_SIDED_SHARE = 0.5
INPUT_SIDE_NEIGHBOURS = 48
# Edges of the k-NN graph (10 a point) read at a time: their gathered normals and positions
# would otherwise cost ~1.1 KB a point at once (11 GB at 10M points).
EDGE_CHUNK = 250_000
INPUT_SIDE_CHUNK = 100_000        # rows of input heights at a time (~300 MB)
# On a closed object not found thin-walled, step 5 keeps to regions (connected k-NN components
# of the points it would turn) seen about as much from either side, a median |vote| of at most
# this: a thin tip is (star prism, 30K points at 0.6% and 2%: every tip 0.05-0.08), a one-sided
# surface seen through an opening is not (a bust open at its base, 50K at 1.1%: its regions
# 0.24-0.45; there step 5 turned 37% of the points and flipped half of them).
BALANCED_VOTE = 0.15


def _edge_dots(normals, i, j):
    """n_i . n_j per edge, in chunks of `EDGE_CHUNK` edges."""
    dot = np.empty(len(i))
    for s in range(0, len(i), EDGE_CHUNK):
        e = slice(s, s + EDGE_CHUNK)
        dot[e] = np.einsum("ec,ec->e", normals[i[e]], normals[j[e]])
    return dot


def _reflected_agreement(points, normals, i, j):
    """n_j . (n_i reflected across the plane bisecting edge i-j), in chunks of `EDGE_CHUNK` edges."""
    agreement = np.empty(len(i))
    for s in range(0, len(i), EDGE_CHUNK):
        ie, je = i[s:s + EDGE_CHUNK], j[s:s + EDGE_CHUNK]
        d = points[je] - points[ie]
        length = np.linalg.norm(d, axis=1, keepdims=True)
        d = d / np.maximum(length, 1e-300)
        n_i = normals[ie]
        reflected = n_i - 2.0 * np.einsum("ec,ec->e", n_i, d)[:, None] * d
        agreement[s:s + EDGE_CHUNK] = np.einsum("ec,ec->e", reflected, normals[je])
    return agreement


def _tree_signs(n_nodes, i, j, cost, sign_of_edge, labels, n_labels):
    """Sign of every node relative to the root of its component along a spanning forest.

    i, j, cost: undirected edges; sign_of_edge(a, b): +1/-1 per tree edge (a parent of b).
    A virtual node joined to one member of each component turns the forest into one tree,
    so a single breadth-first search and pointer doubling do the work without a loop
    over components.
    """
    first = np.full(n_labels, -1)
    first[labels[::-1]] = np.arange(n_nodes)[::-1]
    virtual = n_nodes
    ii = np.concatenate([i, np.full(n_labels, virtual)])
    jj = np.concatenate([j, first])
    cc = np.concatenate([cost, np.full(n_labels, 1e-9)])
    graph = coo_matrix((cc, (ii, jj)), shape=(n_nodes + 1, n_nodes + 1)).tocsr()
    del ii, jj, cc
    graph = graph.maximum(graph.T)
    forest = minimum_spanning_tree(graph)
    _, pred = breadth_first_order(forest + forest.T, virtual, directed=False, return_predecessors=True)
    parent = np.append(pred[:n_nodes], virtual)
    parent[parent < 0] = np.arange(n_nodes + 1)[parent < 0]
    rel = np.ones(n_nodes + 1, np.int8)
    child = np.flatnonzero((parent != np.arange(n_nodes + 1)) & (parent != virtual))
    rel[child] = sign_of_edge(parent[child], child)
    sign, hop = rel.copy(), parent.copy()
    for _ in range(int(np.ceil(np.log2(n_nodes + 2))) + 1):
        sign = sign * sign[hop]
        hop = hop[hop]
    return sign[:n_nodes]


def orient_outward(points: np.ndarray, normals: np.ndarray, k: int = 10, sources=None,
                   thin_walled=False, with_input_side=False):
    """Outward normals for a closed shape (steps 1-5 of the module doc). sources: each point's
    input position (before denoising; the points themselves for a normals-only run), for step 5.
    thin_walled: the noise estimate found two sheets in many balls (`noise.estimate_noise`), so
    points seen from both sides are walls even when the cloud looks like an open scan.
    with_input_side: also return the points step 5 turned to their input side (`InputSide`)."""
    n = len(points)
    normals = np.asarray(normals, np.float64)
    faced = NO_INPUT_SIDE
    if n < 2:
        return (normals.copy(), faced) if with_input_side else normals.copy()
    k = min(k, n - 1)
    tree = cKDTree(points)
    _, nbr = tree.query(points, k=k + 1, workers=-1)
    i = np.repeat(np.arange(n), k)
    j = nbr[:, 1:].ravel()
    # Geometry is read from points slid onto their own tangent planes (through the centroid
    # of their neighbours): noise across the surface would otherwise swamp short edges.
    centroid = points[nbr].mean(axis=1)
    del nbr
    flat = points - np.einsum("ec,ec->e", points - centroid, normals)[:, None] * normals
    del centroid
    dot = _edge_dots(normals, i, j)
    reflected = _reflected_agreement(flat, normals, i, j)
    # Smooth: nearly parallel normals, and both criteria agree on the sign (this keeps the
    # two sides of a thin spike, whose normals are nearly opposite, apart).
    smooth = (np.abs(dot) >= SMOOTH_COS) & (np.sign(dot) == np.sign(reflected))
    # +1/-1: the side each clearly seen point is seen from, relative to its input normal; 0 if
    # not clearly seen. An edge whose two ends are seen from opposite sides is not smooth.
    view_sign, two_sided, imbalance = clear_view_signs(points, normals, with_two_sided=True)
    closed = bool(np.mean(view_sign != 0) >= SEEN_CLOSED_SHARE)
    if not closed:
        # An open scan (one sweep of a range scanner, a terrain, vegetation): most points are
        # seen from both sides or not at all, and the few clear votes would scramble it.
        view_sign[:] = 0
        if not thin_walled:
            # ... unless it is thin-walled: then its faces were drawn together (a plate whose
            # two faces came out as one sheet is seen from both sides everywhere, like a scan).
            two_sided[:] = False
    smooth &= view_sign[i] * view_sign[j] * np.sign(dot) >= 0

    # 1. Hoppe propagation inside smooth regions.
    si, sj = i[smooth], j[smooth]
    n_reg, region = connected_components(coo_matrix((np.ones(len(si)), (si, sj)), shape=(n, n)), directed=False)
    sign = _tree_signs(n, si, sj, 1.0 - np.abs(dot[smooth]) + 1e-6,
                       lambda a, b: np.where(_edge_dots(normals, a, b) < 0, -1, 1),
                       region, n_reg)
    del si, sj
    oriented = normals * sign[:, None]

    # 2. Regions voted together across sharp edges.
    cross = region[i] != region[j]
    if cross.any():
        ci, cj = i[cross], j[cross]
        agree = _reflected_agreement(flat, oriented, ci, cj)
        ra, rb = np.minimum(region[ci], region[cj]), np.maximum(region[ci], region[cj])
        key, inverse = np.unique(ra.astype(np.int64) * n_reg + rb, return_inverse=True)
        vote = np.bincount(inverse, weights=agree, minlength=len(key))
        pa, pb = key // n_reg, key % n_reg
        adjacency = coo_matrix((np.ones(len(pa)), (pa, pb)), shape=(n_reg, n_reg))
        n_piece, piece = connected_components(adjacency, directed=False)
        vote_of = dict(zip(key.tolist(), vote.tolist()))

        def pair_sign(a, b):
            lo, hi = np.minimum(a, b), np.maximum(a, b)
            v = np.array([vote_of[int(x)] for x in lo.astype(np.int64) * n_reg + hi])
            return np.where(v < 0, -1, 1)

        region_sign = _tree_signs(n_reg, pa, pb, 1.0 / (1.0 + np.abs(vote)), pair_sign, piece, n_piece)
        oriented *= region_sign[region][:, None]

    # 3. Outward, per connected piece of the k-NN graph. By the divergence theorem the
    # surface integral of n . (p - c) is 3x the enclosed volume, positive for outward
    # normals whatever the shape; uniform samples estimate it by a plain sum.
    n_comp, labels = connected_components(coo_matrix((np.ones(len(i)), (i, j)), shape=(n, n)), directed=False)
    centres = np.stack([np.bincount(labels, weights=points[:, a], minlength=n_comp) for a in range(3)], axis=1)
    centres /= np.bincount(labels, minlength=n_comp)[:, None]
    along = np.einsum("ec,ec->e", oriented, points - centres[labels])
    flux = np.bincount(labels, weights=along, minlength=n_comp)
    decide = np.where(_open_height_field(points, oriented, labels, n_comp, flux, along),
                      np.bincount(labels, weights=oriented[:, 2], minlength=n_comp), flux)
    oriented *= np.where(decide[labels] < 0, -1.0, 1.0)[:, None]

    # 4. Clearly seen points face where they are seen from; each other point takes the side
    # that agrees with most of its k nearest clearly seen points.
    clear = np.flatnonzero(view_sign != 0)
    if len(clear):
        oriented[clear] = normals[clear] * view_sign[clear, None]
        rest = np.flatnonzero(view_sign == 0)
        if len(rest):
            _, near = cKDTree(points[clear]).query(points[rest], k=min(k, len(clear)), workers=-1)
            near = clear[near.reshape(len(rest), -1)]
            pull = np.einsum("mc,mkc->m", oriented[rest], oriented[near])
            oriented[rest] *= np.where(pull < 0, -1.0, 1.0)[:, None]

    # 5. Walls thinner than the noise: the side of the input each point lay on.
    if sources is not None and two_sided.any():
        oriented, faced = _face_input_side(points, tree, oriented, np.asarray(sources, np.float64), two_sided,
                                           None if thin_walled else imbalance)
    return (oriented, faced._replace(closed=closed)) if with_input_side else oriented


class InputSide(NamedTuple):
    """The points step 5 turned to their input side (`idx`, rows of the oriented cloud) and,
    along each one's oriented normal, the median and the variance of the heights of its
    INPUT_SIDE_NEIGHBOURS nearest inputs (`input_heights`): what `sheets.seat_on_facing_face`
    needs to put them on the face they face, without a second search of the input. closed: most
    points were clearly seen from one side (a closed object, not an open scan)."""
    idx: np.ndarray
    median: np.ndarray
    variance: np.ndarray
    closed: bool = False


NO_INPUT_SIDE = InputSide(np.zeros(0, np.int64), np.zeros(0), np.zeros(0))


def input_heights(source_tree, sources, points, normals):
    """(M, k) heights along `normals` (M, 3) above each of `points` (M, 3) of its
    INPUT_SIDE_NEIGHBOURS nearest `sources` (source_tree: their k-d tree)."""
    _, around = source_tree.query(points, k=min(INPUT_SIDE_NEIGHBOURS, len(sources)), workers=-1)
    around = around.reshape(len(points), -1)
    return np.einsum("mkc,mc->mk", sources[around] - points[:, None], normals)


def _face_input_side(points, tree, normals, sources, two_sided, imbalance=None):
    """Step 5 of the module doc: points seen from both sides, among neighbours mostly seen from
    both sides, face the side of the local input median their own input position lies on.
    tree: the k-d tree of `points`. imbalance (a closed object not found thin-walled): each
    point's |vote| (`clear_view_signs`); then only in `balanced_regions`. Returns the normals
    and the `InputSide` of the points turned."""
    candidates = np.flatnonzero(two_sided)
    _, near = tree.query(points[candidates], k=min(TWO_SIDED_NEIGHBOURS, len(points)), workers=-1)
    near = near.reshape(len(candidates), -1)
    keep = two_sided[near].mean(axis=1) >= TWO_SIDED_SHARE
    idx = candidates[keep]
    if imbalance is not None and len(idx):
        # A one-sided surface seen through an opening (the hollow of a bust open at its base) is
        # seen from both sides too, but mostly from one: its input side is noise there.
        idx = idx[balanced_regions(idx, near[keep], imbalance)]
    if not len(idx):
        return normals, NO_INPUT_SIDE
    nrm = normals[idx]
    source_tree = tree if np.array_equal(sources, points) else cKDTree(sources)   # normals only: the same cloud
    # In chunks: a wall's points are most of a thin-walled cloud, and their heights with the
    # neighbour query and gathered inputs behind them cost ~3 KB a point at once (30 GB at 10M).
    median, variance = np.empty(len(idx)), np.empty(len(idx))
    for s in range(0, len(idx), INPUT_SIDE_CHUNK):
        rows = idx[s:s + INPUT_SIDE_CHUNK]
        heights = input_heights(source_tree, sources, points[rows], nrm[s:s + INPUT_SIDE_CHUNK])
        median[s:s + INPUT_SIDE_CHUNK] = np.median(heights, axis=1)
        variance[s:s + INPUT_SIDE_CHUNK] = heights.var(axis=1)
    side = np.einsum("mc,mc->m", sources[idx] - points[idx], nrm) - median
    turn = np.where(side < 0, -1.0, 1.0)
    out = normals.copy()
    out[idx] = nrm * turn[:, None]
    # Along the turned normal the heights change sign: the median with them, not the variance.
    return out, InputSide(idx, median * turn, variance)


def balanced_regions(idx, near, imbalance):
    """Bool per `idx` (points step 5 would turn; `near`, their k nearest points): its region
    (the connected k-NN component of `idx`) has a median |vote| of at most BALANCED_VOTE."""
    row = np.full(len(imbalance), -1)
    row[idx] = np.arange(len(idx))
    linked = row[near]
    i, j = np.nonzero(linked >= 0)
    _, region = connected_components(coo_matrix((np.ones(len(i)), (i, linked[i, j])), shape=(len(idx), len(idx))),
                                     directed=False)
    votes = imbalance[idx]
    order = np.lexsort((votes, region))
    counts = np.bincount(region)
    median = votes[order][np.cumsum(counts) - counts + (counts - 1) // 2]     # the lower median
    return median[region] <= BALANCED_VOTE


def _directions(count):
    """Unit vectors spread evenly over the sphere (Fibonacci lattice)."""
    i = np.arange(count) + 0.5
    polar = np.arccos(1.0 - 2.0 * i / count)
    azimuth = np.pi * (1.0 + 5.0 ** 0.5) * i
    return np.stack([np.cos(azimuth) * np.sin(polar), np.sin(azimuth) * np.sin(polar), np.cos(polar)], axis=1)


def visibility_votes(points, normals, views=VIEW_DIRECTIONS, seed=0):
    """(indices, facing) for the points in front in at least one view (of a sample of at most
    VISIBILITY_SAMPLE points): facing = sum of n . v over the directions v a point is seen
    from, over the sum of |n . v|; +1 when every view sees the front of its normal, -1 when
    every view sees its back."""
    idx = np.arange(len(points))
    if len(points) > VISIBILITY_SAMPLE:
        idx = np.sort(np.random.default_rng(seed).choice(len(points), VISIBILITY_SAMPLE, replace=False))
    p = points[idx] - points[idx].mean(axis=0)
    nrm = np.asarray(normals, np.float64)[idx]
    gap, _ = cKDTree(p).query(p[:: max(1, len(p) // 2000)], k=2, workers=-1)
    cell = VIEW_CELL_SPACINGS * max(float(np.median(gap[:, 1])), 1e-12)
    num = np.zeros(len(p))
    den = np.zeros(len(p))
    for v in _directions(views):
        a = np.cross(v, [1.0, 0.0, 0.0] if abs(v[0]) < 0.9 else [0.0, 1.0, 0.0])
        a /= np.linalg.norm(a)
        b = np.cross(v, a)
        iu = np.floor(p @ a / cell).astype(np.int64)
        iw = np.floor(p @ b / cell).astype(np.int64)
        _, pixel = np.unique((iu - iu.min()) * (int(iw.max() - iw.min()) + 1) + (iw - iw.min()),
                             return_inverse=True)
        pixel = pixel.ravel()
        depth = -(p @ v)                   # seen from far along +v: the front has the largest p . v
        front = np.full(pixel.max() + 1, np.inf)
        np.minimum.at(front, pixel, depth)
        seen = depth - front[pixel] <= cell
        w = nrm[seen] @ v
        num[seen] += w
        den[seen] += np.abs(w)
    has = den > 0
    return idx[has], num[has] / den[has]


def clear_view_signs(points, normals, with_two_sided=False):
    """(N,) +1 where a point is clearly seen from the side its normal points to, -1 where from
    the other side, 0 where it is not clearly seen (hidden, or seen from both sides).
    with_two_sided: also return the (N,) mask of the points seen from both sides and the (N,)
    |vote| of each point (`visibility_votes`; 0: seen as much from either side, nan: unseen)."""
    seen, facing = visibility_votes(points, normals)
    sign = np.zeros(len(points))
    clear = np.abs(facing) > CLEAR_VOTE
    sign[seen[clear]] = np.sign(facing[clear])
    if not with_two_sided:
        return sign
    two_sided = np.zeros(len(points), bool)
    two_sided[seen[~clear]] = True
    imbalance = np.full(len(points), np.nan)
    imbalance[seen] = np.abs(facing)
    return sign, two_sided, imbalance


def _open_height_field(points, normals, labels, n_comp, flux, along) -> np.ndarray:
    """Per piece: True for an open, flat height field (terrain seen from above), whose outward
    side the flux cannot tell."""
    magnitude = np.bincount(labels, weights=np.abs(along), minlength=n_comp)
    size = np.bincount(labels, minlength=n_comp)
    vertical = np.bincount(labels, weights=np.abs(normals[:, 2]) > 0.7, minlength=n_comp) / size
    order = np.argsort(labels, kind="stable")
    starts = np.searchsorted(labels[order], np.arange(n_comp))
    lo = np.minimum.reduceat(points[order], starts, axis=0)
    hi = np.maximum.reduceat(points[order], starts, axis=0)
    width = np.linalg.norm(hi[:, :2] - lo[:, :2], axis=1)
    return ((np.abs(flux) < AMBIGUOUS_FLUX * magnitude) & (vertical > HEIGHT_FIELD_SHARE)
            & (hi[:, 2] - lo[:, 2] < HEIGHT_FIELD_FLATNESS * width))


def orient_toward(points, normals, viewpoint):
    viewpoint = np.asarray(viewpoint, np.float64).reshape(3)
    facing = np.einsum("ec,ec->e", normals, viewpoint - points)
    return normals * np.where(facing < 0, -1.0, 1.0)[:, None]


def orient_normals(points, normals, mode="outward", viewpoint=None, sources=None, thin_walled=False,
                   with_input_side=False):
    """Orient unit normals: 'outward' (closed shapes), 'viewpoint' (scans) or 'none'.
    sources ('outward' only): each point's input position, so that points on walls thinner
    than the noise can face the side they were sampled on (step 5 of the module doc);
    thin_walled, with_input_side: see `orient_outward` (no point is turned by step 5 but outward)."""
    if mode not in ORIENTATIONS:
        raise InputError(f"unknown orientation {mode!r}; choose one of {', '.join(ORIENTATIONS)}")
    if mode == "none":
        out = np.asarray(normals, np.float64).copy()
        return (out, NO_INPUT_SIDE) if with_input_side else out
    if mode == "viewpoint":
        if viewpoint is None:
            raise InputError("orientation 'viewpoint' needs a viewpoint (x, y, z)")
        vp = np.asarray(viewpoint, np.float64)
        if vp.size != 3 or not np.isfinite(vp).all():
            raise InputError(f"viewpoint must be three finite numbers, got {viewpoint!r}")
        out = orient_toward(points, normals, vp)
        return (out, NO_INPUT_SIDE) if with_input_side else out
    return orient_outward(np.asarray(points, np.float64), normals, sources=sources, thin_walled=thin_walled,
                          with_input_side=with_input_side)

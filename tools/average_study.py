"""Post-step averaging: the denoise's output moved along its own normals to the mean height of
its k nearest outputs, on its own and chosen per region by the risk estimate (`core.risk`).

A lead for issue #12's density gap (a patch holds 128 points at any density, so a dense cloud's
output is as rough as a 50K one's). For each case SHAPE:POINTS:LEVEL (noise sigma in percent of
the unit diagonal) this runs the denoise (auto, outward) and again on the input nudged along its
normals (the risk estimate's divergence), then prints P2S and Chamfer of: the input, the
denoise, the denoise averaged over k = 16 / 64 / 128 outputs (times POINTS / 50K), the per-region
choice among those by least risk, and plane filters.

  python tools/average_study.py star_prism:200000:2 star_prism:50000:0.6 octahedron:50000:2
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cljn_addon import core  # noqa: E402
from cljn_addon.core.evaluation.baselines import pca_projection_filter  # noqa: E402
from cljn_addon.core.evaluation.metrics import MeshDistance, chamfer  # noqa: E402
from cljn_addon.core.evaluation.shapes import sample_shape, shape_mesh  # noqa: E402
from cljn_addon.core.risk import normal_risk, probe_offsets, regional_choice  # noqa: E402

CHUNK = 50_000


def averaged(points, normals, k):
    """points moved along their normals to the mean height of their k nearest points."""
    tree = cKDTree(points)
    out = points.copy()
    for s in range(0, len(points), CHUNK):
        _, idx = tree.query(points[s:s + CHUNK], k=k, workers=-1)
        rel = points[idx] - points[s:s + CHUNK, None]
        height = np.einsum("ijk,ik->ij", rel, normals[s:s + CHUNK]).mean(axis=1)
        out[s:s + CHUNK] += height[:, None] * normals[s:s + CHUNK]
    return out


def case(text):
    shape, n, level = text.split(":")
    return shape, int(n), float(level)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("cases", nargs="+", type=case, metavar="SHAPE:POINTS:LEVEL")
    args = ap.parse_args(argv)
    model = core.load_model()
    for shape, n, level in args.cases:
        sigma = level / 100
        surface = MeshDistance(*shape_mesh(shape))
        noisy, clean, _ = sample_shape(shape, n, sigma, seed=0)
        start = time.perf_counter()
        res = core.denoise(noisy, model, iterations="auto", orientation="outward", seed=0)
        amplitude, offsets = probe_offsets(res.normals, res.noise_sigma, seed=7)
        probe = core.denoise(noisy + offsets, model, iterations="auto", orientation="outward", seed=0)
        took = time.perf_counter() - start
        ks = [k * max(1, n // 50_000) for k in (16, 64, 128)]
        candidates = [("ours", res.points, probe.points)]
        candidates += [(f"ours+avg{k}", averaged(res.points, res.normals, k), averaged(probe.points, probe.normals, k))
                       for k in ks]
        risks = np.stack([normal_risk(noisy, res.normals, f, fp, amplitude, res.noise_sigma)
                          for _, f, fp in candidates])
        choice = regional_choice(noisy, risks, seed=0)
        chosen = res.points.copy()
        for i, (_, f, _) in enumerate(candidates):
            chosen[choice == i] = f[choice == i]
        rows = [("input", noisy)] + [(name, f) for name, f, _ in candidates] + [("risk choice", chosen)]
        rows += [(f"plane k{k}", pca_projection_filter(noisy, k)) for k in (ks[1], ks[2], 2 * ks[2])]
        print(f"== {shape} {n} {level}%: {took:.0f} s for both runs; chosen: "
              + ", ".join(f"{name} {np.mean(choice == i):.2f}" for i, (name, _, _) in enumerate(candidates)),
              flush=True)
        for name, points in rows:
            print(f"  {name:14s} P2S {surface.distance(points).mean() / sigma:.3f} sigma  "
                  f"Chamfer {chamfer(points, clean) * 1e5:.2f} x1e-5", flush=True)


if __name__ == "__main__":
    main()

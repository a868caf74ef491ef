"""Dense objects: how the noise is read, and what the denoise makes of them, at 100K-1M points.

At these densities the ball that holds 256 points (`noise.NOISE_PATCH_POINTS`) is only a few
noise sigmas wide, so the scene check (`noise.SCENE_SPAN`) reads the noise in it too. For each
named shape, point count and noise level (percent of the unit diagonal) this prints the
estimate's sigma against the true one, each ball size's reading (`noise._estimate`'s median and
quietest balls) and whether the cloud was read as a scene; with `--denoise`, the denoise's
(auto, outward) P2S and Chamfer against the input's and the plane filter's (`--ks`; the eval's
tuned k at 50K points times the density).

  python tools/dense_study.py --shapes star_prism sphere --points 200000 400000 --levels 1.1 2
  python tools/dense_study.py --shapes star_prism --points 200000 --levels 2 --denoise
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cljn_addon import core  # noqa: E402
from cljn_addon.core import noise  # noqa: E402
from cljn_addon.core.evaluation.baselines import pca_projection_filter  # noqa: E402
from cljn_addon.core.evaluation.metrics import MeshDistance, chamfer  # noqa: E402
from cljn_addon.core.evaluation.shapes import sample_shape, shape_mesh  # noqa: E402
from cljn_addon.core.patches import bbox_diagonal  # noqa: E402


def readings(points, sigma):
    """The estimate, and per `noise._estimate` call (ball radius, median and quiet sigma / sigma,
    seconds), by wrapping it for one call of `estimate_noise`."""
    calls, estimate_at = [], noise._estimate

    def wrapped(pts, radius, sample, rng):
        start = time.perf_counter()
        out = estimate_at(pts, radius, sample, rng)
        calls.append((radius, out[0] / sigma, out[2] / sigma, time.perf_counter() - start))
        return out

    noise._estimate = wrapped
    try:
        return noise.estimate_noise(points, 0.05 * bbox_diagonal(points), seed=0), calls
    finally:
        noise._estimate = estimate_at


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--shapes", nargs="+", default=["star_prism", "sphere"])
    ap.add_argument("--points", nargs="+", type=int, default=[200_000, 400_000])
    ap.add_argument("--levels", nargs="+", type=float, default=[1.1, 2.0], help="noise sigma, percent of the diagonal")
    ap.add_argument("--denoise", action="store_true", help="also denoise and score against the plane filter")
    ap.add_argument("--ks", nargs="+", type=int, default=[100, 200, 400], help="the plane filter's neighbours")
    args = ap.parse_args(argv)
    model = core.load_model() if args.denoise else None
    for shape in args.shapes:
        surface = MeshDistance(*shape_mesh(shape)) if args.denoise else None
        for n in args.points:
            for level in args.levels:
                sigma = level / 100
                noisy, clean, _ = sample_shape(shape, n, sigma, seed=0)
                est, calls = readings(noisy, sigma)
                balls = "; ".join(f"balls of r {r:.4f} ({r / sigma:.1f} sigma): median {m:.3f}, quiet {q:.3f} ({s:.1f} s)"
                                  for r, m, q, s in calls)
                print(f"{shape} {n} points {level}%: sigma read {est.sigma / sigma:.3f}x, "
                      f"{'a scene, patches of r %.4f' % est.scene_radius if np.isfinite(est.scene_radius) else 'an object'} | {balls}",
                      flush=True)
                if not args.denoise:
                    continue
                start = time.perf_counter()
                res = core.denoise(noisy, model, iterations="auto", orientation="outward", seed=0)
                took = time.perf_counter() - start
                rows = [("input", noisy)] + [(f"plane k {k}", pca_projection_filter(noisy, k)) for k in args.ks]
                rows.append(("ours", res.points))
                for name, points in rows:
                    print(f"  {name:11s} P2S {surface.distance(points).mean() / sigma:.3f} sigma, "
                          f"Chamfer {chamfer(points, clean) * 1e5:.2f} x1e-5", flush=True)
                print(f"  ours: {took:.0f} s, noise {res.noise_sigma / sigma:.3f}x, {res.iterations} passes, "
                      f"largest move {res.displacement.max() / sigma:.2f} sigma; " + "; ".join(res.steps_taken()), flush=True)


if __name__ == "__main__":
    main()

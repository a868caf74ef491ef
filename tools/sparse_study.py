"""The denoise off the eval's grid: sparse clouds (5K-20K points) of shapes outside the eval.

The eval runs 50K points; a user's scan may hold far fewer, where a patch-radius ball holds
fewer points than a patch. For each shape and case (points, noise), prints Chamfer (x 1e5) and
P2S (x 1e3) of the input, the denoise (auto) and the best of the plane filter (k 20 / 50 / 100)
and jet smoothing (k 30 / 60), chosen by Chamfer, with our ratio to it; flags a cloud the
denoise leaves worse than its input. Shapes: the named shapes of `evaluation.shapes`, and
`cup` (an open cup, walls 4% of its width) and `pair` (a box and a sphere apart).

  python tools/sparse_study.py --shapes sphere torus cup pair star_prism gear stepped_block \\
      thin_plate l_bracket stool --cases 10000:1.0 20000:0.6 5000:1.5
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cljn_addon import core  # noqa: E402
from cljn_addon.core.evaluation import shapes  # noqa: E402
from cljn_addon.core.evaluation.baselines import jet_smooth, jet_smoothing_available, pca_projection_filter  # noqa: E402
from cljn_addon.core.evaluation.metrics import MeshDistance, chamfer  # noqa: E402


def study_mesh(name):
    if name == "cup":
        v, f = shapes.open_cup(shapes.regular_polygon(48, 0.4), shapes.regular_polygon(48, 0.36), 0.8, 0.05)
    elif name == "pair":
        box_v, box_f = shapes.box((0.6, 0.4, 0.3))
        ball_v, ball_f = shapes.sphere(0.2)
        v, f = shapes.concat_meshes((box_v, box_f), (ball_v + (0.7, 0, 0), ball_f))
    else:
        return shapes.shape_mesh(name)
    return shapes.normalise_unit_diagonal(v), f


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--shapes", nargs="+", default=["sphere", "torus", "cup", "pair", "l_bracket"])
    ap.add_argument("--cases", nargs="+", default=["10000:1.0", "20000:0.6", "5000:1.5"], help="POINTS:PERCENT")
    ap.add_argument("--weights", default=None, help="a model file (default: the shipped model)")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args(argv)
    model = core.load_model(args.weights)
    cases = [(int(c.split(":")[0]), float(c.split(":")[1])) for c in args.cases]
    for name in args.shapes:
        v, f = study_mesh(name)
        surface = MeshDistance(v, f)
        for n, percent in cases:
            rng = np.random.default_rng(args.seed)
            clean, _, _ = shapes.sample_mesh(v, f, n, rng)
            noisy = clean + rng.normal(scale=percent / 100, size=clean.shape)

            def score(points):
                return chamfer(points, clean) * 1e5, surface.distance(points).mean() * 1e3

            t0 = time.time()
            res = core.denoise(noisy, model, iterations="auto", orientation="outward", seed=0)
            seconds = time.time() - t0
            classic = {f"plane {k}": score(pca_projection_filter(noisy, k)) for k in (20, 50, 100)}
            if jet_smoothing_available():
                classic.update({f"jet {k}": score(jet_smooth(noisy, k)) for k in (30, 60)})
            best = min(classic, key=lambda c: classic[c][0])
            given, ours, theirs = score(noisy), score(res.points), classic[best]
            worse = " WORSE THAN INPUT" if ours[0] >= given[0] or ours[1] >= given[1] else ""
            print(f"{name:14s} {n:>6d} {percent:4.2f}%: Chamfer input {given[0]:.2f} ours {ours[0]:.2f} {best} "
                  f"{theirs[0]:.2f} ({ours[0] / theirs[0]:.3f}x) | P2S input {given[1]:.3f} ours {ours[1]:.3f} "
                  f"{theirs[1]:.3f} ({ours[1] / theirs[1]:.3f}x) | {res.iterations} passes, plane filter "
                  f"{res.plane_share:.0%}, thin-walled {res.thin_walled}, {seconds:.0f} s{worse}", flush=True)


if __name__ == "__main__":
    main()

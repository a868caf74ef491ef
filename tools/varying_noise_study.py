"""The denoise on clouds whose noise changes across them (a LiDAR's grows with range).

Each case is a shape whose noise grows linearly along x from one level to another (percent of
the diagonal), or with `:step` changes from one to the other at the middle (two merged
scans). Prints Chamfer (x 1e5) and P2S (x 1e3) of the input, of the best plane filter (k 20 /
50 / 100) and jet smoothing (k 30 / 60 / 120) chosen per metric, and of the denoise (auto),
with our ratios; and whether the cloud read as varying (`noise.varying_local_noise`).

  python tools/varying_noise_study.py --cases sphere:50000:0.2:2.0 stepped_block:50000:0.2:2.0 \\
      star_prism:50000:0.2:2.0 torus:50000:0.3:1.5 gear:20000:1.5:0.3 sphere:50000:0.3:0.9 \\
      stepped_block:50000:0.3:0.9 star_prism:50000:0.3:0.9
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cljn_addon import core  # noqa: E402
from cljn_addon.core.evaluation import shapes  # noqa: E402
from cljn_addon.core.evaluation.baselines import jet_smooth, jet_smoothing_available, pca_projection_filter  # noqa: E402
from cljn_addon.core.evaluation.metrics import MeshDistance, chamfer  # noqa: E402
from cljn_addon.core.noise import estimate_noise, varying_local_noise  # noqa: E402
from cljn_addon.core.patches import bbox_diagonal  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", nargs="+", default=["sphere:20000:0.2:2.0"],
                    help="SHAPE:POINTS:LOW:HIGH[:step] (step: LOW on one half, HIGH on the other)")
    ap.add_argument("--weights", default=None, help="a model file (default: the shipped model)")
    args = ap.parse_args(argv)
    model = core.load_model(args.weights)
    for case in args.cases:
        name, n, low, high, *profile = case.split(":")
        noisy, clean, _ = shapes.sample_shape_varying_noise(name, int(n), float(low) / 100, float(high) / 100, seed=3,
                                                            profile=profile[0] if profile else "linear")
        surface = MeshDistance(*shapes.shape_mesh(name))

        def score(points):
            return chamfer(points, clean) * 1e5, surface.distance(points).mean() * 1e3

        centred = noisy - (noisy.min(axis=0) + noisy.max(axis=0)) / 2
        radius = 0.05 * bbox_diagonal(centred)
        varies = varying_local_noise(centred, radius, estimate_noise(centred, radius)) is not None
        classic = {f"plane {k}": score(pca_projection_filter(noisy, k)) for k in (20, 50, 100)}
        if jet_smoothing_available():
            classic.update({f"jet {k}": score(jet_smooth(noisy, k)) for k in (30, 60, 120)})
        by_chamfer = min(classic, key=lambda c: classic[c][0])
        by_p2s = min(classic, key=lambda c: classic[c][1])
        t0 = time.time()
        res = core.denoise(noisy, model, iterations="auto", orientation="outward", seed=0)
        given, ours = score(noisy), score(res.points)
        print(f"{case}: varying {varies} | Chamfer input {given[0]:.2f} {by_chamfer} {classic[by_chamfer][0]:.2f} "
              f"ours {ours[0]:.2f} ({ours[0] / classic[by_chamfer][0]:.3f}x) | P2S input {given[1]:.3f} {by_p2s} "
              f"{classic[by_p2s][1]:.3f} ours {ours[1]:.3f} ({ours[1] / classic[by_p2s][1]:.3f}x) | "
              f"{res.iterations} passes, plane filter {res.plane_share:.0%}, largest bound {res.displacement_bound:.4f}, "
              f"{time.time() - t0:.0f} s", flush=True)


if __name__ == "__main__":
    main()

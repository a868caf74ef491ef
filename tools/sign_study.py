"""Sign output of the denoise on issue #12's orientation shapes, fast.

The star prism (sharp tips whose last ~15% is thinner than the noise) and the gear (teeth 4.2
sigma thick at 2%), 30K points, seed 8 (the clouds of the README's figures): each output normal
against the normal of the clean surface nearest its output point (the eval's "sign output",
what shading sees), and against the face each input point came from.

  python tools/sign_study.py --shapes star_prism gear --levels 0.6 1.1 2.0
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cljn_addon import core  # noqa: E402
from cljn_addon.core.evaluation.metrics import MeshDistance, sign_agreement  # noqa: E402
from cljn_addon.core.evaluation.shapes import sample_shape, shape_mesh  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--shapes", nargs="+", default=["star_prism", "gear"])
    ap.add_argument("--levels", type=float, nargs="+", default=[0.6, 1.1, 2.0], help="percent")
    ap.add_argument("--points", type=int, default=30_000)
    ap.add_argument("--weights", default=None, help="a model file (default: the shipped model)")
    ap.add_argument("--seed", type=int, default=8)
    args = ap.parse_args(argv)
    model = core.load_model(args.weights)
    for name in args.shapes:
        surface = MeshDistance(*shape_mesh(name))
        for percent in args.levels:
            noisy, _, origin = sample_shape(name, args.points, noise=percent / 100, seed=args.seed)
            t0 = time.time()
            res = core.denoise(noisy, model, iterations="auto", orientation="outward", seed=0)
            _, facing = surface.nearest(res.points)
            print(f"{name} {percent:.1f}%: sign output {sign_agreement(res.normals, facing):.1%}, against the faces "
                  f"of origin {sign_agreement(res.normals, origin):.1%} ({res.iterations} passes, "
                  f"{time.time() - t0:.0f} s)", flush=True)


if __name__ == "__main__":
    main()

"""Sign output of the denoise on issue #12's orientation shapes, fast.

The star prism (sharp tips whose last ~15% is thinner than the noise) and the gear (teeth 4.2
sigma thick at 2%), 30K points, seed 8 (the clouds of the README's figures): each output normal
against the normal of the clean surface nearest its output point (the eval's "sign output",
what shading sees), and against the face each input point came from. "Flipped" counts the
output normals that face away from every clean face within one noise sigma of their point (no
clean sample there within 60 degrees of them): a wrong-sign figure that leaves out the points
near an acute edge or notch that carry the other face's outward normal (a face mix-up, which
the MSAE scores, not a flip). "Either face at an edge" reads a point beyond a convex edge (its
nearest clean point is the edge, where the faces meeting there are equally near and
`MeshDistance.nearest` returns one of them) as right when its normal agrees with either face's
(`MeshDistance.sign_at_any_nearest_face`); elsewhere it is the sign output.

  python tools/sign_study.py --shapes star_prism gear --levels 0.6 1.1 2.0
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
from cljn_addon.core.evaluation.metrics import MeshDistance, sign_agreement  # noqa: E402
from cljn_addon.core.evaluation.shapes import sample_mesh, sample_shape, shape_mesh  # noqa: E402

FLIP_COS = 0.5          # a clean face within 60 degrees of the normal: not flipped
CLEAN_SAMPLES = 600_000


def flipped_share(points, normals, facing, clean_tree, clean_normals, sigma):
    """Share of output normals with no clean sample within sigma of their point whose normal
    is within 60 degrees of theirs (only points whose nearest face disagrees are looked at)."""
    suspects = np.flatnonzero(np.einsum("ij,ij->i", normals, facing) < 0)
    near = clean_tree.query_ball_point(points[suspects], sigma, workers=-1)
    flipped = [len(rows) == 0 or (clean_normals[rows] @ normals[s]).max() < FLIP_COS
               for rows, s in zip(near, suspects)]
    return float(np.sum(flipped)) / len(points)


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
        mesh = shape_mesh(name)
        surface = MeshDistance(*mesh)
        clean, clean_normals, _ = sample_mesh(*mesh, CLEAN_SAMPLES, np.random.default_rng(0))
        clean_tree = cKDTree(clean)
        for percent in args.levels:
            noisy, _, origin = sample_shape(name, args.points, noise=percent / 100, seed=args.seed)
            t0 = time.time()
            res = core.denoise(noisy, model, iterations="auto", orientation="outward", seed=0)
            _, facing = surface.nearest(res.points)
            flipped = flipped_share(res.points, res.normals, facing, clean_tree, clean_normals, percent / 100)
            either = surface.sign_at_any_nearest_face(res.points, res.normals).mean()
            print(f"{name} {percent:.1f}%: sign output {sign_agreement(res.normals, facing):.2%} (either face at an "
                  f"edge {either:.2%}), flipped {flipped:.2%}, against the faces of origin {sign_agreement(res.normals, origin):.1%} "
                  f"({res.iterations} passes, {time.time() - t0:.0f} s)", flush=True)


if __name__ == "__main__":
    main()

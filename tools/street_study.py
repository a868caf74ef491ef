"""Issue #12's street scan, synthetic: a car with a building's wall 0.6 m behind it.

`evaluation.shapes.street_scene` (metres) sampled area-uniformly, Gaussian noise in metres. For
the input, the plane filter (k 20 / 50), jet smoothing (k 30) and the denoise (auto), prints the
issue's figures: median and largest move, the share of input points left without an output
point within 2.5 sigma, P2S (cm), Chamfer (cm^2), and how far the wall's points behind the car
end from the wall (a patch of 5% of the diagonal is wider than the gap).

  python tools/street_study.py --points 25000 --noise 0.02
  python tools/street_study.py --points 125000 --noise 0.02 --length 18 --depth 8

`--city`: `evaluation.shapes.city_street` instead (buildings, cars along both kerbs, poles; a
scene whose 5% ball holds several of them): the same figures but the wall's.

  python tools/street_study.py --city --points 100000 --length 150 --depth 30
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
from cljn_addon.core.evaluation.baselines import jet_smooth, jet_smoothing_available, pca_projection_filter  # noqa: E402
from cljn_addon.core.evaluation.metrics import MeshDistance, chamfer  # noqa: E402
from cljn_addon.core.evaluation.shapes import city_street, sample_noisy, street_scene  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--points", type=int, default=25_000)
    ap.add_argument("--noise", type=float, default=0.02, help="sigma in metres")
    ap.add_argument("--length", type=float, default=8.0, help="metres along the street")
    ap.add_argument("--depth", type=float, default=6.0, help="metres from the wall across the street")
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--city", action="store_true", help="the longer street of buildings, cars and poles")
    args = ap.parse_args(argv)
    vertices, faces = (city_street if args.city else street_scene)(args.length, args.depth)
    clean, _, face, noisy = sample_noisy(vertices, faces, args.points, args.noise, args.seed)
    surface = MeshDistance(vertices, faces)
    wall_y = vertices[faces[2, 0], 1]
    # The wall behind the parked car (faces 2 and 3 of `street_scene`); the city has none.
    behind_car = (np.zeros(len(clean), bool) if args.city else
                  ((face == 2) | (face == 3)) & (np.abs(clean[:, 0]) < 2.25) & (clean[:, 2] < 1.5))

    def show(name, points):
        move = np.linalg.norm(points - noisy, axis=1)
        gap, _ = cKDTree(points).query(noisy, workers=-1)
        off_wall = np.abs(points[behind_car, 1] - wall_y)
        print(f"{name:10s} move median {np.median(move) * 100:.2f} cm, largest {move.max() * 100:.1f} cm; "
              f"input without output within 2.5 sigma {np.mean(gap > 2.5 * args.noise):.2%}; "
              f"P2S {surface.distance(points).mean() * 100:.3f} cm; Chamfer {chamfer(points, clean) * 1e4:.2f} cm^2"
              + ("" if args.city else f"; wall behind the car: off the wall {off_wall.mean() * 100:.2f} cm mean, "
                 f"{off_wall.max() * 100:.1f} cm largest"), flush=True)

    show("input", noisy)
    for k in (20, 50):
        show(f"plane {k}", pca_projection_filter(noisy, k))
    if jet_smoothing_available():
        show("jet 30", jet_smooth(noisy, 30))
    t0 = time.time()
    res = core.denoise(noisy, core.load_model(), iterations="auto", orientation="outward", seed=0)
    show("ours", res.points)
    print(f"ours: noise read {res.noise_sigma * 100:.2f} cm, {res.iterations} passes, bound "
          f"{res.displacement_bound * 100:.1f} cm, plane filter {res.plane_share:.0%}, "
          f"input kept {res.kept_share:.1%}, {time.time() - t0:.0f} s")


if __name__ == "__main__":
    main()

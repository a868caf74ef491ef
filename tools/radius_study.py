"""Which patch radius each cloud wants: Chamfer after every pass at several radii.

The paper's radius (5% of the bounding-box diagonal) is one choice for single objects. At low
noise a smaller ball resolves finer detail (column_head at 0.6%, 50K points: 1 pass at 3%
gives Chamfer 4.64, at 5% 5.53, input 6.32) but averages fewer points on smooth parts, and
at high noise a small ball fails outright (cylinder at 2%: 16.1 at 3% against 3.8 at 5%).
This prints, per cloud, the noise sigma the engine reads at each radius
(`core.noise.estimate_noise`, in true sigmas) and Chamfer (x1e-5) after each of the passes,
so a rule tying the radius to the noise, the density or the local detail can be checked on
many clouds before it goes into the engine.

  python tools/radius_study.py --shapes column_head boxunion --levels 0.6 1.1 --points 50000 \
      --fractions 0.05 0.04 0.03
(names as in tools/iteration_study.py; clouds are its `noisy_cloud`, so the two agree.)
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from iteration_study import noisy_cloud  # noqa: E402

from cljn_addon import core  # noqa: E402
from cljn_addon.core.evaluation.metrics import chamfer  # noqa: E402
from cljn_addon.core.noise import estimate_noise  # noqa: E402
from cljn_addon.core.patches import bbox_diagonal  # noqa: E402


def radius_row(name, level, n_points, fraction, passes, model, seed=0):
    """(sigma read at this radius / true sigma, [Chamfer x1e-5 after each pass], seconds)."""
    _, _, clean, noisy = noisy_cloud(name, level, n_points, seed)
    sigma = estimate_noise(noisy, fraction * bbox_diagonal(noisy), seed=seed).sigma
    after = []
    t0 = time.time()
    core.denoise(noisy, model, iterations=passes, patch_radius_fraction=fraction, split_walls=False,
                 on_iteration=lambda _, pts: after.append(chamfer(pts, clean) * 1e5))
    return sigma / level, after, time.time() - t0


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shapes", nargs="+", default=["boxunion", "column_head", "cylinder", "icosahedron",
                                                        "star_smooth"])
    parser.add_argument("--levels", nargs="+", type=float, default=[0.6, 1.1], help="sigma, %% of the diagonal")
    parser.add_argument("--points", type=int, default=50000)
    parser.add_argument("--fractions", nargs="+", type=float, default=[0.05, 0.04, 0.03],
                        help="patch radius, fraction of the bbox diagonal")
    parser.add_argument("--passes", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0, help="sampling seed (noise: seed + 6)")
    parser.add_argument("--dump", type=Path, help="append one JSON line per cloud and radius")
    args = parser.parse_args(argv)
    model = core.load_model()
    for name in args.shapes:
        for level in args.levels:
            for fraction in args.fractions:
                sigma_read, after, seconds = radius_row(name, level / 100, args.points, fraction, args.passes,
                                                        model, args.seed)
                print(f"{name:>14} {level:4.1f}% {args.points} r {fraction:.3f}: sigma^ {sigma_read:.2f}x | "
                      + " ".join(f"{c:6.2f}" for c in after) + f" | best {min(after):6.2f} ({seconds:.0f} s)",
                      flush=True)
                if args.dump:
                    with args.dump.open("a") as f:
                        f.write(json.dumps({"shape": name, "level": level, "points": args.points,
                                            "fraction": fraction, "sigma_read": sigma_read,
                                            "chamfer_after": after}) + "\n")


if __name__ == "__main__":
    main()

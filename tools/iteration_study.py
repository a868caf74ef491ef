"""How many iterations each cloud needs, and whether the noise can tell.

For each shape and noise level: Chamfer after every pass of a 4-pass run, and the RMS move
from the input in units of the true sigma and of the estimated one. Prints a table per cloud
and, per rule, the mean ratio of its Chamfer to the best pass count's:
- `auto`: the engine's rule (core.infer.iterations_for_noise on the estimated sigma);
- `4`: the paper's fixed four passes;
- `oracle`: the discrepancy principle with the true sigma (stop before the RMS move passes
  1.0 sigma); it shows what a good enough noise estimate would give.

  python tools/iteration_study.py --shapes boxunion column_head thin_plate stool --levels 0.6 1.1 2.0
(names are validation meshes in ../shared/data/meshes/validation or built-in shapes).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cljn_addon import core  # noqa: E402
from cljn_addon.cli.paths import DEFAULT_VALIDATION_DIR  # noqa: E402
from cljn_addon.core.evaluation.evaluate import prepare_shape  # noqa: E402
from cljn_addon.core.evaluation.metrics import chamfer  # noqa: E402
from cljn_addon.core.evaluation.shapes import shape_mesh  # noqa: E402
from cljn_addon.core.formats.meshes import read_mesh  # noqa: E402
from cljn_addon.core.infer import iterations_for_noise  # noqa: E402
from cljn_addon.core.patches import bbox_diagonal  # noqa: E402


def mesh_for(name):
    path = DEFAULT_VALIDATION_DIR / f"{name}.off"
    return read_mesh(path) if path.exists() else shape_mesh(name)


def study(name, level, n_points, model, seed=1):
    """Per pass: (chamfer, rms move / true sigma, rms move / estimated sigma); sigma^; radius."""
    v, f, clean, _ = prepare_shape(*mesh_for(name), n_points, seed)
    noisy = clean + np.random.default_rng(seed + 6).normal(scale=level, size=clean.shape)
    passes = []

    def record(_, points):
        rms = float(np.sqrt(np.mean(np.sum((points - noisy) ** 2, axis=1))))
        passes.append((chamfer(points, clean), rms))

    res = core.denoise(noisy, model, iterations=4, on_iteration=record)
    radius = model.config.patch_radius_fraction * bbox_diagonal(noisy)
    return [(cd, rms / level, rms / res.noise_sigma) for cd, rms in passes], res.noise_sigma, radius


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shapes", nargs="+", default=["boxunion", "column_head", "cylinder", "icosahedron",
                                                        "star_smooth", "thin_plate", "l_bracket", "stool"])
    parser.add_argument("--levels", nargs="+", type=float, default=[0.6, 1.1, 2.0], help="sigma, %% of the diagonal")
    parser.add_argument("--points", type=int, default=20000)
    args = parser.parse_args(argv)
    model = core.load_model()
    ratios = {"auto": [], "4": [], "oracle": []}
    for name in args.shapes:
        for level in args.levels:
            passes, sigma_hat, radius = study(name, level / 100, args.points, model)
            cds = [p[0] for p in passes]
            best = min(cds)
            auto = iterations_for_noise(sigma_hat, radius)
            oracle = next((i for i in range(1, 4) if passes[i][1] > 1.0), 4)
            for rule, count in (("auto", auto), ("4", 4), ("oracle", oracle)):
                ratios[rule].append(cds[count - 1] / best)
            print(f"{name:>14} {level:.2f}%  sigma^/sigma {sigma_hat / (level / 100):.2f}  " + "  ".join(
                f"it{i + 1}: CD {cd * 1e5:6.2f} rms/sigma {t:.2f} rms/sigma^ {e:.2f}" for i, (cd, t, e) in enumerate(passes))
                + f"  | auto {auto}, oracle {oracle}", flush=True)
    for rule, values in ratios.items():
        print(f"{rule:>7}: mean Chamfer / best pass count's {np.mean(values):.3f}; "
              f"within 5% of the best on {sum(r <= 1.05 for r in values)}/{len(values)} clouds")


if __name__ == "__main__":
    main()

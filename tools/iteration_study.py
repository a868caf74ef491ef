"""How many iterations each cloud needs, and whether the noise can tell.

For each shape and noise level: Chamfer after every pass of a 4-pass run, and the RMS move
from the input in units of the true sigma and of the estimated one. Prints a table per cloud
and, per rule, the mean ratio of its Chamfer to the best pass count's:
- `auto`: the engine's rule: the count from the estimated sigma (core.infer.iterations_for_noise;
  one pass on a thin-walled object), stopping before the first pass whose RMS move passes
  core.infer.auto_stop_move (STOP_MOVE_SIGMAS x core.noise.surface_noise_sigma);
- `count`: the count alone, without the stop (auto before the stop existed);
- `4`: the paper's fixed four passes;
- `oracle`: the discrepancy principle with the true sigma (stop before the RMS move passes
  1.0 sigma); it shows what a good enough noise estimate would give.

  python tools/iteration_study.py --shapes boxunion column_head thin_plate stool --levels 0.6 1.1 2.0
(names are validation meshes in ../shared/data/meshes/validation or built-in shapes).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cljn_addon import core  # noqa: E402
from cljn_addon.cli.paths import DEFAULT_VALIDATION_DIR  # noqa: E402
from cljn_addon.core.evaluation.evaluate import prepare_shape  # noqa: E402
from cljn_addon.core.evaluation.metrics import chamfer, point2surface  # noqa: E402
from cljn_addon.core.evaluation.shapes import shape_mesh  # noqa: E402
from cljn_addon.core.formats.meshes import read_mesh  # noqa: E402
from cljn_addon.core.infer import auto_iteration_count, auto_stop_move  # noqa: E402
from cljn_addon.core.patches import bbox_diagonal  # noqa: E402


def mesh_for(name):
    path = DEFAULT_VALIDATION_DIR / f"{name}.off"
    return read_mesh(path) if path.exists() else shape_mesh(name)


def noisy_cloud(name, level, n_points, seed=1):
    """(vertices, faces, clean points, noisy points) of one study cloud, reproducibly."""
    v, f, clean, _ = prepare_shape(*mesh_for(name), n_points, seed)
    noisy = clean + np.random.default_rng(seed + 6).normal(scale=level, size=clean.shape)
    return v, f, clean, noisy


def study(name, level, n_points, model, seed=1, record_all=None):
    """Per pass: (chamfer, rms move / true sigma, rms move / estimated sigma); sigma^; radius;
    the engine's auto pass counts with and without the stop (see the module doc).
    record_all: a dict filled with what a stop-rule study needs to replay the run."""
    v, f, clean, noisy = noisy_cloud(name, level, n_points, seed)
    passes, p2s = [], []

    def record(_, points):
        rms = float(np.sqrt(np.mean(np.sum((points - noisy) ** 2, axis=1))))
        passes.append((chamfer(points, clean), rms))
        if record_all is not None:
            p2s.append(float(np.mean(point2surface(points, v, f))))

    res = core.denoise(noisy, model, iterations=4, on_iteration=record)
    radius = model.config.patch_radius_fraction * bbox_diagonal(noisy)
    count = auto_iteration_count(res.noise_sigma, radius, res.thin_walled)
    stop_move = auto_stop_move(noisy, radius, res.noise_sigma) if count > 1 else float("inf")
    auto = next((i for i in range(1, count) if passes[i][1] > stop_move), count)
    if record_all is not None:
        record_all.update(name=name, level=level, points=n_points, seed=seed, sigma_hat=res.noise_sigma,
                          radius=radius, input_chamfer=chamfer(noisy, clean),
                          input_p2s=float(np.mean(point2surface(noisy, v, f))),
                          chamfer=[p[0] for p in passes], rms=[p[1] for p in passes], p2s=p2s,
                          thin_walled=res.thin_walled, stop_move=stop_move, auto=auto, count=count)
    return ([(cd, rms / level, rms / res.noise_sigma) for cd, rms in passes], res.noise_sigma, radius,
            (auto, count))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shapes", nargs="+", default=["boxunion", "column_head", "cylinder", "icosahedron",
                                                        "star_smooth", "thin_plate", "l_bracket", "stool"])
    parser.add_argument("--levels", nargs="+", type=float, default=[0.6, 1.1, 2.0], help="sigma, %% of the diagonal")
    parser.add_argument("--points", type=int, nargs="+", default=[20000])
    parser.add_argument("--seed", type=int, default=1, help="sampling seed (noise: seed + 6)")
    parser.add_argument("--dump", type=Path, help="write every pass of every cloud to this JSON file")
    args = parser.parse_args(argv)
    model = core.load_model()
    ratios = {"auto": [], "count": [], "4": [], "oracle": []}
    records = []
    for name, n_points, level in ((s, n, lv) for s in args.shapes for n in args.points for lv in args.levels):
        records.append({})
        passes, sigma_hat, radius, (auto, count) = study(name, level / 100, n_points, model, seed=args.seed,
                                          record_all=records[-1] if args.dump else None)
        if args.dump:
            args.dump.write_text(json.dumps(records, indent=1))
        cds = [p[0] for p in passes]
        best = min(cds)
        oracle = next((i for i in range(1, 4) if passes[i][1] > 1.0), 4)
        for rule, passes_run in (("auto", auto), ("count", count), ("4", 4), ("oracle", oracle)):
            ratios[rule].append(cds[passes_run - 1] / best)
        print(f"{name:>14} {n_points} {level:.2f}%  sigma^/sigma {sigma_hat / (level / 100):.2f}  " + "  ".join(
            f"it{i + 1}: CD {cd * 1e5:6.2f} rms/sigma {t:.2f} rms/sigma^ {e:.2f}" for i, (cd, t, e) in enumerate(passes))
            + f"  | auto {auto}, count {count}, oracle {oracle}", flush=True)
    for rule, values in ratios.items():
        print(f"{rule:>7}: mean Chamfer / best pass count's {np.mean(values):.3f}; "
              f"within 5% of the best on {sum(r <= 1.05 for r in values)}/{len(values)} clouds")


if __name__ == "__main__":
    main()

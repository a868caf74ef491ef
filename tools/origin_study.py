"""Normals-only mode on the eval's own clouds: origin MSAE and sign per shape and level, fast.

`eval` scores normals-only mode (`core.estimate_normals`) on the origin-normal metric, but it
also runs the denoise, every tuned baseline and the floor for each cloud (~15 min a level and
block here). This rebuilds exactly the clouds of a single-level eval run (`eval --levels L`,
the same shapes, seeds and order) and runs only normals-only mode on them, so a change to that
mode can be measured on all ten rows in minutes; `--baselines` adds tuned PCA (k from the
eval's candidates, shared by the block), the floor and the sign ceiling, and with them the gap
closed. Sign agreement (the eval's "sign ours") is over closed, consistently wound meshes.

  python tools/origin_study.py --block validation --levels 0.6 0.8 1.1 1.5 2.0 [--baselines]
  python tools/origin_study.py --block thin_parts --levels 0.6

`--denoise` runs the denoise instead, as the eval does, and prints its Chamfer (x 1e5), P2S
(x 1e3), output-normal MSAE and sign output (each output normal against the surface nearest its
point) per shape and for the block: the eval's "ours" columns without its baselines.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cljn_addon import core  # noqa: E402
from cljn_addon.cli.paths import DEFAULT_VALIDATION_DIR  # noqa: E402
from cljn_addon.core.evaluation.baselines import pca_normals  # noqa: E402
from cljn_addon.core.evaluation.evaluate import PCA_K, is_closed_and_consistent, noisy_cloud, prepare_shape  # noqa: E402
from cljn_addon.core.evaluation.metrics import MeshDistance, chamfer, floor_and_ceiling_normals, msae, sign_agreement  # noqa: E402
from cljn_addon.core.evaluation.shapes import THIN_SHAPES, shape_mesh  # noqa: E402
from cljn_addon.core.formats.meshes import find_meshes, read_mesh  # noqa: E402


def block_shapes(block, mesh_dir):
    if block == "thin_parts":
        return [(name, *shape_mesh(name)) for name in THIN_SHAPES]
    return [(p.stem, *read_mesh(p)) for p in find_meshes(mesh_dir)]


def eval_clouds(shapes, level, n_points, seed=0):
    """The clouds of `eval --levels level` (a single-level run: level index 0)."""
    for i, (name, v, f) in enumerate(shapes):
        v, f, clean, normals = prepare_shape(v, f, n_points, seed + i)
        yield name, v, f, noisy_cloud(clean, level, seed, 0, i), normals, clean


def denoise_rows(model, shapes, level, n_points):
    """`--denoise`: one line per shape and the block's means, as the eval scores "ours"."""
    scores = []
    for name, v, f, noisy, _, clean in eval_clouds(shapes, level, n_points):
        t0 = time.time()
        res = core.denoise(noisy, model, iterations="auto", orientation="outward", seed=0)
        dist, facing = MeshDistance(v, f).nearest(res.points)
        sign = sign_agreement(res.normals, facing) if is_closed_and_consistent(f) else float("nan")
        scores.append((chamfer(res.points, clean) * 1e5, dist.mean() * 1e3, msae(res.normals, facing), sign))
        print(f"{level:.1%} {name}: Chamfer {scores[-1][0]:.3f} P2S {scores[-1][1]:.3f} output MSAE "
              f"{scores[-1][2]:.4f} sign output {sign:.2%}, plane filter {res.plane_share:.1%}, input kept "
              f"{res.kept_share:.1%} ({time.time() - t0:.0f} s)", flush=True)
    cd, p2s, out_msae, sign = np.nanmean(np.array(scores), axis=0)
    return f"Chamfer {cd:.3f}, P2S {p2s:.3f}, output MSAE {out_msae:.4f}, sign output {sign:.2%} (closed shapes)"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--block", choices=("validation", "thin_parts"), default="validation")
    ap.add_argument("--mesh-dir", default=str(DEFAULT_VALIDATION_DIR))
    ap.add_argument("--levels", type=float, nargs="+", default=[0.6, 0.8, 1.1, 1.5, 2.0], help="percent")
    ap.add_argument("--points", type=int, default=50_000)
    ap.add_argument("--baselines", action="store_true", help="also tuned PCA and the floor (slow)")
    ap.add_argument("--weights", default=None, help="a model file (default: the shipped model)")
    ap.add_argument("--denoise", action="store_true", help="the denoise's positions and output normals instead")
    args = ap.parse_args(argv)
    model = core.load_model(args.weights)
    shapes = block_shapes(args.block, args.mesh_dir)
    for percent in args.levels:
        level = percent / 100
        if args.denoise:
            print(f"{args.block} {percent:.1f}%: denoise {denoise_rows(model, shapes, level, args.points)}", flush=True)
            continue
        ours, pca, floors, signs, ceilings = [], {k: [] for k in PCA_K}, [], [], []
        for name, v, f, noisy, normals, _ in eval_clouds(shapes, level, args.points):
            t0 = time.time()
            res = core.estimate_normals(noisy, model, orientation="outward", seed=0)
            ours.append(msae(res.normals, normals))
            line = (f"{percent:.1f}% {name}: normals only {ours[-1]:.4f}, plane filter {res.plane_share:.1%}, "
                    f"input kept {res.kept_share:.1%} ({time.time() - t0:.0f} s)")
            closed = is_closed_and_consistent(f)
            if closed:
                signs.append(sign_agreement(res.normals, normals))
                line += f", sign {signs[-1]:.1%}"
            if args.baselines:
                for k in PCA_K:
                    pca[k].append(msae(pca_normals(noisy, k), normals))
                floor_n, ceiling_n = floor_and_ceiling_normals(noisy, v, f, level)
                floors.append(msae(floor_n, normals))
                line += f"; floor {floors[-1]:.4f}"
                if closed:
                    ceilings.append(sign_agreement(ceiling_n, normals))
                    line += f", sign ceiling {ceilings[-1]:.1%}"
            print(line, flush=True)
        row = f"{args.block} {percent:.1f}%: normals only {np.mean(ours):.4f}, sign {np.mean(signs):.1%}"
        if args.baselines:
            k = min(PCA_K, key=lambda k: np.mean(pca[k]))
            p, fl = np.mean(pca[k]), np.mean(floors)
            row += (f", tuned PCA {p:.4f} (k {k}), floor {fl:.4f}, gap closed {(p - np.mean(ours)) / (p - fl):.0%}, "
                    f"sign ceiling {np.mean(ceilings):.1%}")
        print(row, flush=True)


if __name__ == "__main__":
    main()

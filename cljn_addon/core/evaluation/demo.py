"""The built-in example: a noisy scan of a block with sharp convex and concave edges is
denoised and its normals estimated; before/after numbers are printed and files written."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from .baselines import pca_normals
from ..errors import ModelMismatchError, ModelNotFoundError
from ..infer import denoise
from .metrics import MeshDistance, chamfer, msae, sharp_feature_mask, sign_agreement
from ..model import load_model
from ..formats.points import PointCloud, write_ply
from .shapes import sample_shape, shape_mesh


def main(argv=None):
    parser = argparse.ArgumentParser(prog="run.py demo", description=__doc__)
    parser.add_argument("--out-dir", default="out/demo", help="where the PLY files go")
    parser.add_argument("--shape", default="stepped_block", help="built-in shape (stepped_block, box, star, torus, ...)")
    parser.add_argument("--points", type=int, default=30_000)
    parser.add_argument("--noise", type=float, default=1.0, help="sigma, percent of the bbox diagonal")
    parser.add_argument("--iterations", type=int, default=4)
    parser.add_argument("--model", default=None, help="weights file (default: the shipped model)")
    args = parser.parse_args(argv)
    try:
        model = load_model(args.model)
    except (ModelNotFoundError, ModelMismatchError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    noisy, clean, truth = sample_shape(args.shape, args.points, noise=args.noise / 100, seed=1)
    print(f"{args.shape}: {len(noisy)} points, Gaussian noise {args.noise:g}% of the bbox diagonal")
    from tqdm import tqdm

    with tqdm(total=100, unit="%", desc="denoising", leave=False) as bar:
        def progress(fraction, message):
            bar.set_description(message, refresh=False)
            bar.update(int(fraction * 100) - bar.n)

        res = denoise(noisy, model, iterations=args.iterations, orientation="outward", progress=progress)
    dist = MeshDistance(*shape_mesh(args.shape))
    sharp = sharp_feature_mask(clean, truth)
    pca = {k: pca_normals(noisy, k) for k in (20, 40, 60, 100)}
    k_best = min(pca, key=lambda k: msae(pca[k], truth))
    print(f"{'':28s}{'noisy input':>14s}{'CLJN':>14s}")
    print(f"{'Chamfer distance (x1e-5)':28s}{chamfer(noisy, clean) * 1e5:14.2f}{chamfer(res.points, clean) * 1e5:14.2f}")
    print(f"{'Point2Surface (x1e-3)':28s}{dist.distance(noisy).mean() * 1e3:14.2f}{dist.distance(res.points).mean() * 1e3:14.2f}")
    print(f"{'':28s}{f'PCA (best k={k_best})':>14s}{'CLJN':>14s}")
    print(f"{'Normal MSAE (rad^2)':28s}{msae(pca[k_best], truth):14.4f}{msae(res.normals, truth):14.4f}")
    print(f"{'  at sharp edges':28s}{msae(pca[k_best], truth, sharp):14.4f}{msae(res.normals, truth, sharp):14.4f}")
    print(f"normals pointing outward: {sign_agreement(res.normals, truth) * 100:.1f}%; "
          f"outliers flagged: {int(res.outliers.sum())}; {res.seconds:.1f} s")
    out = Path(args.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_ply(out / "noisy.ply", PointCloud(points=noisy.astype(np.float32)))
    write_ply(out / "clean.ply", PointCloud(points=clean.astype(np.float32), normals=truth.astype(np.float32)))
    write_ply(out / "denoised.ply", PointCloud(points=res.points.astype(np.float32), normals=res.normals,
                                               extra={"displacement": res.displacement.astype(np.float32)}),
              outliers=res.outliers)
    print(f"wrote {out / 'noisy.ply'}, {out / 'denoised.ply'} (x y z nx ny nz), {out / 'clean.ply'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

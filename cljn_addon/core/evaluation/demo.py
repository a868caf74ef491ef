"""The built-in example: a noisy scan of a block with sharp convex and concave edges is
denoised and its normals estimated; `run_demo` computes the before/after numbers,
`demo_table` formats them and `write_demo_files` writes the PLY files (cli/demo.py prints)."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..formats.points import PointCloud, write_ply
from ..infer import denoise
from .baselines import pca_normals
from .metrics import MeshDistance, chamfer, msae, sharp_feature_mask, sign_agreement
from .shapes import sample_shape, shape_mesh

PCA_NEIGHBOURS = (20, 40, 60, 100)


@dataclass
class DemoResult:
    shape: str
    noise_percent: float
    noisy: np.ndarray
    clean: np.ndarray
    truth: np.ndarray          # clean normals
    result: object             # core.DenoiseResult
    numbers: dict              # the table's values


def run_demo(model, shape="stepped_block", points=30_000, noise_percent=1.0, iterations="auto",
             progress=None) -> DemoResult:
    noisy, clean, truth = sample_shape(shape, points, noise=noise_percent / 100, seed=1)
    res = denoise(noisy, model, iterations=iterations, orientation="outward", progress=progress)
    dist = MeshDistance(*shape_mesh(shape))
    sharp = sharp_feature_mask(clean, truth)
    pca = {k: pca_normals(noisy, k) for k in PCA_NEIGHBOURS}
    k_best = min(pca, key=lambda k: msae(pca[k], truth))
    numbers = {
        "chamfer": (chamfer(noisy, clean), chamfer(res.points, clean)),
        "point2surface": (dist.distance(noisy).mean(), dist.distance(res.points).mean()),
        "pca_k": k_best,
        "msae": (msae(pca[k_best], truth), msae(res.normals, truth)),
        "msae_sharp": (msae(pca[k_best], truth, sharp), msae(res.normals, truth, sharp)),
        "outward": sign_agreement(res.normals, truth),
        "outliers": int(res.outliers.sum()),
        "seconds": res.seconds,
    }
    return DemoResult(shape, noise_percent, noisy, clean, truth, res, numbers)


def demo_table(demo: DemoResult) -> list:
    """The lines the demo prints (README shows them)."""
    n = demo.numbers
    pca = f"PCA (best k={n['pca_k']})"
    return [
        f"{'':28s}{'noisy input':>14s}{'CLJN':>14s}",
        f"{'Chamfer distance (x1e-5)':28s}{n['chamfer'][0] * 1e5:14.2f}{n['chamfer'][1] * 1e5:14.2f}",
        f"{'Point2Surface (x1e-3)':28s}{n['point2surface'][0] * 1e3:14.2f}{n['point2surface'][1] * 1e3:14.2f}",
        f"{'':28s}{pca:>14s}{'CLJN':>14s}",
        f"{'Normal MSAE (rad^2)':28s}{n['msae'][0]:14.4f}{n['msae'][1]:14.4f}",
        f"{'  at sharp edges':28s}{n['msae_sharp'][0]:14.4f}{n['msae_sharp'][1]:14.4f}",
        f"normals pointing outward: {n['outward'] * 100:.1f}%; "
        f"outliers flagged: {n['outliers']}; {n['seconds']:.1f} s",
    ]


def write_demo_files(out_dir, demo: DemoResult) -> list:
    """noisy.ply, denoised.ply (x y z nx ny nz + displacement + outlier flag), clean.ply."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    res = demo.result
    write_ply(out / "noisy.ply", PointCloud(points=demo.noisy.astype(np.float32)))
    write_ply(out / "denoised.ply", PointCloud(points=res.points.astype(np.float32), normals=res.normals,
                                               extra={"displacement": res.displacement.astype(np.float32)}),
              outliers=res.outliers)
    write_ply(out / "clean.ply", PointCloud(points=demo.clean.astype(np.float32),
                                            normals=demo.truth.astype(np.float32)))
    return [out / "noisy.ply", out / "denoised.ply", out / "clean.ply"]

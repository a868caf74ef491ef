"""A wall thinner than the noise against one sheet with the same height spread: what any blind
filter can tell apart, and what each one scores on both.

A plate t thick under Gaussian noise sigma has heights across it drawn from two Gaussians at
+-t/2; one sheet (the same plate, its faces together) under noise sqrt(sigma^2 + t^2/4) has
heights of the same mean and variance, and the two differ only in the fourth moment (kurtosis
3 - 2a^4 / (sigma^2 + a^2)^2, a = t/2: 2.970 for the eval's plate at 2%). A filter that cannot
tell the two apart gives both the same output; the tuned plane filter's residual spread covers
the plate's two faces and costs the sheet, the denoise's sheet the other way round. This puts
numbers on it: Chamfer (x 1e5) of the input, the denoise (auto) and the plane filter and jet
smoothing at each of the eval's neighbourhood sizes, on the plate and on its one-sheet twin,
and the kurtosis of the inner heights of each input (with its standard error).

  python tools/thin_limit_study.py --levels 2.0 [--points 50000]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cljn_addon import core  # noqa: E402
from cljn_addon.core.evaluation.baselines import jet_smooth, jet_smoothing_available, pca_projection_filter  # noqa: E402
from cljn_addon.core.evaluation.evaluate import FILTER_K, JET_K, prepare_shape  # noqa: E402
from cljn_addon.core.evaluation.metrics import chamfer  # noqa: E402
from cljn_addon.core.evaluation.shapes import thin_plate  # noqa: E402

PLATE_THICKNESS = 0.018     # the eval's plate (`shapes.thin_plate`), before the unit-diagonal scale
ONE_SHEET = 1e-6            # the twin: the same plate with its faces together


def inner_heights_kurtosis(noisy, clean):
    """Kurtosis of the heights (z: the plate lies in xy) of the points away from the rims."""
    inner = (np.abs(clean[:, 0]) < 0.4 * np.ptp(clean[:, 0])) & (np.abs(clean[:, 1]) < 0.4 * np.ptp(clean[:, 1]))
    z = noisy[inner, 2] - noisy[inner, 2].mean()
    return float(np.mean(z ** 4) / np.mean(z ** 2) ** 2), float(np.sqrt(24.0 / inner.sum()))


def study(model, level, n_points, seed):
    v, f = thin_plate(PLATE_THICKNESS)
    v, f, clean, _ = prepare_shape(v, f, n_points, seed)
    half = float(np.ptp(v[:, 2])) / 2
    v1, f1 = thin_plate(ONE_SHEET)
    v1, f1, clean1, _ = prepare_shape(v1, f1, n_points, seed)
    rng = np.random.default_rng(seed)
    twin_sigma = float(np.hypot(level, half))
    cases = [(f"plate {2 * half:.2%} thick, noise {level:.2%}", clean, clean + rng.normal(scale=level, size=clean.shape)),
             (f"one sheet, noise {twin_sigma:.2%}", clean1, clean1 + rng.normal(scale=twin_sigma, size=clean1.shape))]
    for name, truth, noisy in cases:
        kurt, se = inner_heights_kurtosis(noisy, truth)
        t0 = time.time()
        ours = core.denoise(noisy, model, iterations="auto", orientation="outward", seed=seed).points
        line = (f"{name}: inner-height kurtosis {kurt:.3f} (se {se:.3f}); Chamfer input {chamfer(noisy, truth) * 1e5:.2f}, "
                f"ours {chamfer(ours, truth) * 1e5:.2f} ({time.time() - t0:.0f} s)")
        print(line, flush=True)
        plane = {k: chamfer(pca_projection_filter(noisy, k), truth) * 1e5 for k in FILTER_K}
        print("  plane filter " + ", ".join(f"k {k}: {c:.2f}" for k, c in plane.items()), flush=True)
        if jet_smoothing_available():
            jet = {k: chamfer(jet_smooth(noisy, k), truth) * 1e5 for k in JET_K}
            print("  jet smoothing " + ", ".join(f"k {k}: {c:.2f}" for k, c in jet.items()), flush=True)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--levels", type=float, nargs="+", default=[2.0], help="noise sigma, percent of the diagonal")
    ap.add_argument("--points", type=int, default=50_000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--weights", default=None, help="weights file (default: the shipped model)")
    args = ap.parse_args()
    model = core.load_model(args.weights)
    for level in args.levels:
        study(model, level / 100, args.points, args.seed)


if __name__ == "__main__":
    main()

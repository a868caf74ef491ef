"""`run.py demo`: denoise a built-in noisy scan, print the before/after table, write the PLY
files (the computation is core.evaluation.demo)."""
from __future__ import annotations

import argparse

from ..core.errors import ModelMismatchError, ModelNotFoundError
from .console import err, out
from .exitcodes import EXIT_OK, EXIT_USAGE
from .parser import iterations_arg
from .progress import Progress


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="run.py demo",
        description="The built-in example: a noisy scan of a block with sharp convex and concave "
                    "edges is denoised and its normals estimated; before/after numbers are printed "
                    "and files written.")
    parser.add_argument("--out-dir", default="out/demo", help="where the PLY files go")
    parser.add_argument("--shape", default="stepped_block", help="built-in shape (stepped_block, box, star, torus, ...)")
    parser.add_argument("--points", type=int, default=30_000)
    parser.add_argument("--noise", type=float, default=1.0, help="sigma, percent of the bbox diagonal")
    parser.add_argument("--iterations", type=iterations_arg, default="auto",
                        help="filtering iterations, or auto (default; see denoise --help)")
    parser.add_argument("--model", default=None, help="weights file (default: the shipped model)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar or lines")
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    from ..core.evaluation.demo import demo_table, run_demo, write_demo_files
    from ..core.model import load_model

    try:
        model = load_model(args.model)
    except (ModelNotFoundError, ModelMismatchError) as exc:
        err(f"error: {exc}")
        return EXIT_USAGE
    with Progress("denoising", enabled=not args.no_progress) as bar:
        demo = run_demo(model, args.shape, args.points, args.noise, args.iterations, progress=bar)
    out(f"{args.shape}: {len(demo.noisy)} points, Gaussian noise {args.noise:g}% of the bbox diagonal")
    for line in demo_table(demo):
        out(line)
    noisy, denoised, clean = write_demo_files(args.out_dir, demo)
    out(f"wrote {noisy}, {denoised} (x y z nx ny nz), {clean}")
    return EXIT_OK

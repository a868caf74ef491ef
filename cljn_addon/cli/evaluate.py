"""`run.py eval`: the evaluation table on held-out meshes (see core.evaluation.evaluate)."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ..core.config import TEST_NOISE_LEVELS
from ..core.errors import InputError, ModelMismatchError, ModelNotFoundError
from .parser import iterations_arg
from .paths import DEFAULT_VALIDATION_DIR


def main(argv=None):
    parser = argparse.ArgumentParser(prog="run.py eval", description="Evaluate a model on held-out meshes against tuned classic baselines.")
    parser.add_argument("mesh_dir", nargs="?", default=str(DEFAULT_VALIDATION_DIR),
                        help="folder of closed meshes (.off/.obj/.ply); default: the validation set")
    parser.add_argument("--model", default=None, help="weights file (default: the shipped model)")
    parser.add_argument("--points", type=int, default=50_000, help="points sampled per shape")
    parser.add_argument("--levels", type=float, nargs="+", default=[x * 100 for x in TEST_NOISE_LEVELS],
                        help="noise sigma in percent of the bbox diagonal")
    parser.add_argument("--iterations", type=iterations_arg, default="auto",
                        help="a whole number, or auto (default: 1-4 from the estimated noise)")
    parser.add_argument("--synthetic", nargs="*", default=None, metavar="SHAPE",
                        help="evaluate built-in shapes instead of a folder")
    parser.add_argument("--no-thin", action="store_true",
                        help="skip the thin-part block (plate, open box, tube, L-bracket, stool)")
    parser.add_argument("--thin-only", action="store_true", help="only the thin-part block")
    parser.add_argument("--no-tune", action="store_true", help="fixed-k baselines (fast)")
    parser.add_argument("--known-noise", action="store_true",
                        help="give the engine each cloud's true noise sigma (as `denoise --noise` does) "
                             "instead of letting it estimate the noise; the default run is blind")
    parser.add_argument("--json", default=None, help="also write the full result as JSON")
    parser.add_argument("--threads", type=int, default=None)
    args = parser.parse_args(argv)
    if args.threads:
        import torch
        torch.set_num_threads(args.threads)
    from ..core.evaluation.evaluate import evaluate, format_table
    from ..core.evaluation.shapes import THIN_SHAPES, shape_mesh
    from ..core.formats.meshes import find_meshes, read_mesh
    from ..core.model import load_model
    try:
        model = load_model(args.model)
        blocks = {}
        if not args.thin_only:
            if args.synthetic:
                blocks["synthetic"] = [(n, *shape_mesh(n)) for n in args.synthetic]
            else:
                blocks["validation"] = [(p.stem, *read_mesh(p)) for p in find_meshes(args.mesh_dir)]
                if not blocks["validation"]:
                    raise InputError(f"{args.mesh_dir}: no meshes found")
        if not args.no_thin:
            blocks["thin_parts"] = [(n, *shape_mesh(n)) for n in THIN_SHAPES]
    except (InputError, ModelNotFoundError, ModelMismatchError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    results = {}
    for name, shapes in blocks.items():
        print(f"== {name} ({len(shapes)} shapes)", flush=True)
        results[name] = evaluate(shapes, model, [x / 100 for x in args.levels], args.points, args.iterations,
                                 log=lambda m: print(m, flush=True), tune=not args.no_tune,
                                 known_noise=args.known_noise)
    for name, result in results.items():
        print(f"\n## {name}\n\n{format_table(result)}")
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2))
    return 0

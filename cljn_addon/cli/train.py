"""`run.py train`: the two-stage training (core.training.train.train_model) on meshes and
built-in shapes, with the progress bar and log lines on the terminal."""
from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from ..core.errors import Cancelled, InputError
from ..core.training.config import DEFAULT_CACHE, TrainConfig
from .console import err, out
from .exitcodes import EXIT_INTERRUPTED, EXIT_OK, EXIT_USAGE
from .paths import DEFAULT_TRAIN_DIR, DEFAULT_VALIDATION_DIR
from .progress import Progress

PROGRESS_LINE_SECONDS = 60    # off a terminal: a progress line at least this often


def _bool(text):
    return text.lower() in ("1", "true", "yes")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="run.py train",
        description="Train a CLJN model (contrastive stage, then the joint-loss regressor). "
                    "Defaults are the paper's hyper-parameters; see the README for the CPU recipe.")
    parser.add_argument("meshes", nargs="*", help="mesh files or folders (.off/.obj/.ply); "
                        f"default: {DEFAULT_TRAIN_DIR}")
    parser.add_argument("--out", "-o", required=True, help="output folder (weights, config, card, log, checkpoint)")
    parser.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.pt")
    parser.add_argument("--synthetic", nargs="*", default=[], metavar="SHAPE",
                        help="add built-in CAD-like shapes (box, cylinder, star, octahedron, stepped_block, ...)")
    parser.add_argument("--thin-parts", type=int, default=0, metavar="N",
                        help="add N procedural thin-part shapes (plates, plate pairs, tubes, open "
                             "containers, L/T/U/I/Z profiles, gears)")
    parser.add_argument("--relief-parts", type=int, default=0, metavar="N",
                        help="add N procedural carved solids (relief at the noise's own scale)")
    parser.add_argument("--quick", action="store_true", help="small schedule (minutes), as Blender's button")
    parser.add_argument("--cache-dir", default=str(DEFAULT_CACHE), help="where sampled clouds are cached")
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    parser.add_argument("--validation-dir", default=str(DEFAULT_VALIDATION_DIR),
                        help="held-out meshes for the model card's table (skipped if absent; '' to skip)")
    parser.add_argument("--validation-points", type=int, default=20_000)
    parser.add_argument("--no-progress", action="store_true", help="no progress bar or lines")
    for field in dataclasses.fields(TrainConfig):      # every TrainConfig field as --field-name
        flag = "--" + field.name.replace("_", "-")
        if field.type == "bool":
            parser.add_argument(flag, type=_bool, default=None, metavar="BOOL", help=f"default {field.default}")
        else:
            kind = {"int": int, "float": float}.get(field.type, str)
            parser.add_argument(flag, type=kind, default=None, help=f"default {field.default!r}")
    return parser


def _sources(args) -> list:
    from ..core.formats.meshes import find_meshes

    sources = []
    for item in args.meshes or [str(DEFAULT_TRAIN_DIR)]:
        path = Path(item)
        sources += [str(p) for p in find_meshes(path)] if path.is_dir() else [str(path)]
    sources += [f"shape:{name}" for name in args.synthetic]
    sources += [f"thin:{i}" for i in range(args.thin_parts)]
    sources += [f"relief:{i}" for i in range(args.relief_parts)]
    return sources


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if args.threads:
        import torch

        torch.set_num_threads(args.threads)
    from ..core.training.train import train_model

    overrides = {f.name: getattr(args, f.name) for f in dataclasses.fields(TrainConfig)
                 if getattr(args, f.name) is not None}
    try:
        with Progress("training", enabled=not args.no_progress, every=PROGRESS_LINE_SECONDS) as bar:
            train_model(_sources(args), args.out, resume=args.resume, quick=args.quick,
                        progress=bar, log=out, cache_dir=args.cache_dir,
                        validation_dir=args.validation_dir or None,
                        validation_points=args.validation_points, **overrides)
    except InputError as exc:
        err(f"error: {exc}")
        return EXIT_USAGE
    except Cancelled as exc:
        err(str(exc))
        return EXIT_INTERRUPTED
    except KeyboardInterrupt:
        err("interrupted; rerun with --resume to continue from the last checkpoint")
        return EXIT_INTERRUPTED
    return EXIT_OK

"""run.py's entry: the arguments meant for us (plain Python or Blender), the command table and
the dependency check. Importing the command line imports neither bpy nor torch: each command
imports the engine (and, for .blend files, Blender) when it runs.
"""
from __future__ import annotations

import sys

from . import bench, clouds, demo, evaluate, train
from .console import err
from .dependencies import engine_missing_message
from .exitcodes import EXIT_INTERRUPTED, EXIT_OK, EXIT_USAGE, UsageError
from .parser import PROG, build_parser

# Commands that parse their own arguments: name -> (main(argv) -> exit code, help line).
COMMANDS = {
    "train": (train.main, "train a model (contrastive pretraining, then the regressor)"),
    "eval": (evaluate.main, "evaluate a model on test shapes (normal error, Chamfer)"),
    "demo": (demo.main, "denoise built-in noisy shapes and write before/after files"),
    "bench": (bench.main, "time the engine on this machine"),
}


def argv_from_sys(argv=None, in_blender=None) -> list:
    """The arguments meant for us.

    Under Blender sys.argv holds Blender's own arguments (`blender -b -P run.py -- ARGS`):
    take what follows the first `--` (nothing when there is none). Under plain Python take
    argv[1:].
    """
    argv = list(sys.argv if argv is None else argv)
    if in_blender is None:
        head = argv[1:argv.index("--")] if "--" in argv else argv[1:]
        in_blender = _running_inside_blender() or any(
            a in ("-P", "--python", "--python-expr", "-b", "--background") for a in head)
    if in_blender:
        return argv[argv.index("--") + 1:] if "--" in argv else []
    return argv[1:]


def _running_inside_blender() -> bool:
    """True in the Blender application (not the bpy wheel, whose binary_path is empty)."""
    bpy = sys.modules.get("bpy")
    if bpy is None:
        return False
    try:
        return bool(bpy.app.binary_path) and not getattr(bpy.app, "module", False)
    except AttributeError:
        return False


def main(argv=None) -> int:
    argv = argv_from_sys() if argv is None else list(argv)
    if argv and argv[0] in COMMANDS:
        return _run_command(argv[0], argv[1:])
    parser = build_parser(COMMANDS)
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:                    # argparse: 0 for --help, 2 for usage errors
        return int(exc.code or 0) if not isinstance(exc.code, str) else EXIT_USAGE
    try:
        return clouds.CloudCommand(args).run()
    except UsageError as exc:
        err(f"{PROG} {args.command}: error: {exc}")
        return EXIT_USAGE
    except KeyboardInterrupt:
        err("interrupted; no partial output was written")
        return EXIT_INTERRUPTED


# Commands that build or train torch networks; denoise and normals run without torch (numpy).
NEEDS_TORCH = ("train", "eval", "demo", "bench")


def _run_command(name, rest) -> int:
    message = engine_missing_message()
    if message:
        err(message)
        return EXIT_USAGE
    if name in NEEDS_TORCH and not any(a in ("-h", "--help") for a in rest):
        from ..core.options import torch_available

        if not torch_available():
            err(f"error: `{name}` needs torch, which is not installed in this Python "
                "(pip install -r requirements.txt); denoise and normals run without it")
            return EXIT_USAGE
    entry = COMMANDS[name][0]
    try:
        code = entry(rest)
    except KeyboardInterrupt:
        err("interrupted")
        return EXIT_INTERRUPTED
    except SystemExit as exc:                    # argparse --help and usage errors
        code = exc.code
    if code is None:
        return EXIT_OK
    return code if isinstance(code, int) else EXIT_USAGE

"""Headless command line for CLJN Denoise.

Two ways in, same arguments, same results:

    python standalone/run.py COMMAND ARGS...                 (Python 3.11 with the bpy wheel)
    blender -b -P standalone/run.py -- COMMAND ARGS...       (Blender 4.2+; arguments after --)

Both run the engine in `cljn_addon.core` and, for .blend files, the extension's own object
code in `cljn_addon.blender.object_io`. This module imports neither bpy nor torch at import
time: bpy is imported only for .blend input/output and --preview, torch only with the engine.

Exit codes: 0 success; 1 unexpected internal error; 2 bad input or usage (also a missing or
mismatched model, and a batch whose inputs all failed); 3 a batch where some inputs failed
(the others are processed and written); 130 interrupted.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import re
import shutil
import sys
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path

EXIT_OK = 0
EXIT_INTERNAL = 1
EXIT_USAGE = 2
EXIT_PARTIAL = 3
EXIT_INTERRUPTED = 130

PROG = "run.py"
POINT_SUFFIXES = (".ply", ".xyz", ".npy")
BLEND_SUFFIX = ".blend"
ALL_SUFFIXES = POINT_SUFFIXES + (BLEND_SUFFIX,)

# Commands implemented in the engine; each module has main(argv) -> exit code and its own --help.
DISPATCH = {
    "train": ("cljn_addon.core.training.train", "train a model (contrastive pretraining, then the regressor)"),
    "eval": ("cljn_addon.cli.evaluate", "evaluate a model on test shapes (normal error, Chamfer)"),
    "demo": ("cljn_addon.core.evaluation.demo", "denoise built-in noisy shapes and write before/after files"),
    "bench": ("cljn_addon.core.evaluation.benchmark", "time the engine on this machine"),
}

EPILOG = """\
invocation:
  python standalone/run.py COMMAND ...            (Python 3.11 with the bpy wheel)
  blender -b -P standalone/run.py -- COMMAND ...  (Blender 4.2 or newer)

formats (by extension):
  .ply    in: ascii and binary (little/big endian), any extra properties (kept)
          out: binary little endian: x y z nx ny nz, the input's other properties,
               cljn_outlier (uchar, 1 = flagged as outlier)
  .xyz    in/out: "x y z" per line; normals in the sibling .normals file (PCPNet layout);
          other properties are not written
  .npy    in: (N,3), (N,6) x y z nx ny nz, or a structured array with x y z fields
          out: (N,6) x y z nx ny nz in the input's float type
  .blend  in: every point-cloud object (or --objects NAME...) is processed; other objects
          are left alone; saved as a new .blend (or --in-place, keeping NAME.blend1)
          out from a point file: a new scene holding the cloud as a mesh of vertices

exit codes:
  0    success
  1    unexpected internal error (a bug; rerun with --debug and report it)
  2    bad input or usage: unreadable/truncated/empty file, NaN coordinates, a .blend
       without point clouds, a missing or mismatched model (also: every input of a batch
       failed)
  3    a batch where some inputs failed; the others were processed and written
  130  interrupted (Ctrl-C); no partial output is left behind
"""


class UsageError(Exception):
    """Bad command line: one line on stderr, exit 2."""


# ============================================================================ argv handling

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


# ============================================================================ argument parser

def _positive_int(text):
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def _percent(text):
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not (0.0 < value <= 100.0) or not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be above 0 and at most 100 (percent), got {text}")
    return value


def _finite(text):
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be finite, got {text}")
    return value


def _add_cloud_options(p: argparse.ArgumentParser, normals_only: bool):
    p.add_argument("inputs", nargs="+", metavar="INPUT",
                   help="point clouds (.ply .xyz .npy) or Blender scenes (.blend)")
    out = p.add_argument_group("output (one of -o, --out-dir, --in-place)")
    dest = out.add_mutually_exclusive_group(required=True)
    dest.add_argument("-o", "--output", metavar="OUTPUT",
                      help="output file for a single input; its extension picks the format")
    dest.add_argument("--out-dir", metavar="DIR",
                      help="write each result as DIR/<input name> (created if missing)")
    dest.add_argument("--in-place", action="store_true",
                      help="replace each input, keeping a backup (NAME.blend1 for .blend, "
                           "NAME.bak otherwise)")
    out.add_argument("--format", choices=[s[1:] for s in ALL_SUFFIXES],
                     help="with --out-dir: output format (default: the input's)")
    out.add_argument("--report", metavar="FILE.json",
                     help="write a machine-readable summary (per input: points, outliers, "
                          "seconds, output path, status)")
    out.add_argument("--preview", metavar="FILE.png",
                     help="render a before/after picture (several clouds: FILE_<name>.png)")
    out.add_argument("--preview-color", choices=["normal", "displacement"], default="normal",
                     help="colour the result by normal (default) or by displacement")
    blend = p.add_argument_group(".blend input")
    blend.add_argument("--objects", nargs="+", metavar="NAME",
                       help="process only these objects (default: every point-cloud object); "
                            "put it after the inputs")
    blend.add_argument("--use-mesh-vertices", action="store_true",
                       help="treat the vertices of any mesh as a point cloud")
    eng = p.add_argument_group("engine (as in the panel)")
    eng.add_argument("--model", metavar="FILE.safetensors",
                     help="weights file with its .json beside it (default: the shipped model)")
    eng.add_argument("--iterations", type=_positive_int, default=4,
                     help=("accepted for symmetry with denoise: normals take one network pass"
                           if normals_only else
                           "filtering iterations (default 4; 10 for very noisy scans)"))
    eng.add_argument("--patch-radius", type=_percent, metavar="PERCENT",
                     help="patch radius in percent of the bounding-box diagonal (default 5)")
    eng.add_argument("--orient", choices=["outward", "viewpoint", "none"], default="outward",
                     help="normal orientation (default outward)")
    eng.add_argument("--viewpoint", type=_finite, nargs=3, metavar=("X", "Y", "Z"),
                     help="with --orient viewpoint: the scanner position (a .blend uses its "
                          "scene camera when this is not given)")
    eng.add_argument("--device", default="auto",
                     help="auto (default), cpu, cuda, gpu or mps")
    eng.add_argument("--threads", type=_positive_int, metavar="N",
                     help="CPU threads for the network (torch.set_num_threads)")
    eng.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    misc = p.add_argument_group("messages")
    misc.add_argument("--no-progress", action="store_true", help="no progress bar or lines")
    misc.add_argument("--debug", action="store_true", help="print tracebacks of internal errors")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=PROG, formatter_class=argparse.RawDescriptionHelpFormatter,
        description="CLJN Denoise: filter point clouds and estimate their normals with a "
                    "learned network (contrastive learning for joint normal estimation and "
                    "point-cloud filtering).",
        epilog=EPILOG)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    p = sub.add_parser("denoise", help="filter positions and estimate normals",
                       formatter_class=argparse.RawDescriptionHelpFormatter, epilog=EPILOG,
                       description="Filter positions and estimate normals of point clouds.")
    _add_cloud_options(p, normals_only=False)
    p = sub.add_parser("normals", help="estimate normals only (positions bit-identical)",
                       formatter_class=argparse.RawDescriptionHelpFormatter, epilog=EPILOG,
                       description="Estimate normals only; positions are written back "
                                   "bit-identical.")
    _add_cloud_options(p, normals_only=True)
    for name, (_module, text) in DISPATCH.items():
        sub.add_parser(name, help=f"{text} (see: {PROG} {name} --help)", add_help=False)
    return parser


# ============================================================================ main

def main(argv=None) -> int:
    argv = argv_from_sys() if argv is None else list(argv)
    if argv and argv[0] in DISPATCH:
        return _dispatch(argv[0], argv[1:])
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:                    # argparse: 0 for --help, 2 for usage errors
        return int(exc.code or 0) if not isinstance(exc.code, str) else EXIT_USAGE
    try:
        return CloudCommand(args).run()
    except UsageError as exc:
        _err(f"{PROG} {args.command}: error: {exc}")
        return EXIT_USAGE
    except KeyboardInterrupt:
        _err("interrupted; no partial output was written")
        return EXIT_INTERRUPTED


ENGINE_MODULES = ("numpy", "scipy", "torch", "safetensors")


def _engine_dependencies_missing() -> list:
    """Names of the engine's packages that cannot be imported. Inside Blender, first add the
    folders where the extension's Install Dependencies button puts them."""
    import importlib.util

    def missing():
        importlib.invalidate_caches()
        return [m for m in ENGINE_MODULES if importlib.util.find_spec(m) is None]

    gone = missing()
    if gone and "bpy" in sys.modules:
        for folder in _blender_site_packages():
            if folder not in sys.path:
                sys.path.append(folder)          # appended: Blender's own numpy stays first
        gone = missing()
    return gone


def _blender_site_packages() -> list:
    """Where the extension installs torch & co.: its user folder in any extension repository,
    or (loaded as a plain package, as here) the fallback folder of cljn_addon.blender.deps."""
    folders = []
    try:
        import bpy

        root = bpy.utils.user_resource("EXTENSIONS", path=".user")
        if root and os.path.isdir(root):
            for repo in sorted(os.listdir(root)):
                folders.append(os.path.join(root, repo, "cljn_denoise", "site-packages"))
        from .blender import deps

        folders.append(deps.site_packages_dir(create=False))
    except Exception:                                     # noqa: BLE001 - best effort only
        pass
    return [f for f in folders if f and os.path.isdir(f)]


def _missing_dependencies_message(names) -> str:
    where = ("Blender's Python: install them with the extension's Install Dependencies button "
             "(Edit > Preferences > Add-ons > CLJN Denoise)" if "bpy" in sys.modules else
             "this Python: pip install -r requirements.txt")
    return f"error: {', '.join(names)} not installed in {where}"


def _dispatch(name, rest) -> int:
    import importlib

    module_name = DISPATCH[name][0]
    gone = _engine_dependencies_missing()
    if gone:
        _err(_missing_dependencies_message(gone))
        return EXIT_USAGE
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        if exc.name and module_name.startswith(exc.name):
            _err(f"{PROG}: error: the '{name}' command is not available in this build")
            return EXIT_USAGE
        raise
    try:
        code = module.main(rest)
    except KeyboardInterrupt:
        _err("interrupted")
        return EXIT_INTERRUPTED
    except SystemExit as exc:
        code = exc.code
    if code is None:
        return EXIT_OK
    return code if isinstance(code, int) else EXIT_USAGE


def _err(line: str):
    print(line, file=sys.stderr, flush=True)


def _out(line: str):
    print(line, file=sys.stdout, flush=True)


# ============================================================================ progress

class Progress:
    """progress(fraction, message) callback: a tqdm bar with ETA on a terminal, plain lines
    (every 10 %, with an estimate of the time left) otherwise."""

    def __init__(self, label: str, enabled: bool = True, stream=None):
        self.label = label
        self.stream = stream or sys.stderr
        self.enabled = enabled
        self.tty = enabled and hasattr(self.stream, "isatty") and self.stream.isatty()
        self.bar = None
        self.start = time.monotonic()
        self.last_step = -1
        self.last_message = None
        self.done = 0.0

    def __call__(self, fraction, message=""):
        if not self.enabled:
            return
        fraction = min(max(float(fraction), 0.0), 1.0)
        if self.tty:
            if self.bar is None:
                from tqdm import tqdm

                self.bar = tqdm(total=100.0, desc=self.label, file=self.stream, leave=False,
                                **_terminal_size(self.stream),
                                bar_format="{desc}: {percentage:3.0f}%|{bar}| "
                                           "[{elapsed}<{remaining}]{postfix}")
            value = round(100.0 * fraction, 2)
            if message != self.last_message:
                self.bar.set_postfix_str(message, refresh=False)
                self.last_message = message
            if value > self.done:
                self.bar.update(value - self.done)
                self.done = value
            else:
                self.bar.refresh()
            return
        step = int(fraction * 10)
        if step > self.last_step:
            self.last_step = step
            elapsed = time.monotonic() - self.start
            eta = ""
            if 0.0 < fraction < 1.0 and elapsed > 1.0:
                eta = f", about {_duration(elapsed * (1.0 - fraction) / fraction)} left"
            text = f"{self.label}: {100.0 * fraction:3.0f}%{eta}" + (f" ({message})" if message
                                                                     else "")
            print(text, file=self.stream, flush=True)

    def close(self):
        if self.bar is not None:
            self.bar.close()
            self.bar = None


def _terminal_size(stream) -> dict:
    """tqdm size overrides for terminals that report a size of 0 (tqdm then draws nothing)."""
    try:
        size = os.get_terminal_size(stream.fileno())
    except (AttributeError, OSError, ValueError):
        return {}
    out = {}
    if size.columns <= 0:
        out["ncols"] = 80
    if size.lines <= 0:
        out["nrows"] = 24
    return out


def _duration(seconds: float) -> str:
    seconds = max(0, int(round(seconds)))
    if seconds < 90:
        return f"{seconds} s"
    minutes, seconds = divmod(seconds, 60)
    if minutes < 90:
        return f"{minutes} min {seconds:02d} s"
    hours, minutes = divmod(minutes, 60)
    return f"{hours} h {minutes:02d} min"


# ============================================================================ jobs

@dataclass
class Job:
    input: Path
    output: Path
    report: dict = field(default_factory=dict)

    @property
    def is_blend(self) -> bool:
        return self.input.suffix.lower() == BLEND_SUFFIX


@dataclass
class PreviewItem:
    label: str
    before: object
    after: object
    normals: object
    displacement: object
    outliers: object
    job: object = None


def _same_file(a: Path, b: Path) -> bool:
    try:
        if a.exists() and b.exists():
            return os.path.samefile(a, b)
    except OSError:
        pass
    return os.path.normcase(os.path.abspath(a)) == os.path.normcase(os.path.abspath(b))


def _backup_path(path: Path) -> Path:
    if path.suffix.lower() == BLEND_SUFFIX:
        return path.with_name(path.name + "1")          # Blender's own backup name
    return path.with_name(path.name + ".bak")


def _outputs_of(path: Path) -> list:
    if path.suffix.lower() == ".xyz":
        return [path, path.with_suffix(".normals")]
    return [path]


class CloudCommand:
    """`denoise` and `normals`."""

    def __init__(self, args):
        self.args = args
        self.normals_only = args.command == "normals"
        self.model = None
        self.previews: list[PreviewItem] = []
        self.jobs = self._plan()

    # ------------------------------------------------------------------ planning
    def _plan(self) -> list:
        a = self.args
        inputs = [Path(p) for p in a.inputs]
        for p in inputs:
            if p.suffix.lower() not in ALL_SUFFIXES:
                raise UsageError(f"{p}: unsupported input format {p.suffix or '(none)'!r} "
                                 f"(use {', '.join(ALL_SUFFIXES)})")
        if a.format and not a.out_dir:
            raise UsageError("--format goes with --out-dir (with -o the extension picks it)")
        if a.objects and not any(p.suffix.lower() == BLEND_SUFFIX for p in inputs):
            raise UsageError("--objects applies to .blend inputs only")
        if a.viewpoint is not None and a.orient != "viewpoint":
            raise UsageError("--viewpoint goes with --orient viewpoint")
        if a.orient == "viewpoint" and a.viewpoint is None:
            plain = [p for p in inputs if p.suffix.lower() != BLEND_SUFFIX]
            if plain:
                raise UsageError(f"--orient viewpoint needs --viewpoint X Y Z for {plain[0]}")
        if a.preview and Path(a.preview).suffix.lower() != ".png":
            raise UsageError(f"--preview wants a .png file name, got {a.preview}")
        if a.report and Path(a.report).suffix.lower() != ".json":
            raise UsageError(f"--report wants a .json file name, got {a.report}")
        jobs = []
        if a.output:
            if len(inputs) != 1:
                raise UsageError(f"-o takes a single input ({len(inputs)} given); "
                                 "use --out-dir for several")
            jobs.append(Job(inputs[0], Path(a.output)))
        elif a.out_dir:
            out_dir = Path(a.out_dir)
            for p in inputs:
                suffix = "." + a.format if a.format else p.suffix.lower()
                jobs.append(Job(p, out_dir / (p.stem + suffix)))
        else:
            jobs = [Job(p, p) for p in inputs]
        seen = {}
        for job in jobs:
            out_suffix = job.output.suffix.lower()
            if out_suffix not in ALL_SUFFIXES:
                raise UsageError(f"{job.output}: unsupported output format "
                                 f"{job.output.suffix or '(none)'!r} (use {', '.join(ALL_SUFFIXES)})")
            if job.is_blend and out_suffix != BLEND_SUFFIX:
                raise UsageError(f"{job.input}: a .blend input is saved as a .blend, "
                                 f"not {out_suffix}")
            for target in _outputs_of(job.output):
                if not a.in_place:
                    for p in inputs:
                        if _same_file(target, p):
                            raise UsageError(f"{target} is an input: refusing to overwrite it "
                                             "(use --in-place, or another output name)")
                key = os.path.normcase(os.path.abspath(target))
                if key in seen:
                    raise UsageError(f"{seen[key]} and {job.input} would both be written to "
                                     f"{target}")
                seen[key] = job.input
        return jobs

    # ------------------------------------------------------------------ running
    def run(self) -> int:
        a = self.args
        t_start = time.monotonic()
        for job in self.jobs:
            job.report = {"input": str(job.input), "output": None, "status": "pending"}
        gone = _engine_dependencies_missing()
        if gone:
            _err(_missing_dependencies_message(gone))
            return EXIT_USAGE
        try:
            self._load_model()
        except _ModelError as exc:
            _err(f"error: {exc}")
            for job in self.jobs:
                job.report.update(status="error", error=str(exc))
            self._write_report(EXIT_USAGE, time.monotonic() - t_start, model_error=str(exc))
            return EXIT_USAGE
        failures, internal = 0, 0
        for job in self.jobs:
            try:
                if job.is_blend:
                    self._run_blend(job)
                else:
                    self._run_points(job)
                job.report["status"] = "ok"
            except KeyboardInterrupt:
                job.report.update(status="error", error="interrupted")
                self._write_report(EXIT_INTERRUPTED, time.monotonic() - t_start)
                raise
            except Exception as exc:                              # noqa: BLE001
                failures += 1
                message, is_internal = self._describe(job, exc)
                internal += is_internal
                _err(f"error: {message}")
                if is_internal and a.debug:
                    traceback.print_exc()
                job.report.update(status="error", error=message, output=None)
        if failures == 0:
            code = EXIT_OK
        elif failures < len(self.jobs):
            code = EXIT_PARTIAL
        else:
            code = EXIT_INTERNAL if internal == failures else EXIT_USAGE
        if a.preview and self.previews:
            self._write_previews()
        if len(self.jobs) > 1:
            ok = len(self.jobs) - failures
            _out(f"{ok} of {len(self.jobs)} inputs done" + (f", {failures} failed" if failures
                                                           else ""))
        self._write_report(code, time.monotonic() - t_start)
        return code

    def _describe(self, job, exc):
        """(one-line message naming the file, is it an internal error?)."""
        from .core.errors import Cancelled, InputError

        name = str(job.input)
        if isinstance(exc, (InputError, Cancelled, _BlendError)):
            text = str(exc)
            return (text if text.startswith(name) else f"{name}: {text}"), False
        if isinstance(exc, OSError):
            where = exc.filename or name
            return f"{where}: {exc.strerror or exc}", False
        if isinstance(exc, MemoryError):
            return f"{name}: out of memory (try a smaller cloud or fewer threads)", False
        return (f"{name}: internal error: {type(exc).__name__}: {exc}"
                + ("" if self.args.debug else " (rerun with --debug for details)")), True

    def _load_model(self):
        from . import core

        a = self.args
        if a.threads:
            import torch

            torch.set_num_threads(a.threads)
        try:
            self.model = core.load_model(a.model)
        except (core.ModelNotFoundError, core.ModelMismatchError) as exc:
            raise _ModelError(f"model: {exc}") from None
        except OSError as exc:
            raise _ModelError(f"model: {a.model}: {exc.strerror or exc}") from None

    def _engine(self, points, label, viewpoint=None):
        from . import core

        a = self.args
        kwargs = dict(iterations=a.iterations, orientation=a.orient, device=a.device, seed=a.seed,
                      viewpoint=viewpoint if viewpoint is not None else a.viewpoint)
        if a.patch_radius is not None:
            kwargs["patch_radius_fraction"] = a.patch_radius / 100.0
        progress = Progress(label, enabled=not a.no_progress)
        try:
            fn = core.estimate_normals if self.normals_only else core.denoise
            return fn(points, self.model, progress=progress, **kwargs)
        finally:
            progress.close()

    def _stats(self, label, res, output=None) -> dict:
        import numpy as np

        n = int(len(res.points))
        outliers = int(np.count_nonzero(res.outliers))
        disp = float(np.mean(res.displacement)) if n else 0.0
        seconds = float(getattr(res, "seconds", 0.0) or 0.0)
        line = (f"{label}: {n} points, {outliers} outliers flagged, "
                f"mean displacement {disp:.4g}, {seconds:.1f} s")
        if output is not None:
            line += f" -> {output}"
        _out(line)
        return {"points": n, "outliers": outliers, "mean_displacement": disp,
                "seconds": round(seconds, 3)}

    def _keep_preview(self, job, label, before, res):
        if not self.args.preview:
            return
        import numpy as np

        n = len(before)
        keep = slice(None)
        if n > PREVIEW_MAX_POINTS:
            keep = np.sort(np.random.default_rng(0).choice(n, PREVIEW_MAX_POINTS, replace=False))
        self.previews.append(PreviewItem(
            label, np.asarray(before, np.float64)[keep], np.asarray(res.points, np.float64)[keep],
            np.asarray(res.normals, np.float64)[keep],
            np.asarray(res.displacement, np.float64)[keep], np.asarray(res.outliers, bool)[keep],
            job))

    # ------------------------------------------------------------------ point files
    def _run_points(self, job):
        import numpy as np

        from .core.formats import points as pointio

        cloud = pointio.read_points(job.input)
        points = pointio.check_points(cloud.points, str(job.input))
        res = self._engine(points, job.input.name)
        dtype = cloud.points.dtype if cloud.points.dtype.kind == "f" else np.float64
        out_points = cloud.points if self.normals_only else np.asarray(res.points).astype(dtype)
        comment = ("CLJN Denoise: normals estimated" if self.normals_only
                   else "CLJN Denoise: positions filtered, normals estimated")
        result = pointio.PointCloud(out_points, np.asarray(res.normals, np.float32),
                                    dict(cloud.extra), None,
                                    [c for c in cloud.comments if not c.startswith("CLJN Denoise")]
                                    + [comment])
        if self.args.in_place:
            self._backup(job.output)
        job.output.parent.mkdir(parents=True, exist_ok=True)
        if job.output.suffix.lower() == BLEND_SUFFIX:
            written = [self._save_cloud_as_blend(job, cloud, res)]
        else:
            written = pointio.write_points(job.output, result, outliers=res.outliers)
        job.report["output"] = str(job.output)
        if len(written) > 1:
            job.report["files"] = [str(p) for p in written]
        job.report.update(self._stats(str(job.input), res, job.output))
        self._keep_preview(job, job.input.stem, points, res)

    def _save_cloud_as_blend(self, job, cloud, res) -> Path:
        """A new .blend holding the cloud as a mesh of vertices only (the extension's point
        cloud), its other properties as point attributes, the result written by object_io."""
        import numpy as np

        bpy = _import_bpy()
        from .blender import object_io

        with _quiet_stdout():
            bpy.ops.wm.read_factory_settings(use_empty=True)
        name = job.input.stem
        mesh = bpy.data.meshes.new(name)
        mesh.vertices.add(len(cloud.points))
        mesh.vertices.foreach_set("co", np.asarray(cloud.points, np.float32).ravel())
        for key, values in cloud.extra.items():
            attr_name = re.sub(r"[^A-Za-z0-9_]", "_", key)
            if attr_name in mesh.attributes or attr_name == "position" or \
                    attr_name.startswith("cljn_"):
                continue
            values = np.asarray(values)
            if values.dtype == np.bool_:
                kind, data = "BOOLEAN", values
            elif values.dtype.kind in "iu" and values.dtype.itemsize <= 2 or values.dtype in (
                    np.int32,):
                kind, data = "INT", values.astype(np.int32)
            else:
                kind, data = "FLOAT", values.astype(np.float32)
            mesh.attributes.new(attr_name, kind, "POINT").data.foreach_set("value", data)
        mesh.update()
        obj = bpy.data.objects.new(name, mesh)
        bpy.context.scene.collection.objects.link(obj)
        for warning in object_io.write_result(obj, res, normals_only=self.normals_only) or ():
            _err(f"warning: {job.input}: {warning}")
        _save_blend(bpy, job.output)
        return job.output

    def _backup(self, path: Path):
        """Copy each file about to be replaced to its backup name (atomically)."""
        from .core.formats.points import atomic_paths

        for target in _outputs_of(path):
            if target.exists():
                backup = _backup_path(target)
                with atomic_paths(backup) as (tmp,):
                    shutil.copy2(target, tmp)

    # ------------------------------------------------------------------ .blend files
    def _run_blend(self, job):
        import numpy as np

        from .core.formats import points as pointio

        bpy = _import_bpy()
        from .blender import object_io

        a = self.args
        if not job.input.exists():
            raise _BlendError(f"{job.input}: file not found")
        try:
            with _quiet_stdout():
                bpy.ops.wm.open_mainfile(filepath=str(job.input.resolve()), load_ui=False)
        except RuntimeError as exc:
            raise _BlendError(f"{job.input}: not a readable .blend file "
                              f"({_first_line(exc)})") from None
        objects = self._blend_objects(job, bpy, object_io)
        options = {}
        if a.orient == "viewpoint" and a.viewpoint is None:      # the panel's "Toward Camera"
            if bpy.context.scene is None or bpy.context.scene.camera is None:
                raise _BlendError(f"{job.input}: --orient viewpoint needs --viewpoint X Y Z "
                                  "(the scene has no camera to use instead)")
            options = object_io.orientation_options(bpy.context.scene, "CAMERA")
        per_object, results = [], []
        for obj in objects:
            label = f"{job.input} [{obj.name}]"
            matrix = np.array(obj.matrix_world, dtype=np.float64)
            points = pointio.check_points(object_io.read_world_points(obj, matrix), label)
            res = self._engine(points, f"{job.input.name} [{obj.name}]", options.get("viewpoint"))
            results.append((obj, res, matrix))
            stats = self._stats(label, res)
            per_object.append({"name": obj.name, **stats})
            self._keep_preview(job, f"{job.input.stem}_{obj.name}", points, res)
        for obj, res, matrix in results:                 # all computed: now change the scene
            for warning in object_io.write_result(obj, res, normals_only=self.normals_only,
                                                  matrix_world=matrix) or ():
                _err(f"warning: {job.input}: {warning}")
        if a.in_place:
            self._backup(job.output)
        job.output.parent.mkdir(parents=True, exist_ok=True)
        _save_blend(bpy, job.output)
        job.report["output"] = str(job.output)
        job.report["objects"] = per_object
        job.report.update(
            points=sum(o["points"] for o in per_object),
            outliers=sum(o["outliers"] for o in per_object),
            mean_displacement=(float(np.average([o["mean_displacement"] for o in per_object],
                                                weights=[o["points"] for o in per_object]))),
            seconds=round(sum(o["seconds"] for o in per_object), 3))
        _out(f"{job.input}: {len(per_object)} point-cloud object(s) -> {job.output}")

    def _blend_objects(self, job, bpy, object_io):
        a = self.args
        use_verts = a.use_mesh_vertices
        if a.objects:
            chosen = []
            for name in a.objects:
                obj = bpy.data.objects.get(name)
                if obj is None:
                    found = [o.name for o in object_io.point_cloud_objects(bpy.data.objects,
                                                                           use_verts)]
                    raise _BlendError(f"{job.input}: no object named {name!r} (point clouds "
                                      f"here: {', '.join(found) or 'none'})")
                reason = object_io.check_point_cloud(obj, use_verts)
                if reason is not None:
                    raise _BlendError(f"{job.input}: {reason}")
                chosen.append(obj)
            return chosen
        chosen = list(object_io.point_cloud_objects(bpy.data.objects, use_verts))
        if not chosen:
            raise _BlendError(f"{job.input}: no point-cloud objects in this .blend"
                              + ("" if use_verts else
                                 " (--use-mesh-vertices takes any mesh's vertices)"))
        return chosen

    # ------------------------------------------------------------------ report and preview
    def _write_report(self, code, seconds, model_error=None):
        a = self.args
        if not a.report:
            return
        from .core.formats.points import atomic_paths

        report = {
            "command": a.command,
            "exit_code": code,
            "model": a.model or "default",
            "options": {"iterations": a.iterations, "patch_radius_percent": a.patch_radius,
                        "orient": a.orient, "viewpoint": a.viewpoint, "device": a.device,
                        "threads": a.threads, "seed": a.seed, "in_place": a.in_place,
                        "objects": a.objects, "use_mesh_vertices": a.use_mesh_vertices},
            "inputs": [job.report for job in self.jobs],
            "succeeded": sum(job.report.get("status") == "ok" for job in self.jobs),
            "failed": sum(job.report.get("status") == "error" for job in self.jobs),
            "seconds": round(seconds, 3),
        }
        if model_error:
            report["error"] = model_error
        path = Path(a.report)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            with atomic_paths(path) as (tmp,):
                tmp.write_text(json.dumps(report, indent=2) + "\n")
        except OSError as exc:
            _err(f"error: {path}: cannot write the report ({exc.strerror or exc})")

    def _write_previews(self):
        a = self.args
        base = Path(a.preview)
        used = set()
        for item in self.previews:
            target = base
            if len(self.previews) > 1:
                safe = re.sub(r"[^A-Za-z0-9._-]+", "_", item.label).strip("_") or "cloud"
                name, k = safe, 1
                while name in used:
                    k += 1
                    name = f"{safe}_{k}"
                used.add(name)
                target = base.with_name(f"{base.stem}_{name}{base.suffix}")
            try:
                render_preview(item, target, color_by=a.preview_color,
                               title=("normals" if self.normals_only else "denoised"))
            except Exception as exc:                                # noqa: BLE001
                _err(f"warning: {target}: preview not written ({type(exc).__name__}: {exc})")
                if a.debug:
                    traceback.print_exc()
                continue
            _out(f"preview: {target}")
            if item.job is not None:
                item.job.report.setdefault("previews", []).append(str(target))


class _ModelError(Exception):
    pass


class _BlendError(Exception):
    """A .blend the user can fix (message names the file)."""


def _first_line(exc) -> str:
    text = str(exc).strip()
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    return lines[0] if lines else type(exc).__name__


# ============================================================================ bpy helpers

def _import_bpy():
    try:
        import bpy
    except ImportError:
        raise _BlendError("this needs Blender's Python module: run under Blender "
                          "(blender -b -P standalone/run.py -- ...) or install the bpy wheel") \
            from None
    return bpy


@contextlib.contextmanager
def _quiet_stdout():
    """Silence Blender's C-level chatter on stdout ("Read blend: ...", "Saved: ..." with our
    temporary names), so that stdout carries our summary lines only. Failures still reach us:
    the operators raise RuntimeError with Blender's message."""
    try:
        fd = sys.stdout.fileno()
    except (AttributeError, OSError, ValueError):
        yield
        return
    sys.stdout.flush()
    saved = os.dup(fd)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, fd)
        yield
    finally:
        try:
            sys.stdout.flush()
        except (OSError, ValueError):
            pass
        os.dup2(saved, fd)
        os.close(saved)
        os.close(devnull)


def _save_blend(bpy, target: Path):
    """Save a copy of the open file to `target` atomically (temporary .blend, then replace)."""
    from .core.formats.points import atomic_paths

    with atomic_paths(target) as (tmp,):
        tmp.unlink()                      # Blender writes it; an existing file would be backed up
        try:
            with _quiet_stdout():
                result = bpy.ops.wm.save_as_mainfile(filepath=str(tmp.resolve()), copy=True,
                                                     check_existing=False)
        except RuntimeError as exc:
            raise _BlendError(f"{target}: cannot save ({_first_line(exc)})") from None
        if "FINISHED" not in result or not tmp.exists():
            raise _BlendError(f"{target}: Blender did not save the file")
        for stray in (tmp.with_name(tmp.name + "1"),):
            if stray.exists():
                stray.unlink()


# ============================================================================ preview

PREVIEW_MAX_POINTS = 30000
PREVIEW_SIZE = (960, 480)


def _srgb_to_linear(c):
    import numpy as np

    c = np.clip(c, 0.0, 1.0)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def _ramp(t):
    """Dark blue -> teal -> yellow for t in [0, 1] (a viridis-like ramp, sRGB)."""
    import numpy as np

    stops = np.array([[0.27, 0.00, 0.33], [0.23, 0.32, 0.55], [0.13, 0.57, 0.55],
                      [0.37, 0.79, 0.38], [0.99, 0.91, 0.14]])
    t = np.clip(np.asarray(t, np.float64), 0.0, 1.0) * (len(stops) - 1)
    i = np.minimum(t.astype(int), len(stops) - 2)
    f = (t - i)[:, None]
    return stops[i] * (1.0 - f) + stops[i + 1] * f


def render_preview(item: PreviewItem, target: Path, color_by="normal", title="denoised"):
    """Render input (left, grey, depth-shaded) and result (right, coloured) side by side with
    Cycles on the CPU (works headless, in the bpy wheel and in `blender -b`)."""
    import numpy as np

    from .core.formats.points import atomic_paths

    bpy = _import_bpy()
    with _quiet_stdout():
        bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene

    before, after = item.before, item.after
    both = np.concatenate([before, after])
    lo, hi = both.min(axis=0), both.max(axis=0)
    centre = (lo + hi) / 2.0
    diag = float(np.linalg.norm(hi - lo)) or 1.0
    view = np.array([0.55, -1.0, 0.45])              # camera looks along -view
    view /= np.linalg.norm(view)
    right = np.cross([0.0, 0.0, 1.0], view)
    right /= np.linalg.norm(right)
    up = np.cross(view, right)

    def place(p):
        return (p - centre) / diag                    # unit diagonal, centred

    b, r = place(before), place(after)
    # Horizontal half-width of each cloud on screen, to space them.
    half = max(np.abs(b @ right).max(), np.abs(r @ right).max(), 1e-3)
    vert = max(np.abs(b @ up).max(), np.abs(r @ up).max(), 1e-3)
    gap = 0.15 * half + 0.02
    offset = half + gap / 2
    width = 2 * (2 * half + gap) * 1.08
    aspect = PREVIEW_SIZE[0] / PREVIEW_SIZE[1]
    width = max(width, 2 * vert * 1.25 * aspect)       # fit the taller side too
    radius = _splat_radius(r)

    def depth_shade(p):
        d = p @ view
        span = float(d.max() - d.min()) or 1.0
        return 0.55 + 0.45 * (d - d.min()) / span     # nearer is brighter

    grey = np.repeat((0.62 * depth_shade(b))[:, None], 3, axis=1)
    if color_by == "displacement":
        disp = np.asarray(item.displacement, np.float64)
        scale = float(np.percentile(disp, 99)) if len(disp) and disp.max() > 0 else 1.0
        colours = _ramp(disp / (scale or 1.0))
    else:
        nrm = np.asarray(item.normals, np.float64)
        colours = 0.5 + 0.5 * nrm * (0.75 + 0.25 * depth_shade(r))[:, None]
    outl = np.asarray(item.outliers, bool)
    grey[outl] = (0.9, 0.1, 0.1)
    colours[outl] = (0.9, 0.1, 0.1)

    mat = _emission_material(bpy, "cljn_preview")
    group = _points_node_group(bpy, radius, mat)
    _add_cloud(bpy, scene, "before", b - offset * right, grey, group)
    _add_cloud(bpy, scene, "after", r + offset * right, colours, group)
    _add_label(bpy, scene, "input", -offset * right + up * (vert + 0.03), view, right, up,
               width * 0.035)
    _add_label(bpy, scene, title, offset * right + up * (vert + 0.03), view, right, up,
               width * 0.035)

    cam_data = bpy.data.cameras.new("cljn_preview_camera")
    cam_data.type = "ORTHO"
    cam_data.ortho_scale = width
    cam = bpy.data.objects.new("cljn_preview_camera", cam_data)
    scene.collection.objects.link(cam)
    cam.matrix_world = _look_matrix(view * 4.0 + up * 0.03, view, right, up)
    cam_data.clip_end = 20.0
    scene.camera = cam

    world = bpy.data.worlds.new("cljn_preview_world")
    world.use_nodes = True
    bg = world.node_tree.nodes.get("Background")
    if bg is not None:
        bg.inputs["Color"].default_value = (0.93, 0.93, 0.93, 1.0)
        bg.inputs["Strength"].default_value = 1.0
    scene.world = world

    render = scene.render
    render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = 6
    scene.cycles.use_denoising = False
    scene.cycles.use_adaptive_sampling = False
    scene.cycles.max_bounces = 0
    render.resolution_x, render.resolution_y = PREVIEW_SIZE
    render.resolution_percentage = 100
    render.film_transparent = False
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    render.image_settings.file_format = "PNG"
    render.image_settings.color_mode = "RGB"
    render.use_file_extension = False
    target.parent.mkdir(parents=True, exist_ok=True)
    with atomic_paths(target) as (tmp,):
        render.filepath = str(tmp.resolve())
        with _quiet_stdout():
            bpy.ops.render.render(write_still=True)
        if tmp.stat().st_size == 0:
            raise RuntimeError("Cycles wrote an empty image")


def _splat_radius(points) -> float:
    """Sphere radius that closes the gaps between neighbours (points at unit diagonal)."""
    import numpy as np
    from scipy.spatial import cKDTree

    if len(points) < 2:
        return 0.01
    dist, _ = cKDTree(points).query(points, k=2)
    spacing = float(np.median(dist[:, 1]))
    return float(np.clip(0.9 * spacing, 0.0015, 0.02))


def _look_matrix(location, view, right, up):
    import mathutils

    m = mathutils.Matrix.Identity(4)
    for i in range(3):
        m[i][0], m[i][1], m[i][2], m[i][3] = right[i], up[i], view[i], location[i]
    return m


def _emission_material(bpy, name):
    mat = bpy.data.materials.new(name)
    with _no_deprecation_warnings():
        mat.use_nodes = True
    nt = mat.node_tree
    nt.nodes.clear()
    attr = nt.nodes.new("ShaderNodeAttribute")
    attr.attribute_name = "cljn_color"
    emit = nt.nodes.new("ShaderNodeEmission")
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    nt.links.new(attr.outputs["Color"], emit.inputs["Color"])
    nt.links.new(emit.outputs["Emission"], out.inputs["Surface"])
    return mat


@contextlib.contextmanager
def _no_deprecation_warnings():
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        yield


def _points_node_group(bpy, radius, mat):
    """Geometry nodes: mesh vertices -> points (spheres in Cycles) with the material."""
    ng = bpy.data.node_groups.new("cljn_preview_points", "GeometryNodeTree")
    ng.interface.new_socket(name="Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    ng.interface.new_socket(name="Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    gin = ng.nodes.new("NodeGroupInput")
    gout = ng.nodes.new("NodeGroupOutput")
    to_points = ng.nodes.new("GeometryNodeMeshToPoints")
    to_points.inputs["Radius"].default_value = radius
    set_mat = ng.nodes.new("GeometryNodeSetMaterial")
    set_mat.inputs["Material"].default_value = mat
    ng.links.new(gin.outputs[0], to_points.inputs["Mesh"])
    ng.links.new(to_points.outputs["Points"], set_mat.inputs["Geometry"])
    ng.links.new(set_mat.outputs["Geometry"], gout.inputs[0])
    return ng


def _add_cloud(bpy, scene, name, points, colours, group):
    import numpy as np

    mesh = bpy.data.meshes.new(f"cljn_preview_{name}")
    mesh.vertices.add(len(points))
    mesh.vertices.foreach_set("co", np.asarray(points, np.float32).ravel())
    rgba = np.ones((len(points), 4), np.float32)
    rgba[:, :3] = _srgb_to_linear(colours)
    attr = mesh.attributes.new("cljn_color", "FLOAT_COLOR", "POINT")
    attr.data.foreach_set("color", rgba.ravel())
    mesh.update()
    obj = bpy.data.objects.new(f"cljn_preview_{name}", mesh)
    scene.collection.objects.link(obj)
    obj.modifiers.new("points", "NODES").node_group = group
    return obj


def _add_label(bpy, scene, text, location, view, right, up, size):
    curve = bpy.data.curves.new(f"cljn_label_{text}", "FONT")
    curve.body = text
    curve.align_x = "CENTER"
    curve.size = size
    obj = bpy.data.objects.new(f"cljn_label_{text}", curve)
    scene.collection.objects.link(obj)
    obj.matrix_world = _look_matrix(location, view, right, up)
    mat = bpy.data.materials.new(f"cljn_label_{text}")
    with _no_deprecation_warnings():
        mat.use_nodes = True
    emit = mat.node_tree.nodes.new("ShaderNodeEmission")
    emit.inputs["Color"].default_value = (0.02, 0.02, 0.02, 1.0)
    out = mat.node_tree.nodes.get("Material Output")
    mat.node_tree.links.new(emit.outputs["Emission"], out.inputs["Surface"])
    curve.materials.append(mat)
    return obj


if __name__ == "__main__":                                          # pragma: no cover
    sys.exit(main())

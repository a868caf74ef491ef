"""`run.py denoise` and `run.py normals`: a batch of point files (.ply .xyz .npy .las .laz) and .blend
files, each written to its output (or in place with a backup), one summary line per input,
an optional JSON report and before/after previews.

Point files go straight through the engine; .blend files go through the extension's own
pipeline (blender/pipeline.py: snapshot world points -> engine -> write back), the one the
Denoise Points operator runs. numpy, torch and bpy are imported when a batch runs.
"""
from __future__ import annotations

import math
import os
import re
import shutil
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path

from ..core.errors import InputError, user_message
from ..core.options import DenoiseOptions
from .console import err, out
from .dependencies import engine_missing_message
from .exitcodes import EXIT_INTERNAL, EXIT_INTERRUPTED, EXIT_OK, EXIT_PARTIAL, EXIT_USAGE, UsageError
from .parser import ALL_SUFFIXES, BLEND_SUFFIX
from .progress import Progress
from .report import build_report, write_report


@dataclass
class FileJob:
    """One input of the batch and where its result goes."""

    input: Path
    output: Path
    report: dict = field(default_factory=dict)

    @property
    def is_blend(self) -> bool:
        return self.input.suffix.lower() == BLEND_SUFFIX


def options_from_args(args) -> DenoiseOptions:
    """The engine options of the command line (the panel builds the same object)."""
    return DenoiseOptions(
        iterations=args.iterations,
        patch_radius_fraction=None if args.patch_radius is None else args.patch_radius / 100.0,
        orientation=args.orient, viewpoint=args.viewpoint, device=args.device, seed=args.seed,
        normals_only=args.command == "normals", model_path=args.model,
        max_displacement=getattr(args, "max_displacement", None), backend=args.backend,
        noise_sigma=getattr(args, "noise", None), solid=getattr(args, "solid", False))


def _scales_text(scales) -> str:
    """0.001, or 0.001/0.001/0.0001 when the axes differ."""
    return "/".join(f"{v:g}" for v in scales) if len(set(scales)) > 1 else f"{scales[0]:g}"


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
    """The files written for `path` (.xyz: the normals go to a sibling .normals file)."""
    if path.suffix.lower() == ".xyz":
        return [path, path.with_suffix(".normals")]
    return [path]


def _check_args(a, inputs):
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


def _jobs(a, inputs) -> list:
    if a.output:
        if len(inputs) != 1:
            raise UsageError(f"-o takes a single input ({len(inputs)} given); "
                             "use --out-dir for several")
        return [FileJob(inputs[0], Path(a.output))]
    if a.out_dir:
        out_dir = Path(a.out_dir)
        return [FileJob(p, out_dir / (p.stem + ("." + a.format if a.format else p.suffix.lower())))
                for p in inputs]
    return [FileJob(p, p) for p in inputs]


def _check_outputs(a, inputs, jobs):
    from ..core.formats.las import LAS_SUFFIXES

    if not any(job.output.suffix.lower() in LAS_SUFFIXES for job in jobs):
        for flag, given in (("--keep-las-scale", a.keep_las_scale), ("--classify-outliers", a.classify_outliers)):
            if given:
                raise UsageError(f"{flag} applies to .las/.laz outputs; none of the outputs is one")
    seen = {}
    for job in jobs:
        out_suffix = job.output.suffix.lower()
        if out_suffix not in ALL_SUFFIXES:
            raise UsageError(f"{job.output}: unsupported output format "
                             f"{job.output.suffix or '(none)'!r} (use {', '.join(ALL_SUFFIXES)})")
        if job.is_blend and out_suffix != BLEND_SUFFIX:
            raise UsageError(f"{job.input}: a .blend input is saved as a .blend, not {out_suffix}")
        for target in _outputs_of(job.output):
            if not a.in_place:
                for p in inputs:
                    if _same_file(target, p):
                        raise UsageError(f"{target} is an input: refusing to overwrite it "
                                         "(use --in-place, or another output name)")
            key = os.path.normcase(os.path.abspath(target))
            if key in seen:
                raise UsageError(f"{seen[key]} and {job.input} would both be written to {target}")
            seen[key] = job.input


def plan(a) -> list:
    """The batch's jobs, or UsageError before anything is read or written."""
    inputs = [Path(p) for p in a.inputs]
    _check_args(a, inputs)
    jobs = _jobs(a, inputs)
    _check_outputs(a, inputs, jobs)
    return jobs


class _ModelError(Exception):
    pass


def _blender():
    """The extension's Blender modules (InputError without bpy)."""
    try:
        from ..blender import blendfile, object_io, pipeline
    except ImportError as exc:
        if (exc.name or "").split(".")[0] not in ("bpy", "mathutils"):
            raise
        raise InputError("this needs Blender's Python module: run under Blender "
                         "(blender -b -P standalone/run.py -- ...) or install the bpy wheel") from None
    return blendfile, object_io, pipeline


class CloudCommand:
    """`denoise` and `normals`: plan (all usage errors first), then each input in turn."""

    def __init__(self, args):
        self.args = args
        self.options = options_from_args(args)
        self.normals_only = self.options.normals_only
        self.model = None
        self.previews: list = []
        self.jobs = plan(args)

    # ------------------------------------------------------------------ running
    def run(self) -> int:
        a = self.args
        t_start = time.monotonic()
        for job in self.jobs:
            job.report = {"input": str(job.input), "output": None, "status": "pending"}
        message = engine_missing_message()
        if message:
            err(message)
            return EXIT_USAGE
        try:
            self._load_model()
        except _ModelError as exc:
            err(f"error: {exc}")
            for job in self.jobs:
                job.report.update(status="error", error=str(exc))
            self._report(EXIT_USAGE, t_start, model_error=str(exc))
            return EXIT_USAGE
        failures, internal = 0, 0
        for job in self.jobs:
            try:
                (self._run_blend if job.is_blend else self._run_points)(job)
                job.report["status"] = "ok"
            except KeyboardInterrupt:
                job.report.update(status="error", error="interrupted")
                self._report(EXIT_INTERRUPTED, t_start)
                raise
            except Exception as exc:                              # noqa: BLE001
                failures += 1
                message, is_internal = self._describe(job, exc)
                internal += is_internal
                err(f"error: {message}")
                if is_internal and a.debug:
                    traceback.print_exc()
                job.report.update(status="error", error=message, output=None)
        code = self._exit_code(failures, internal)
        if a.preview and self.previews:
            self._write_previews()
        if len(self.jobs) > 1:
            ok = len(self.jobs) - failures
            out(f"{ok} of {len(self.jobs)} inputs done" + (f", {failures} failed" if failures else ""))
        self._report(code, t_start)
        return code

    def _exit_code(self, failures, internal) -> int:
        if failures == 0:
            return EXIT_OK
        if failures < len(self.jobs):
            return EXIT_PARTIAL
        return EXIT_INTERNAL if internal == failures else EXIT_USAGE

    def _report(self, code, t_start, model_error=None):
        if self.args.report:
            write_report(self.args.report, build_report(self.args, self.jobs, code,
                                                        time.monotonic() - t_start, model_error))

    def _describe(self, job, exc):
        """(one-line message naming the file, is it an internal error?)."""
        name = str(job.input)
        text = user_message(exc)
        if text is not None:
            return (text if text.startswith(name) else f"{name}: {text}"), False
        if isinstance(exc, OSError):
            where = exc.filename or name
            return f"{where}: {exc.strerror or exc}", False
        if isinstance(exc, MemoryError):
            return f"{name}: out of memory (try a smaller cloud or fewer threads)", False
        return (f"{name}: internal error: {type(exc).__name__}: {exc}"
                + ("" if self.args.debug else " (rerun with --debug for details)")), True

    def _load_model(self):
        from ..core.errors import ModelMismatchError, ModelNotFoundError
        from ..core.options import resolve_backend

        try:
            backend = resolve_backend(self.options.backend)
        except InputError as exc:
            raise _ModelError(f"backend: {exc}") from None
        if self.args.threads and backend == "torch":
            import torch

            torch.set_num_threads(self.args.threads)
        try:
            self.model = self.options.load_model()
        except (ModelNotFoundError, ModelMismatchError) as exc:
            raise _ModelError(f"model: {exc}") from None
        except OSError as exc:
            raise _ModelError(f"model: {self.args.model}: {exc.strerror or exc}") from None

    def _engine(self, points, label, options=None):
        with Progress(label, enabled=not self.args.no_progress) as progress:
            return (options or self.options).run(points, self.model, progress=progress)

    def _stats(self, label, res, output=None) -> dict:
        import numpy as np

        n = int(len(res.points))
        outliers = int(np.count_nonzero(res.outliers))
        disp = float(np.mean(res.displacement)) if n else 0.0
        # res is a core.DenoiseResult (denoise and normals-only alike): its fields always exist.
        seconds = float(res.seconds)
        sigma = float(res.noise_sigma)
        bound = float(res.displacement_bound)
        given = self.options.noise_sigma is not None
        details = (f"{'given' if given else 'estimated'} noise {sigma:.4g}"
                   + (f" (no point moved more than {bound:.4g}), " if math.isfinite(bound) else ", ")
                   if math.isfinite(sigma) else "")
        details += "".join(step + ", " for step in res.steps_taken())
        passes = int(res.iterations)
        stopped = bool(res.stopped_early)
        details += f"{passes} pass{'es' if passes != 1 else ''}" + (" (stopped: moved as far as the noise), " if stopped else ", ")
        ran_on = res.ran_on
        where = f"on {ran_on}, " if ran_on else ""
        line = (f"{label}: {n} points, {outliers} outliers flagged, "
                f"mean displacement {disp:.4g}, {details}{where}{seconds:.1f} s")
        if output is not None:
            line += f" -> {output}"
        out(line)
        return {"points": n, "outliers": outliers, "mean_displacement": disp,
                "noise_sigma": sigma if math.isfinite(sigma) else None, "noise_given": given,
                "displacement_bound": bound if math.isfinite(bound) else None,
                "thin_walled": bool(res.thin_walled), "solid_share": round(float(res.solid_share), 4),
                "split_share": round(float(res.split_share), 4),
                "rod_share": round(float(res.rod_share), 4), "rim_share": round(float(res.rim_share), 4),
                "plane_share": round(float(res.plane_share), 4), "kept_share": round(float(res.kept_share), 4),
                "noise_range": None if res.noise_range is None else [float(q) for q in res.noise_range],
                "scene_radius": float(res.scene_radius) if math.isfinite(res.scene_radius) else None,
                "passes": passes, "stopped_by_noise": stopped,
                "seconds": round(seconds, 3), "ran_on": ran_on}

    def _keep_preview(self, job, label, before, res):
        if self.args.preview:
            from ..blender.preview import PreviewItem

            self.previews.append(PreviewItem.of(label, before, res, job))

    def _backup(self, path: Path):
        """Copy each file about to be replaced to its backup name (atomically)."""
        from ..core.formats.points import atomic_paths

        for target in _outputs_of(path):
            if target.exists():
                with atomic_paths(_backup_path(target)) as (tmp,):
                    shutil.copy2(target, tmp)

    # ------------------------------------------------------------------ point files
    def _run_points(self, job):
        import numpy as np

        from ..core.formats import points as pointio
        from ..core.formats.las import LAS_SUFFIXES

        if job.output.suffix.lower() == BLEND_SUFFIX:
            return self._run_points_to_blend(job)
        # LAS/LAZ -> LAS/LAZ streams the records again on writing: only positions in memory.
        cloud = pointio.read_points(job.input, with_fields=job.output.suffix.lower() not in LAS_SUFFIXES)
        res = self._engine(cloud.points, job.input.name)
        dtype = cloud.points.dtype if cloud.points.dtype.kind == "f" else np.float64
        out_points = cloud.points if self.normals_only else np.asarray(res.points).astype(dtype)
        comment = ("CLJN Denoise: normals estimated" if self.normals_only
                   else "CLJN Denoise: positions filtered, normals estimated")
        result = pointio.PointCloud(out_points, np.asarray(res.normals, np.float32),
                                    dict(cloud.extra), None,
                                    [c for c in cloud.comments if not c.startswith("CLJN Denoise")]
                                    + [comment], source=cloud.source, origin=cloud.origin)
        if self.args.in_place:
            self._backup(job.output)
        job.output.parent.mkdir(parents=True, exist_ok=True)
        written = pointio.write_points(job.output, result, outliers=res.outliers,
                                       keep_las_scale=self.args.keep_las_scale,
                                       classify_outliers=self.args.classify_outliers)
        job.report["output"] = str(job.output)
        if len(written) > 1:
            job.report["files"] = [str(p) for p in written]
        job.report.update(self._stats(str(job.input), res, job.output))
        if job.output.suffix.lower() in LAS_SUFFIXES:
            self._note_las_scale(job, cloud)
            if self.args.classify_outliers:
                job.report["outliers_classified"] = int(np.count_nonzero(res.outliers))
        self._keep_preview(job, job.input.stem, np.asarray(cloud.points, np.float64), res)

    def _note_las_scale(self, job, cloud):
        """Report the scale a LAS/LAZ was written at; say so when it is finer than the input's."""
        from ..core.formats.las import LasSource, file_scales

        written = file_scales(job.output)
        job.report["las_scale"] = list(written)
        if isinstance(cloud.source, LasSource):
            given = tuple(float(v) for v in cloud.source.header.scales)
            if written != given:
                out(f"{job.output}: written at scale {_scales_text(written)}, finer than the "
                    f"input's {_scales_text(given)}, too coarse for the moves "
                    "(--keep-las-scale keeps it)")

    def _run_points_to_blend(self, job):
        """A new .blend holding the cloud as the extension's point cloud (LAS/LAZ: as File >
        Import makes it, recentred and exportable), the result written by the pipeline."""
        from ..core.formats import points as pointio
        from ..core.formats.las import LAS_SUFFIXES

        blendfile, _object_io, pipeline = _blender()
        blendfile.empty_scene()
        if job.input.suffix.lower() in LAS_SUFFIXES:
            from ..blender import las_io

            obj = las_io.import_las(job.input, as_point_cloud=False)
        else:
            cloud = pointio.read_points(job.input)
            obj = blendfile.new_point_cloud_object(job.input.stem, cloud.points, cloud.extra)
        snap = pipeline.snapshot(obj)
        res = self._engine(snap.points, job.input.name)
        for warning in pipeline.write_back(snap, res, self.normals_only):
            err(f"warning: {job.input}: {warning}")
        if self.args.in_place:
            self._backup(job.output)
        job.output.parent.mkdir(parents=True, exist_ok=True)
        blendfile.save_blend(job.output)
        job.report["output"] = str(job.output)
        job.report.update(self._stats(str(job.input), res, job.output))
        self._keep_preview(job, job.input.stem, snap.points, res)

    # ------------------------------------------------------------------ .blend files
    def _run_blend(self, job):
        import numpy as np

        blendfile, _object_io, pipeline = _blender()
        blendfile.open_blend(job.input)
        objects = pipeline.file_objects(self.args.objects, self.args.use_mesh_vertices)
        options = self.options
        if options.orientation == "viewpoint" and options.viewpoint is None:   # "Toward Camera"
            viewpoint = pipeline.camera_viewpoint()
            if viewpoint is None:
                raise InputError(f"{job.input}: --orient viewpoint needs --viewpoint X Y Z "
                                 "(the scene has no camera to use instead)")
            options = options.replace(viewpoint=viewpoint)
        per_object, results = [], []
        for obj in objects:
            label = f"{job.input} [{obj.name}]"
            snap = pipeline.snapshot(obj)
            res = self._engine(snap.points, f"{job.input.name} [{obj.name}]", options)
            results.append((snap, res))
            per_object.append({"name": obj.name, **self._stats(label, res)})
            self._keep_preview(job, f"{job.input.stem}_{obj.name}", snap.points, res)
        for snap, res in results:                 # all computed: now change the scene
            for warning in pipeline.write_back(snap, res, self.normals_only):
                err(f"warning: {job.input}: {warning}")
        if self.args.in_place:
            self._backup(job.output)
        job.output.parent.mkdir(parents=True, exist_ok=True)
        blendfile.save_blend(job.output)
        job.report["output"] = str(job.output)
        job.report["objects"] = per_object
        job.report.update(
            points=sum(o["points"] for o in per_object),
            outliers=sum(o["outliers"] for o in per_object),
            mean_displacement=(float(np.average([o["mean_displacement"] for o in per_object],
                                                weights=[o["points"] for o in per_object]))),
            seconds=round(sum(o["seconds"] for o in per_object), 3))
        out(f"{job.input}: {len(per_object)} point-cloud object(s) -> {job.output}")

    # ------------------------------------------------------------------ previews
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
                from ..blender.preview import render_preview

                render_preview(item, target, color_by=a.preview_color,
                               title=("normals" if self.normals_only else "denoised"))
            except Exception as exc:                                # noqa: BLE001
                err(f"warning: {target}: preview not written ({type(exc).__name__}: {exc})")
                if a.debug:
                    traceback.print_exc()
                continue
            out(f"preview: {target}")
            if item.job is not None:
                item.job.report.setdefault("previews", []).append(str(target))

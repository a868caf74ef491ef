"""Operators: Denoise Points, Estimate Normals, Restore Original, Train Model, dependencies.

Long runs go through `_JobOperator`: the operator reads arrays on the main thread, the engine
runs in a worker thread while a modal timer updates the progress indicator and the status
text (Esc cancels, nothing is written), and the results are written on the main thread at the
end, so each run is one undo step. Under `bpy.app.background`, and when called with
EXEC_DEFAULT from scripts, the same work runs synchronously. torch is imported only inside
the work functions.
"""

import os
import threading
import time
import traceback

import bpy
import numpy as np
from bpy.props import EnumProperty, StringProperty

from . import deps, object_io, pipeline
from .preferences import get_preferences

NOTHING_SELECTED = ("Nothing selected: select one or more point clouds (meshes without faces "
                    "or Point Cloud objects)")

_active_job = None          # at most one engine job at a time


class BackgroundJob:
    """work(progress, cancel) on a worker thread (start) or inline (run); polled by the caller."""

    def __init__(self, work, title):
        self.work = work
        self.title = title
        self.cancel = threading.Event()
        self.fraction = 0.0
        self.message = ""
        self.result = None
        self.error = None
        self.started = time.perf_counter()
        self.seconds = 0.0
        self._thread = None

    def progress(self, fraction, message=""):
        self.fraction = float(min(max(fraction, 0.0), 1.0))
        self.message = str(message)

    def run(self):
        try:
            self.result = self.work(self.progress, self.cancel)
        except BaseException as exc:   # reported on the main thread
            self.error = exc
        finally:
            self.seconds = time.perf_counter() - self.started

    def start(self):
        self._thread = threading.Thread(target=self.run, name=f"cljn: {self.title}", daemon=True)
        self._thread.start()

    @property
    def done(self) -> bool:
        return self._thread is None or not self._thread.is_alive()

    def status_text(self) -> str:
        if self.cancel.is_set():
            return f"CLJN {self.title}: cancelling..."
        return f"CLJN {self.title}: {self.fraction * 100:.0f}% {self.message}  (Esc to cancel)"


def describe_error(exc: BaseException) -> str:
    """One plain sentence for the user; unexpected errors also go to the console in full."""
    if isinstance(exc, ImportError):
        name = (getattr(exc, "name", None) or "").split(".")[0]
        if name in deps.REQUIRED:
            deps.refresh()
            return deps.missing_message([name])
        if name in deps.TORCH:
            deps.refresh()
            return deps.TORCH_MESSAGE
        return f"Could not load the CLJN engine ({exc}); try Install Dependencies"
    if isinstance(exc, deps.DependencyError):
        return f"Installing dependencies failed: {exc}"
    from ..core import errors

    if isinstance(exc, errors.ModelNotFoundError):
        return f"{exc} In Blender: choose a model file in the CLJN panel, or press Train Model"
    if isinstance(exc, errors.ModelMismatchError):
        return f"Model file mismatch: {exc}"
    message = errors.user_message(exc)
    if message is not None:
        return message
    traceback.print_exception(type(exc), exc, exc.__traceback__)
    return f"Unexpected error ({type(exc).__name__}: {exc}); details in the system console"


def _run_synchronously(context) -> bool:
    """No event loop to drive a modal operator: run inline (background mode, no window)."""
    return bpy.app.background or context.window is None


def _mode_poll(cls, context) -> bool:
    if _active_job is not None:
        cls.poll_message_set("A CLJN job is running: wait for it or press Esc")
        return False
    if context.mode != "OBJECT":
        cls.poll_message_set("Switch to Object Mode first")
        return False
    return True


class _JobOperator:
    """Mixin: prepare() on the main thread -> work in a BackgroundJob -> apply() on the main thread."""

    job_title = "working"
    cancelled_text = "nothing was changed"

    def prepare(self, context):
        """Return work(progress, cancel), or None after reporting why not."""
        raise NotImplementedError

    def apply(self, context, result) -> set:
        raise NotImplementedError

    def _prepare_or_report(self, context):
        try:
            return self.prepare(context)
        except Exception as exc:   # e.g. a torch that is installed but broken
            self.report({"ERROR"}, describe_error(exc))
            return None

    def execute(self, context):
        global _active_job
        work = self._prepare_or_report(context)
        if work is None:
            return {"CANCELLED"}
        job = BackgroundJob(work, self.job_title)
        _active_job = job
        try:
            job.run()
        finally:
            _active_job = None
        return self._finish(context, job)

    def invoke(self, context, event):
        global _active_job
        if _run_synchronously(context):
            return self.execute(context)
        work = self._prepare_or_report(context)
        if work is None:
            return {"CANCELLED"}
        self._job = BackgroundJob(work, self.job_title)
        _active_job = self._job
        self._job.start()
        wm = context.window_manager
        self._timer = wm.event_timer_add(0.1, window=context.window)
        wm.progress_begin(0, 100)
        wm.modal_handler_add(self)
        self._status(context, self._job.status_text())
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        job = self._job
        if event.type == "ESC" and event.value == "PRESS":
            job.cancel.set()
            self._status(context, job.status_text())
            return {"RUNNING_MODAL"}
        if event.type == "TIMER":
            context.window_manager.progress_update(int(job.fraction * 100))
            self._status(context, job.status_text())
            if job.done:
                self._cleanup(context)
                return self._finish(context, job)
        return {"PASS_THROUGH"}

    def cancel(self, context):
        # Blender ends the modal operator (e.g. a file is loaded): stop and write nothing.
        job = getattr(self, "_job", None)
        if job is not None:
            job.cancel.set()
        self._cleanup(context)

    def _cleanup(self, context):
        global _active_job
        wm = context.window_manager
        if getattr(self, "_timer", None) is not None:
            wm.event_timer_remove(self._timer)
            self._timer = None
            wm.progress_end()
        self._status(context, None)
        _active_job = None

    @staticmethod
    def _status(context, text):
        workspace = getattr(context, "workspace", None)
        if workspace is not None:
            workspace.status_text_set(text)

    def _finish(self, context, job) -> set:
        if job.cancel.is_set():
            self.report({"WARNING"}, f"{job.title.capitalize()} cancelled: {self.cancelled_text}")
            return {"CANCELLED"}
        if job.error is not None:
            self.report({"ERROR"}, describe_error(job.error))
            return {"CANCELLED"}
        try:
            return self.apply(context, job.result)
        except Exception as exc:
            self.report({"ERROR"}, describe_error(exc))
            return {"CANCELLED"}


# ---------------------------------------------------------------------------------------------
# Denoise Points / Estimate Normals


def _report_missing_deps(op) -> bool:
    missing = deps.missing()
    if missing:
        op.report({"ERROR"}, deps.missing_message(missing))
        return True
    return False


class _PointsOperator(_JobOperator):
    normals_only = False

    @classmethod
    def poll(cls, context):
        return _mode_poll(cls, context)

    def prepare(self, context):
        settings = context.scene.cljn_denoise
        selected = list(context.selected_objects)
        if not selected:
            self.report({"ERROR"}, NOTHING_SELECTED)
            return None
        refused = [r for r in (object_io.check_point_cloud(o, settings.use_mesh_vertices) for o in selected) if r]
        objects = object_io.point_cloud_objects(selected, settings.use_mesh_vertices)
        if not objects:
            more = f" ({len(refused) - 1} more objects refused)" if len(refused) > 1 else ""
            self.report({"ERROR"}, refused[0] + more)
            return None
        if _report_missing_deps(self):
            return None
        try:
            options = pipeline.options_from_settings(context, settings, self.normals_only)
        except ValueError as exc:
            self.report({"ERROR"}, str(exc))
            return None
        for reason in refused:
            self.report({"WARNING"}, reason + " (skipped)")
        snapshots = [pipeline.snapshot(obj) for obj in objects]
        self._snapshots = snapshots

        def work(progress, cancel):
            progress(0.0, "loading the model")
            model = options.load_model()
            return pipeline.compute(snapshots, options, model, progress=progress, cancel=cancel)

        return work

    def apply(self, context, results):
        written, points, moved = 0, 0, []
        for snap, result in zip(self._snapshots, results):
            try:
                for warning in pipeline.write_back(snap, result, normals_only=self.normals_only):
                    self.report({"WARNING"}, warning)
            except ValueError as exc:
                self.report({"WARNING"}, str(exc))
                continue
            written += 1
            points += len(result.normals)
            if not self.normals_only:
                moved.append(np.asarray(result.displacement))
        if not written:
            self.report({"ERROR"}, "Nothing was written")
            return {"CANCELLED"}
        seconds = sum(getattr(r, "seconds", 0.0) for r in results)
        what = "Normals estimated for" if self.normals_only else "Denoised"
        text = f"{what} {written} point cloud{'s' if written > 1 else ''} ({points:,} points) in {seconds:.1f} s"
        if moved:
            text += f"; mean move {float(np.mean(np.concatenate(moved))):.4g}"
            passes = sorted({int(getattr(r, "iterations", 0)) for r in results})
            text += f"; {'/'.join(map(str, passes))} pass{'' if passes == [1] else 'es'}"
            if any(getattr(r, "stopped_early", False) for r in results):
                text += " (auto stopped once points had moved as far as the noise)"
        # The engine's own words for its extra steps (the command line prints the same), per object
        for snap, result in zip(self._snapshots, results):
            steps = result.steps_taken()
            if steps:
                text += f"; {snap.name + ': ' if len(results) > 1 else ''}{', '.join(steps)}"
        self.report({"INFO"}, text)
        return {"FINISHED"}


class CLJN_OT_denoise_points(_PointsOperator, bpy.types.Operator):
    """Filter the noise out of the selected point clouds and estimate their normals"""
    bl_idname = "cljn.denoise_points"
    bl_label = "Denoise Points"
    bl_options = {"REGISTER", "UNDO"}
    job_title = "denoising"
    normals_only = False


class CLJN_OT_estimate_normals(_PointsOperator, bpy.types.Operator):
    """Estimate normals of the selected point clouds; positions stay untouched"""
    bl_idname = "cljn.estimate_normals"
    bl_label = "Estimate Normals"
    bl_options = {"REGISTER", "UNDO"}
    job_title = "estimating normals"
    normals_only = True


class CLJN_OT_restore_original(bpy.types.Operator):
    """Put back the positions saved before the first Denoise Points (cljn_original_position)"""
    bl_idname = "cljn.restore_original"
    bl_label = "Restore Original"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        return _mode_poll(cls, context)

    def execute(self, context):
        selected = list(context.selected_objects)
        if not selected:
            self.report({"ERROR"}, NOTHING_SELECTED)
            return {"CANCELLED"}
        restored, seen = [], set()
        for obj in selected:
            if obj.type not in ("MESH", "POINTCLOUD") or obj.data.as_pointer() in seen:
                continue
            seen.add(obj.data.as_pointer())
            if object_io.restore_original(obj):
                restored.append(obj.name)
        if not restored:
            self.report({"ERROR"}, "None of the selected objects has a saved original "
                        f"({object_io.ORIGINAL_POSITION}): nothing to restore")
            return {"CANCELLED"}
        self.report({"INFO"}, f"Restored the original positions of {', '.join(restored)}")
        return {"FINISHED"}


# ---------------------------------------------------------------------------------------------
# Train Model


class CLJN_OT_train_model(_JobOperator, bpy.types.Operator):
    """Train a model on the selected clean meshes (with faces) and make it the active model"""
    bl_idname = "cljn.train_model"
    bl_label = "Train Model"
    bl_options = {"REGISTER", "UNDO"}
    job_title = "training"

    preset: EnumProperty(
        name="Network Size",
        items=(("small", "Small", "The network the extension ships (slower to train)"),
               ("tiny", "Tiny", "A very small network that trains in seconds (for trying things out)")),
        default="small")

    @classmethod
    def poll(cls, context):
        return _mode_poll(cls, context)

    def prepare(self, context):
        selected = list(context.selected_objects)
        if not selected:
            self.report({"ERROR"}, "Nothing selected: select one or more clean meshes with faces to train on")
            return None
        meshes = [o for o in selected if o.type == "MESH" and len(o.data.polygons)]
        if not meshes:
            self.report({"ERROR"}, "Train Model needs clean meshes with faces: none of the selected "
                        "objects is one")
            return None
        if _report_missing_deps(self):
            return None
        if deps.torch_missing():
            self.report({"ERROR"}, deps.TORCH_MESSAGE)
            return None
        sources = [object_io.mesh_world_triangles(o) for o in meshes]
        stamp = time.strftime("%Y%m%d-%H%M%S")
        out_dir = os.path.join(deps.user_dir("models"), f"{bpy.path.clean_name(meshes[0].name)}-{stamp}")
        preset = self.preset

        def work(progress, cancel):
            from ..core.training import train

            progress(0.0, "sampling the meshes")
            return train.train_model(sources, out_dir, preset=preset, quick=True,
                                     progress=progress, cancel=cancel)

        return work

    def apply(self, context, weights):
        settings = context.scene.cljn_denoise
        settings.model_source = "FILE"
        settings.model_path = str(weights)
        self.report({"INFO"}, f"Trained model saved to {weights}; it is now the active model")
        return {"FINISHED"}


# ---------------------------------------------------------------------------------------------
# Dependencies


class CLJN_OT_install_dependencies(_JobOperator, bpy.types.Operator):
    """Install scipy, safetensors, laspy and lazrs (or the packages given, e.g. torch) into this
    extension's user directory with Blender's pip"""
    bl_idname = "cljn.install_dependencies"
    bl_label = "Install Dependencies"
    bl_options = {"REGISTER"}
    job_title = "installing dependencies"
    cancelled_text = "pip was stopped; press Install Dependencies again to finish"

    packages: StringProperty(
        name="Packages", options={"HIDDEN", "SKIP_SAVE"},
        description="Space-separated pip requirements (default: everything the engine needs)")

    @classmethod
    def poll(cls, context):
        if _active_job is not None:
            cls.poll_message_set("A CLJN job is running: wait for it or press Esc")
            return False
        return True

    def prepare(self, context):
        prefs = get_preferences(context)
        extra = prefs.pip_extra_args if prefs is not None else ""
        cpu_only = prefs.torch_cpu_only if prefs is not None else True
        if deps.needs_network(extra) and not bpy.app.online_access:
            self.report({"ERROR"}, "Online access is off: turn on Edit > Preferences > System > Network > "
                        "Allow Online Access, then press Install Dependencies again")
            return None
        packages = self.packages.split() or [*deps.REQUIRED.values(), *deps.LIDAR.values()]
        self._packages = packages

        def work(progress, cancel):
            return deps.install(packages, torch_cpu_only=cpu_only, extra_args=extra,
                                progress=progress, cancel=cancel)

        return work

    def apply(self, context, target):
        still = deps.missing() if not self.packages else []
        if still:
            self.report({"WARNING"}, f"pip finished, but {', '.join(still)} still cannot be found in {target}")
        else:
            self.report({"INFO"}, f"Installed {', '.join(self._packages)} into {target}")
        for area in getattr(context.screen, "areas", ()):
            area.tag_redraw()
        return {"FINISHED"}


class CLJN_OT_check_dependencies(bpy.types.Operator):
    """Import scipy, safetensors, laspy, lazrs and torch now to check that they work"""
    bl_idname = "cljn.check_dependencies"
    bl_label = "Check Dependencies"
    bl_options = {"REGISTER"}

    def execute(self, context):
        deps.activate()
        missing = deps.check_imports()
        if missing:
            self.report({"WARNING"}, deps.missing_message(missing))
        else:
            extra = "; torch is not installed (optional)" if deps.torch_missing() else ", torch too"
            self.report({"INFO"}, f"scipy, safetensors, laspy and lazrs import fine{extra}")
        return {"FINISHED"}


classes = (
    CLJN_OT_denoise_points,
    CLJN_OT_estimate_normals,
    CLJN_OT_restore_original,
    CLJN_OT_train_model,
    CLJN_OT_install_dependencies,
    CLJN_OT_check_dependencies,
)


def register():
    for cls in classes:
        bpy.utils.register_class(cls)


def unregister():
    global _active_job
    if _active_job is not None:
        _active_job.cancel.set()
        _active_job = None
    from ..core.options import clear_model_cache

    clear_model_cache()
    for cls in reversed(classes):
        bpy.utils.unregister_class(cls)

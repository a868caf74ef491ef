"""One pipeline for Blender objects, used by the Denoise Points / Estimate Normals operators
and by the command line's .blend files:

    snapshot(obj)            world points and the matrix they were read with (main thread)
    compute(snapshots, ...)  the engine on each (any thread: touches no Blender data)
    write_back(snap, result) through the same matrix onto the same object (main thread)

`options_from_settings` builds the engine's `DenoiseOptions` from the panel's properties
(the command line builds the same object from its arguments).
"""
from __future__ import annotations

import os
from dataclasses import dataclass

import bpy
import numpy as np

from ..core.errors import InputError
from ..core.options import DenoiseOptions
from . import object_io
from .preferences import get_preferences
from .properties import BACKEND_TO_CORE, DEVICE_TO_CORE


@dataclass
class Snapshot:
    """An object's points as the engine sees them, and how to find the object again."""

    name: str
    data_pointer: int
    matrix: np.ndarray       # matrix_world when read: results go back through it
    points: np.ndarray       # (N, 3) float64, world space


def snapshot(obj) -> Snapshot:
    matrix = np.array(obj.matrix_world, dtype=np.float64)
    return Snapshot(obj.name, obj.data.as_pointer(), matrix, object_io.read_world_points(obj, matrix))


def compute(snapshots, options: DenoiseOptions, model, *, progress=None, cancel=None) -> list:
    """The engine on each snapshot in turn; progress(fraction, "name: message") over all."""
    results = []
    for i, snap in enumerate(snapshots):
        on_progress = None
        if progress is not None:
            def on_progress(fraction, message="", i=i, name=snap.name):
                progress((i + min(max(fraction, 0.0), 1.0)) / len(snapshots), f"{name}: {message}")
        results.append(options.run(snap.points, model, progress=on_progress, cancel=cancel))
    return results


def write_back(snap: Snapshot, result, normals_only=False) -> list:
    """Write result onto the snapshot's object through the snapshot's matrix; returns warnings.
    InputError when the object was removed, replaced or edited since the snapshot."""
    obj = bpy.data.objects.get(snap.name)
    if obj is None or obj.data is None or obj.data.as_pointer() != snap.data_pointer:
        raise InputError(f"'{snap.name}' was removed or replaced while running: skipped")
    return object_io.write_result(obj, result, normals_only=normals_only, matrix_world=snap.matrix)


# ------------------------------------------------------------------------- panel -> options

def file_objects(names=None, use_mesh_vertices=False) -> list:
    """The point clouds of the open file to process: the named ones (each must be one), or
    every point-cloud object. InputError saying what is wrong otherwise."""
    found = object_io.point_cloud_objects(bpy.data.objects, use_mesh_vertices)
    if not names:
        if not found:
            raise InputError("no point-cloud objects in this .blend"
                             + ("" if use_mesh_vertices else
                                " (--use-mesh-vertices takes any mesh's vertices)"))
        return found
    chosen = []
    for name in names:
        obj = bpy.data.objects.get(name)
        if obj is None:
            raise InputError(f"no object named {name!r} (point clouds here: "
                             f"{', '.join(o.name for o in found) or 'none'})")
        reason = object_io.check_point_cloud(obj, use_mesh_vertices)
        if reason is not None:
            raise InputError(reason)
        chosen.append(obj)
    return chosen


def camera_viewpoint(scene=None) -> tuple | None:
    """The active camera's position (world space) of scene (default: the current one), or
    None without one."""
    scene = scene if scene is not None else bpy.context.scene
    if scene is None or scene.camera is None:
        return None
    return tuple(scene.camera.matrix_world.translation)


def _orientation(scene, choice) -> dict:
    """The panel's Orientation (properties.ORIENTATIONS) as engine options."""
    if choice == "OUTWARD":
        return {"orientation": "outward"}
    if choice == "NONE":
        return {"orientation": "none"}
    if choice == "CAMERA":
        viewpoint = camera_viewpoint(scene)
        if viewpoint is None:
            raise InputError("Orientation 'Toward Camera' needs an active scene camera: add one "
                             "or pick another orientation")
        return {"orientation": "viewpoint", "viewpoint": viewpoint}
    if choice == "CURSOR":
        return {"orientation": "viewpoint", "viewpoint": tuple(scene.cursor.location)}
    raise InputError(f"unknown orientation {choice!r}")


def _model_path(context, settings):
    """None for the shipped model, else an absolute path that exists."""
    if settings.model_source == "FILE":
        if not settings.model_path.strip():
            raise InputError("Model is set to File but no file is chosen: pick a .safetensors file "
                             "in the CLJN panel, or set Model to Default")
        path = bpy.path.abspath(settings.model_path)
    else:
        prefs = get_preferences(context)
        if prefs is None or not prefs.default_model_path.strip():
            return None
        path = bpy.path.abspath(prefs.default_model_path)
    if not os.path.isfile(path):
        raise InputError(f"Model file not found: {path}")
    return path


def _panel_or_preferences(context, settings, name, to_core) -> str:
    """The panel's choice of `name` (device, backend), or the preferences' when it is Default."""
    key = getattr(settings, name)
    if key == "PREFERENCES":
        prefs = get_preferences(context)
        key = getattr(prefs, name) if prefs is not None else "AUTO"
    return to_core[key]


def _typed_distance(value: float) -> float:
    """The decimal the user typed: a FloatProperty is single precision (0.004 reads back as
    0.0040000002), and the panel should run exactly as `--noise 0.004` does."""
    return float(f"{value:.7g}")


def options_from_settings(context, settings, normals_only=False) -> DenoiseOptions:
    """The panel's settings (scene.cljn_denoise) as engine options; InputError with a plain
    message when they cannot be used (no camera, missing model file...)."""
    return DenoiseOptions(iterations="auto" if settings.auto_iterations else settings.iterations,
                          patch_radius_fraction=settings.patch_radius / 100.0,
                          noise_sigma=_typed_distance(settings.noise_sigma) if settings.use_known_noise else None,
                          device=_panel_or_preferences(context, settings, "device", DEVICE_TO_CORE),
                          backend=_panel_or_preferences(context, settings, "backend", BACKEND_TO_CORE),
                          normals_only=normals_only, solid=settings.treat_as_solid,
                          model_path=_model_path(context, settings),
                          **_orientation(context.scene, settings.orientation))

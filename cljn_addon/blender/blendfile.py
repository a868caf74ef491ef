""".blend files for the command line: open, save (atomically), and "arrays -> a new point-cloud
object" (a mesh of vertices only, the inverse of reading world points in object_io).

Blender prints its own chatter ("Read blend: ...", "Saved: ...") on the C-level stdout;
`quiet_stdout` keeps stdout for the command line's summary lines.
"""
from __future__ import annotations

import contextlib
import os
import re
import sys
from pathlib import Path

import bpy
import numpy as np

from ..core.errors import InputError
from ..core.formats.points import atomic_paths


def _first_line(exc) -> str:
    text = str(exc).strip()
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    return lines[0] if lines else type(exc).__name__


@contextlib.contextmanager
def quiet_stdout():
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


def open_blend(path: Path) -> None:
    """Open `path` as the current file (InputError naming it when it cannot be read)."""
    if not path.exists():
        raise InputError(f"{path}: file not found")
    try:
        with quiet_stdout():
            bpy.ops.wm.open_mainfile(filepath=str(path.resolve()), load_ui=False)
    except RuntimeError as exc:
        raise InputError(f"{path}: not a readable .blend file ({_first_line(exc)})") from None


def empty_scene() -> None:
    """Blender's factory settings with an empty scene."""
    with quiet_stdout():
        bpy.ops.wm.read_factory_settings(use_empty=True)


def save_blend(target: Path) -> None:
    """Save a copy of the open file to `target` atomically (temporary .blend, then replace)."""
    with atomic_paths(target) as (tmp,):
        tmp.unlink()                      # Blender writes it; an existing file would be backed up
        try:
            with quiet_stdout():
                result = bpy.ops.wm.save_as_mainfile(filepath=str(tmp.resolve()), copy=True,
                                                     check_existing=False)
        except RuntimeError as exc:
            raise InputError(f"{target}: cannot save ({_first_line(exc)})") from None
        if "FINISHED" not in result or not tmp.exists():
            raise InputError(f"{target}: Blender did not save the file")
        stray = tmp.with_name(tmp.name + "1")
        if stray.exists():
            stray.unlink()


def _attribute_kind(values: np.ndarray):
    """(Blender attribute type, values converted) for a per-point property."""
    if values.dtype == np.bool_:
        return "BOOLEAN", values
    if values.dtype.kind in "iu" and values.dtype.itemsize <= 2 or values.dtype == np.int32:
        return "INT", values.astype(np.int32)
    return "FLOAT", values.astype(np.float32)


def new_point_cloud_object(name, points, extra=None, scene=None):
    """A new object in `scene` (default: the current one): a mesh of vertices only at
    `points` (object space = world space), with `extra` {name: (N,) array} as POINT
    attributes (names made Blender-safe; ours, cljn_*, and position are never overwritten)."""
    mesh = bpy.data.meshes.new(name)
    mesh.vertices.add(len(points))
    mesh.vertices.foreach_set("co", np.asarray(points, np.float32).ravel())
    for key, values in (extra or {}).items():
        attr_name = re.sub(r"[^A-Za-z0-9_]", "_", key)
        if attr_name in mesh.attributes or attr_name == "position" or attr_name.startswith("cljn_"):
            continue
        kind, data = _attribute_kind(np.asarray(values))
        mesh.attributes.new(attr_name, kind, "POINT").data.foreach_set("value", data)
    mesh.update()
    obj = bpy.data.objects.new(name, mesh)
    (scene or bpy.context.scene).collection.objects.link(obj)
    return obj

"""The engine options of one denoising run, in one object.

Both front ends build a `DenoiseOptions`: the Blender panel from its properties
(blender/pipeline.py) and the command line from its arguments (cli/clouds.py). `run()` hands
them to `core.denoise` or `core.estimate_normals`. Imports neither torch nor bpy.
"""
from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass

from .config import ORIENTATIONS
from .errors import InputError

_model_cache: dict = {}     # (path, mtime) -> loaded network; one model at a time


def clear_model_cache():
    _model_cache.clear()


@dataclass(frozen=True)
class DenoiseOptions:
    """iterations: filtering passes (ignored when normals_only). patch_radius_fraction: of the
    bbox diagonal, None for the model's own (5%). orientation: one of config.ORIENTATIONS;
    'viewpoint' needs viewpoint=(x, y, z) in world space. model_path: None for the shipped model.
    normals_only: estimate normals, positions untouched (core.estimate_normals).
    max_displacement: cap on how far any point moves (cloud units); None for 3 x the noise
    sigma estimated from the cloud."""

    iterations: int | str = 4          # or "auto"
    patch_radius_fraction: float | None = None
    orientation: str = "outward"
    viewpoint: tuple | None = None
    device: str = "auto"
    seed: int = 0
    normals_only: bool = False
    model_path: str | None = None
    max_displacement: float | None = None

    def __post_init__(self):
        if self.orientation not in ORIENTATIONS:
            raise InputError(f"unknown orientation {self.orientation!r}; "
                             f"choose one of {', '.join(ORIENTATIONS)}")
        if self.viewpoint is not None:
            object.__setattr__(self, "viewpoint", tuple(float(v) for v in self.viewpoint))

    def replace(self, **changes) -> "DenoiseOptions":
        return dataclasses.replace(self, **changes)

    def engine_kwargs(self) -> dict:
        """Keyword arguments of core.denoise / core.estimate_normals."""
        kwargs = dict(orientation=self.orientation, viewpoint=self.viewpoint, device=self.device,
                      seed=self.seed)
        if not self.normals_only:
            kwargs["iterations"] = self.iterations
            if self.max_displacement is not None:
                kwargs["max_displacement"] = self.max_displacement
        if self.patch_radius_fraction is not None:
            kwargs["patch_radius_fraction"] = self.patch_radius_fraction
        return kwargs

    def load_model(self):
        """The network for these options (the shipped one when model_path is None), loaded once
        per file and modification time."""
        from .model import load_model

        path = self.model_path
        key = (path, os.path.getmtime(path) if path and os.path.exists(path) else None)
        model = _model_cache.get(key)
        if model is None:
            model = load_model(path)
            _model_cache.clear()
            _model_cache[key] = model
        return model

    def run(self, points, model, *, progress=None, cancel=None):
        """The engine on (N, 3) world-space points; returns a core.DenoiseResult."""
        from . import infer

        fn = infer.estimate_normals if self.normals_only else infer.denoise
        return fn(points, model, progress=progress, cancel=cancel, **self.engine_kwargs())

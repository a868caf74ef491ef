"""The engine options of one denoising run, in one object.

Both front ends build a `DenoiseOptions`: the Blender panel from its properties
(blender/pipeline.py) and the command line from its arguments (cli/clouds.py). `run()` hands
them to `core.denoise` or `core.estimate_normals`. Imports neither torch nor bpy.
"""
from __future__ import annotations

import dataclasses
import importlib.util
import os
from dataclasses import dataclass

from .config import BACKENDS, ORIENTATIONS
from .errors import InputError, positive_number

_model_cache: dict = {}     # (path, mtime) -> loaded network; one model at a time


def clear_model_cache():
    _model_cache.clear()


def torch_available() -> bool:
    try:
        return importlib.util.find_spec("torch") is not None
    except (ImportError, ValueError):
        return False


def resolve_backend(name: str = "auto") -> str:
    """'torch' or 'numpy' for a backend choice; auto takes torch when it is installed (its
    GPU paths and bf16 on CPU), numpy otherwise."""
    name = (name or "auto").lower()
    if name not in BACKENDS:
        raise InputError(f"unknown backend {name!r}; choose one of {', '.join(BACKENDS)}")
    if name == "torch" and not torch_available():
        raise InputError("the torch backend needs torch, which is not installed: choose the numpy "
                         "backend (or auto), or install torch")
    if name == "auto":
        return "torch" if torch_available() else "numpy"
    return name


@dataclass(frozen=True)
class DenoiseOptions:
    """iterations: filtering passes, or "auto" (default: 1-4 from the estimated noise, see
    core.infer.iterations_for_noise); ignored when normals_only. patch_radius_fraction: of the
    bbox diagonal, None for the model's own (5%). orientation: one of config.ORIENTATIONS;
    'viewpoint' needs viewpoint=(x, y, z) in world space. model_path: None for the shipped model.
    normals_only: estimate normals, positions untouched (core.estimate_normals).
    backend: 'auto', 'torch' or 'numpy' (see resolve_backend).
    max_displacement: cap on how far any point moves (cloud units); None for 3 x the noise
    sigma estimated from the cloud. noise_sigma: the scanner's noise (standard deviation, cloud
    units) when the user knows it, in place of the estimate; None to estimate it.
    solid: never handle the object as thin-walled (own-sheet patches, one pass with auto
    iterations, no risk check), though its noise balls read two sheets: a sculpt whose relief,
    ribs or limbs read as a thin part's two sides. Denoise only."""

    iterations: int | str = "auto"     # or a whole number
    patch_radius_fraction: float | None = None
    orientation: str = "outward"
    viewpoint: tuple | None = None
    device: str = "auto"
    seed: int = 0
    normals_only: bool = False
    model_path: str | None = None
    max_displacement: float | None = None
    backend: str = "auto"
    noise_sigma: float | None = None
    solid: bool = False

    def __post_init__(self):
        if self.orientation not in ORIENTATIONS:
            raise InputError(f"unknown orientation {self.orientation!r}; "
                             f"choose one of {', '.join(ORIENTATIONS)}")
        if self.viewpoint is not None:
            object.__setattr__(self, "viewpoint", tuple(float(v) for v in self.viewpoint))
        if self.noise_sigma is not None:
            object.__setattr__(self, "noise_sigma", positive_number(
                self.noise_sigma, "scanner noise must be a positive distance, got {!r}"))
        if (self.backend or "auto").lower() not in BACKENDS:
            raise InputError(f"unknown backend {self.backend!r}; choose one of {', '.join(BACKENDS)}")

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
            if self.solid:
                kwargs["own_sheet"] = False
        if self.noise_sigma is not None:
            kwargs["noise_sigma"] = self.noise_sigma
        if self.patch_radius_fraction is not None:
            kwargs["patch_radius_fraction"] = self.patch_radius_fraction
        return kwargs

    def load_model(self):
        """The network for these options (the shipped one when model_path is None) on their
        backend, loaded once per file, modification time and backend."""
        backend = resolve_backend(self.backend)
        if backend == "numpy":
            from .numpy_net import load_numpy_net as load_model
        else:
            from .model import load_model

        path = self.model_path
        key = (path, os.path.getmtime(path) if path and os.path.exists(path) else None, backend)
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

"""The CLJN engine: numpy, scipy and torch only (never bpy).

The method lives at this level (config, patches, model, infer, refine, orient, device,
errors); three sub-packages hold the other roles: `formats` (point and mesh files),
`training` (data, losses, the two-stage loop) and `evaluation` (metrics, baselines, the eval,
demo and bench logic, synthetic shapes).

Public API: load_model, build_model, save_model, denoise, estimate_normals, DenoiseResult,
and the user-facing errors. Imports are lazy: `core.errors`, `core.config` and
`core.formats` load without torch; the engine names import torch on first use.
"""
from __future__ import annotations

import importlib

from .errors import Cancelled, InputError, ModelMismatchError, ModelNotFoundError

_LAZY = {
    "CLJNNet": "model", "build_model": "model", "load_model": "model", "save_model": "model",
    "DenoiseResult": "infer", "denoise": "infer", "estimate_normals": "infer",
}

__all__ = ["Cancelled", "InputError", "ModelMismatchError", "ModelNotFoundError", *_LAZY]


def __getattr__(name):
    if name in _LAZY:
        value = getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_LAZY))

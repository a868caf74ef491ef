"""The CLJN engine: numpy, scipy and torch only (never bpy).

Public API: load_model, build_model, save_model, denoise, estimate_normals, DenoiseResult,
and the user-facing errors. Submodules: config, patches, model, losses, data, train,
infer, refine, orient, metrics, baselines, shapes, meshio, pointio, evaluate.
"""
from .errors import Cancelled, InputError, ModelMismatchError, ModelNotFoundError
from .model import CLJNNet, build_model, load_model, save_model

try:
    from .infer import DenoiseResult, denoise, estimate_normals
except ImportError:  # pragma: no cover - only while the engine is being assembled
    pass

__all__ = ["Cancelled", "InputError", "ModelMismatchError", "ModelNotFoundError", "CLJNNet",
           "build_model", "load_model", "save_model", "DenoiseResult", "denoise", "estimate_normals"]

"""The CLJN engine: numpy, scipy and torch only (never bpy).

Public API: load_model, build_model, save_model, denoise, estimate_normals, DenoiseResult,
and the user-facing errors. Submodules: config, patches, model, losses, data, train,
infer, refine, orient, metrics, baselines, shapes, meshio, pointio, evaluate.
"""
from .errors import Cancelled, InputError, ModelMismatchError, ModelNotFoundError
from .infer import DenoiseResult, denoise, estimate_normals
from .model import CLJNNet, build_model, load_model, save_model

__all__ = ["Cancelled", "InputError", "ModelMismatchError", "ModelNotFoundError", "CLJNNet",
           "build_model", "load_model", "save_model", "DenoiseResult", "denoise", "estimate_normals"]

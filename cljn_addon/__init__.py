"""CLJN Denoise: point-cloud denoising and normal estimation with a learned network.

Two ways in:
- `cljn_addon.core`: the engine (numpy + torch, never imports bpy); used headless by standalone/.
- This package as a Blender extension (id `cljn_denoise`): Blender calls `register()` and
  `unregister()` below. Importing this file imports neither bpy nor torch, so the engine stays
  usable without Blender and the extension registers even before torch is installed.

Inside the package every import is relative: installed as an extension it is importable only
as `bl_ext.<repository>.cljn_denoise`.
"""


def register():
    from .blender import register as _register

    _register()


def unregister():
    from .blender import unregister as _unregister

    _unregister()

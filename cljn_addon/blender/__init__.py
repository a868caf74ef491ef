"""Blender glue of CLJN Denoise: properties, operators, panel, preferences, object <-> arrays.

Thin by design: object_io reads arrays with foreach_get, the engine (..core) does the work,
object_io writes the results with foreach_set. Nothing here imports torch at registration.
"""
from . import deps, operators, panel, preferences, properties

_modules = (preferences, properties, operators, panel)


def register():
    deps.activate()
    for module in _modules:
        module.register()


def unregister():
    for module in reversed(_modules):
        module.unregister()
    deps.deactivate()

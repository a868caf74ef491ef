"""Blender glue of CLJN Denoise: everything that imports bpy.

Thin by design: object_io reads arrays with foreach_get and writes results with foreach_set,
pipeline runs "snapshot world points -> engine -> write back" for the operators and for the
command line's .blend files, blendfile opens/saves .blend files and builds point-cloud
objects from arrays, preview renders the CLI's before/after picture; properties, operators,
panel and preferences are the UI; las_io and las_operators
import and export LAS/LAZ; deps finds and installs torch & co. Nothing here imports
torch at registration, and importing this package imports no bpy (register() does).
"""


def _ui_modules():
    from . import las_operators, operators, panel, preferences, properties

    return (preferences, properties, operators, las_operators, panel)


def register():
    from . import deps

    deps.activate()
    for module in _ui_modules():
        module.register()


def unregister():
    from . import deps

    for module in reversed(_ui_modules()):
        module.unregister()
    deps.deactivate()

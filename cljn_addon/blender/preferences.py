"""Add-on preferences: default model file, device and backend, and the Python dependencies."""

import bpy
from bpy.props import BoolProperty, EnumProperty, StringProperty

from . import deps
from .properties import BACKENDS, DEVICES

ADDON_PACKAGE = deps.ADDON_PACKAGE


def get_preferences(context=None):
    """This add-on's preferences, or None when it is not registered as an add-on."""
    context = context or bpy.context
    addon = context.preferences.addons.get(ADDON_PACKAGE)
    return addon.preferences if addon is not None else None


def draw_dependencies(layout, context, compact=False):
    """Dependency status and the Install button; shared by the preferences and the panel."""
    found = deps.status()
    missing = deps.missing()
    col = layout.column(align=True)
    if not compact:
        for name in (*deps.REQUIRED, *deps.LIDAR):
            ok = found.get(name) and deps.import_error(name) is None
            col.label(text=f"{name}: {'found' if ok else 'missing'}", icon="CHECKMARK" if ok else "ERROR")
        ok = not deps.torch_missing()
        col.label(text=f"torch (optional: GPU, training): {'found' if ok else 'not installed'}",
                  icon="CHECKMARK" if ok else "INFO")
    if missing:
        box = layout.box()
        box.alert = True
        box.label(text=f"Missing in Blender's Python: {', '.join(missing)}", icon="ERROR")
        box.label(text="Press Install Dependencies (scipy, safetensors, laspy, lazrs: ~50 MB)")
        box.operator("cljn.install_dependencies", icon="IMPORT")
    elif not compact:
        row = layout.row()
        row.operator("cljn.install_dependencies", text="Reinstall Dependencies", icon="IMPORT")
    if not compact:
        row = layout.row()
        op = row.operator("cljn.install_dependencies", text="Install torch", icon="IMPORT")
        if op is not None:
            op.packages = "torch"
        layout.label(text="torch adds GPUs (CUDA/MPS), faster bf16 on recent CPUs and Train Model "
                          "(several hundred MB); denoising runs without it")
        layout.operator("cljn.check_dependencies", icon="FILE_REFRESH")


class CLJN_AddonPreferences(bpy.types.AddonPreferences):
    bl_idname = ADDON_PACKAGE

    default_model_path: StringProperty(
        name="Default Model File", subtype="FILE_PATH",
        description="Used when the panel's Model is Default; empty means the model shipped with the extension")
    device: EnumProperty(name="Device", items=DEVICES, default="AUTO",
                         description="Where the network runs when the panel's Device is Default")
    backend: EnumProperty(name="Backend", items=BACKENDS, default="AUTO",
                          description="What runs the network when the panel's Backend is Default")
    torch_cpu_only: BoolProperty(
        name="CPU-only torch", default=True,
        description="Install the CPU build of torch (much smaller download); untick for CUDA builds")
    pip_extra_args: StringProperty(
        name="Extra pip Arguments",
        description="Added to the pip command line, e.g. --proxy URL or --no-index --find-links DIR")

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        layout.prop(self, "default_model_path")
        layout.prop(self, "device")
        layout.prop(self, "backend")
        box = layout.box()
        box.label(text="Dependencies (scipy, safetensors, laspy, lazrs; torch optional)")
        draw_dependencies(box, context)
        sub = box.column()
        sub.prop(self, "torch_cpu_only")
        sub.prop(self, "pip_extra_args")
        sub.label(text=f"Installed into: {deps.site_packages_dir(create=False)}")


classes = (CLJN_AddonPreferences,)


def register():
    for cls in classes:
        bpy.utils.register_class(cls)


def unregister():
    for cls in reversed(classes):
        bpy.utils.unregister_class(cls)

"""The 3D Viewport sidebar panel (N panel, tab "CLJN") and the Object menu entries."""

import os

import bpy

from ..core.config import DEFAULT_WEIGHTS
from . import deps, object_io
from .preferences import draw_dependencies, get_preferences


def shipped_model_present() -> bool:
    return DEFAULT_WEIGHTS.is_file()


def _default_model_text(context) -> tuple[str, str]:
    prefs = get_preferences(context)
    if prefs is not None and prefs.default_model_path.strip():
        return f"Preferences: {os.path.basename(bpy.path.abspath(prefs.default_model_path))}", "FILE"
    if shipped_model_present():
        return "The shipped model", "CHECKMARK"
    return "No shipped model in this build: choose a file or train one", "ERROR"


class VIEW3D_PT_cljn_denoise(bpy.types.Panel):
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "CLJN"
    bl_label = "Denoise Points"

    def draw(self, context):
        layout = self.layout
        settings = context.scene.cljn_denoise

        if deps.missing():
            draw_dependencies(layout, context, compact=True)

        col = layout.column()
        col.use_property_split = True
        col.use_property_decorate = False
        col.prop(settings, "model_source", expand=True)
        if settings.model_source == "FILE":
            col.prop(settings, "model_path", text="File")
        else:
            text, icon = _default_model_text(context)
            col.label(text=text, icon=icon)
        col.prop(settings, "auto_iterations")
        row = col.row()
        row.enabled = not settings.auto_iterations
        row.prop(settings, "iterations")
        col.prop(settings, "patch_radius")
        col.prop(settings, "use_known_noise")
        row = col.row()
        row.enabled = settings.use_known_noise
        row.prop(settings, "noise_sigma")
        col.prop(settings, "treat_as_solid")
        col.prop(settings, "orientation")
        col.prop(settings, "device")
        col.prop(settings, "backend")
        col.prop(settings, "use_mesh_vertices")

        selected = list(context.selected_objects)
        clouds = object_io.point_cloud_objects(selected, settings.use_mesh_vertices)
        if not selected:
            layout.label(text="Select point clouds to process", icon="INFO")
        elif not clouds:
            layout.label(text="No point cloud among the selection", icon="ERROR")
        else:
            points = sum(object_io.point_count(o) for o in clouds)
            layout.label(text=f"{len(clouds)} point cloud(s), {points:,} points", icon="POINTCLOUD_DATA")

        col = layout.column(align=True)
        col.scale_y = 1.3
        col.operator("cljn.denoise_points", icon="MOD_SMOOTH")
        col.operator("cljn.estimate_normals", icon="NORMALS_VERTEX")
        layout.operator("cljn.restore_original", icon="LOOP_BACK")

        box = layout.box()
        box.label(text="Train on selected clean meshes")
        box.operator("cljn.train_model", icon="EXPERIMENTAL")


def draw_object_menu(self, context):
    layout = self.layout
    layout.separator()
    layout.operator("cljn.denoise_points", icon="MOD_SMOOTH")
    layout.operator("cljn.estimate_normals", icon="NORMALS_VERTEX")
    layout.operator("cljn.restore_original", icon="LOOP_BACK")
    layout.operator("cljn.train_model", text="Train CLJN Model", icon="EXPERIMENTAL")


classes = (VIEW3D_PT_cljn_denoise,)


def register():
    for cls in classes:
        bpy.utils.register_class(cls)
    bpy.types.VIEW3D_MT_object.append(draw_object_menu)


def unregister():
    bpy.types.VIEW3D_MT_object.remove(draw_object_menu)
    for cls in reversed(classes):
        bpy.utils.unregister_class(cls)

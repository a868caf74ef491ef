"""File > Import > LAS/LAZ Point Cloud and File > Export > LAS/LAZ Point Cloud (las_io does the work)."""

from pathlib import Path

import bpy
from bpy.props import BoolProperty, StringProperty
from bpy_extras.io_utils import ExportHelper, ImportHelper

from ..core.errors import InputError
from ..core.formats import las
from . import las_io, object_io


class CLJN_OT_import_las(bpy.types.Operator, ImportHelper):
    """Import a LAS/LAZ point cloud, recentred (its true coordinates are kept for export)"""
    bl_idname = "cljn.import_las"
    bl_label = "Import LAS/LAZ"
    bl_options = {"REGISTER", "UNDO"}

    filter_glob: StringProperty(default="*.las;*.laz", options={"HIDDEN"})
    as_point_cloud: BoolProperty(
        name="As Point Cloud Object", default=True,
        description="A Point Cloud object (points drawn in the viewport); off: a mesh of vertices")

    def execute(self, context):
        try:
            obj = las_io.import_las(self.filepath, as_point_cloud=self.as_point_cloud,
                                    scene=context.scene)
        except InputError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        for other in context.selected_objects:
            other.select_set(False)
        obj.select_set(True)
        context.view_layer.objects.active = obj
        self.report({"INFO"}, f"Imported {object_io.point_count(obj)} points as '{obj.name}'")
        return {"FINISHED"}


class CLJN_OT_export_las(bpy.types.Operator, ExportHelper):
    """Export the active point cloud as LAS/LAZ (true coordinates, every imported field, normals)"""
    bl_idname = "cljn.export_las"
    bl_label = "Export LAS/LAZ"

    filename_ext = ".laz"
    check_extension = None          # .las or .laz, as typed
    filter_glob: StringProperty(default="*.las;*.laz", options={"HIDDEN"})
    keep_scale: BoolProperty(
        name="Keep File Scale", default=False,
        description="Write at the imported file's scale even where its grid is too coarse for "
                    "the cleaning (moves of a few mm on a 1 cm grid round back); off: a scale "
                    "10-1000x finer then, every imported coordinate still exact")
    classify_outliers: BoolProperty(
        name="Outliers as Noise (Class 7)", default=False,
        description="Give points flagged as outliers classification 7 (ASPRS low point/noise), "
                    "for tools that filter by class; their own class is overwritten in the file")

    @classmethod
    def poll(cls, context):
        obj = context.active_object
        if obj is None or obj.type not in ("MESH", "POINTCLOUD"):
            cls.poll_message_set("Make a point cloud (a mesh or a Point Cloud object) active")
            return False
        return True

    def execute(self, context):
        path = Path(self.filepath)
        if path.suffix.lower() not in (".las", ".laz"):
            self.report({"ERROR"}, f"{path}: the file name must end in .las or .laz")
            return {"CANCELLED"}
        try:
            warnings = las_io.export_las(context.active_object, path, keep_scale=self.keep_scale,
                                         classify_outliers=self.classify_outliers)
            scale = max(las.file_scales(path))
        except InputError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        for warning in warnings:
            self.report({"WARNING"}, warning)
        self.report({"INFO"}, f"Exported '{context.active_object.name}' to {path} (scale {scale:g})")
        return {"FINISHED"}


def _menu_import(self, context):
    self.layout.operator(CLJN_OT_import_las.bl_idname, text="LAS/LAZ Point Cloud (.las, .laz)")


def _menu_export(self, context):
    self.layout.operator(CLJN_OT_export_las.bl_idname, text="LAS/LAZ Point Cloud (.las, .laz)")


classes = (CLJN_OT_import_las, CLJN_OT_export_las)


def register():
    for cls in classes:
        bpy.utils.register_class(cls)
    bpy.types.TOPBAR_MT_file_import.append(_menu_import)
    bpy.types.TOPBAR_MT_file_export.append(_menu_export)


def unregister():
    bpy.types.TOPBAR_MT_file_export.remove(_menu_export)
    bpy.types.TOPBAR_MT_file_import.remove(_menu_import)
    for cls in reversed(classes):
        bpy.utils.unregister_class(cls)

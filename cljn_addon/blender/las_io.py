"""LAS/LAZ files <-> Blender objects, for File > Import/Export > LAS/LAZ Point Cloud and the
command line's .las -> .blend path. No UI here.

Import recentres: the object's points are float32 positions relative to ORIGIN (the cloud's
bounding-box centre, float64, kept on the object), so a scan at x = 500,000 m keeps its
millimetres. Intensity and classification become INT point attributes, RGB the colour
attribute "Color" (shown by the object's material). Every record's bytes are kept in INT
attributes `las_record_K` (4 bytes each), and the file's header (scale, offset, VLRs with the
CRS, EVLRs) as a zero-point LAS in HEADER; export rebuilds each record from them, so every
field comes back exactly, and a point whose position was not changed gets back its exact
integer coordinates. Export adds the normals (cljn_normal) and outlier flags (cljn_outlier) as
extra bytes (see core/formats/las.py); edited intensity, classification or colour attributes are
written too. An object that did not come from a LAS file is exported as a new LAS 1.4 file.
"""
from __future__ import annotations

import base64
from pathlib import Path

import bpy
import numpy as np

from ..core.errors import InputError
from ..core.formats import las
from . import object_io

ORIGIN = "cljn_las_origin"          # object property: true coordinates of the local origin
HEADER = "cljn_las_header"          # object property: base64 of the header as a zero-point LAS
RGB_MAX = "cljn_las_rgb_max"        # object property: 255 or 65535, what Color 1.0 stands for
RECORD_PREFIX = "las_record_"       # INT point attributes: the records' bytes, 4 per attribute
COLOR = "Color"
VISIBLE_INT_FIELDS = ("intensity", "classification")


def _records_to_words(records: np.ndarray) -> np.ndarray:
    n, size = records.shape
    padded = np.zeros((n, -(-size // 4) * 4), np.uint8)
    padded[:, :size] = records
    return padded.view(np.int32)


def _words_to_records(words: np.ndarray, size: int) -> np.ndarray:
    return np.ascontiguousarray(words.astype(np.int32)).view(np.uint8)[:, :size]


def _radius_for(points: np.ndarray) -> float:
    """Half the median spacing of a sample: points that touch without hiding each other."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(0)
    sample = points[rng.choice(len(points), min(len(points), 20000), replace=False)]
    d, _ = cKDTree(sample).query(sample, k=2)
    spacing = float(np.median(d[:, 1])) * np.sqrt(len(sample) / len(points))
    return max(spacing * 0.5, 1e-6)


def _color_material(name):
    mat = bpy.data.materials.new(f"{name} colours")
    mat.use_nodes = True
    nodes = mat.node_tree.nodes
    bsdf = next((nd for nd in nodes if nd.type == "BSDF_PRINCIPLED"), None)
    if bsdf is None:
        return mat
    attr = nodes.new("ShaderNodeAttribute")
    attr.attribute_name = COLOR
    mat.node_tree.links.new(attr.outputs["Color"], bsdf.inputs["Base Color"])
    return mat


def _to_point_cloud(obj):
    """Convert a mesh-of-vertices object to a Point Cloud object (same attributes)."""
    mesh = obj.data
    with bpy.context.temp_override(active_object=obj, object=obj, selected_objects=[obj],
                                   selected_editable_objects=[obj]):
        bpy.ops.object.convert(target="POINTCLOUD")
    if obj.type == "POINTCLOUD" and mesh.users == 0:
        bpy.data.meshes.remove(mesh)
    return obj


def point_cloud_supported() -> bool:
    prop = bpy.ops.object.convert.get_rna_type().properties["target"]
    return "POINTCLOUD" in {item.identifier for item in prop.enum_items}


def import_las(path, *, name=None, as_point_cloud=True, scene=None):
    """A new object in `scene` (default: the current one) holding the file's points."""
    path = Path(path)
    cloud = las.read_las(path, with_fields=False)
    header = cloud.source.header
    records = las.load_records(cloud.source)
    view = las.record_view(records, header)
    origin = cloud.origin            # the middle of the file's integer box (true coordinates)
    name = name or path.stem
    mesh = bpy.data.meshes.new(name)
    mesh.vertices.add(len(cloud.points))
    mesh.vertices.foreach_set("co", cloud.points.astype(np.float32).ravel())
    words = _records_to_words(records)
    for k in range(words.shape[1]):
        mesh.attributes.new(f"{RECORD_PREFIX}{k}", "INT", "POINT").data.foreach_set("value", words[:, k])
    dims = set(header.point_format.dimension_names)
    for field in VISIBLE_INT_FIELDS:
        mesh.attributes.new(field, "INT", "POINT").data.foreach_set(
            "value", np.asarray(view[field]).astype(np.int32))
    rgb_max = None
    if {"red", "green", "blue"} <= dims:
        rgb = np.stack([np.asarray(view[c]) for c in ("red", "green", "blue")], axis=1).astype(np.float64)
        rgb_max = 255 if rgb.max(initial=0) <= 255 else 65535
        rgba = np.concatenate([rgb / rgb_max, np.ones((len(rgb), 1))], axis=1).astype(np.float32)
        color = mesh.color_attributes.new(COLOR, "FLOAT_COLOR", "POINT")
        color.data.foreach_set("color", rgba.ravel())
        mesh.color_attributes.active_color = color
        mesh.color_attributes.render_color_index = mesh.color_attributes.active_color_index
    mesh.update()
    obj = bpy.data.objects.new(name, mesh)
    (scene or bpy.context.scene).collection.objects.link(obj)
    obj[ORIGIN] = [float(v) for v in origin]
    obj[HEADER] = base64.b64encode(las.header_bytes(header)).decode("ascii")
    if rgb_max is not None:
        obj[RGB_MAX] = rgb_max
        obj.data.materials.append(_color_material(name))
    if as_point_cloud and point_cloud_supported():
        _to_point_cloud(obj)
        radius = obj.data.attributes.get("radius") or obj.data.attributes.new("radius", "FLOAT", "POINT")
        radius.data.foreach_set("value", np.full(len(cloud.points), _radius_for(cloud.points),
                                                 np.float32))
    return obj


def _int_attribute(data, name, n):
    attr = data.attributes.get(name)
    if attr is None or attr.domain != "POINT" or attr.data_type != "INT":
        return None
    values = np.empty(n, np.int32)
    attr.data.foreach_get("value", values)
    return values


def _world_normals(obj, n):
    attr = obj.data.attributes.get(object_io.NORMAL)
    if attr is None or attr.domain != "POINT" or attr.data_type != "FLOAT_VECTOR":
        return None
    local = np.empty(n * 3, np.float32)
    attr.data.foreach_get("vector", local)
    m3 = np.array(obj.matrix_world, np.float64)[:3, :3]
    world = local.reshape(-1, 3).astype(np.float64) @ np.linalg.inv(m3)   # inverse-transpose
    length = np.linalg.norm(world, axis=1, keepdims=True)
    return np.divide(world, length, out=np.zeros_like(world), where=length > 0).astype(np.float32)


def _outliers(obj, n):
    attr = obj.data.attributes.get(object_io.OUTLIER)
    if attr is None or attr.domain != "POINT" or attr.data_type != "BOOLEAN":
        return None
    values = np.zeros(n, bool)
    attr.data.foreach_get("value", values)
    return values


def _stored_records(obj, header, n):
    size = header.point_format.size
    words = [_int_attribute(obj.data, f"{RECORD_PREFIX}{k}", n) for k in range(-(-size // 4))]
    if any(w is None for w in words):
        return None
    return _words_to_records(np.stack(words, axis=1), size).copy()


def _apply_visible_fields(obj, view, n, warnings):
    dims = set(view.point_format.dimension_names)
    for field in VISIBLE_INT_FIELDS:
        values = _int_attribute(obj.data, field, n)
        if values is None or field not in dims:
            continue
        info = np.iinfo(np.asarray(view[field]).dtype)
        if values.min(initial=0) < info.min or values.max(initial=0) > info.max:
            warnings.append(f"'{obj.name}': '{field}' values outside {info.min}..{info.max} were clipped")
        view[field] = np.clip(values, info.min, info.max)
    color = obj.data.color_attributes.get(COLOR) if hasattr(obj.data, "color_attributes") else None
    if color is not None and not {"red", "green", "blue"} <= dims:
        warnings.append(f"'{obj.name}': its '{COLOR}' attribute is not written: the file's point "
                        f"format {view.point_format.id} has no RGB")
    elif color is not None and color.domain == "POINT":
        rgba = np.empty(n * 4, np.float32)
        color.data.foreach_get("color", rgba)
        scale = float(obj.get(RGB_MAX, 65535))
        rgb = np.clip(np.round(rgba.reshape(-1, 4)[:, :3].astype(np.float64) * scale), 0, 65535)
        for k, c in enumerate(("red", "green", "blue")):
            view[c] = rgb[:, k].astype(np.uint16)


def export_las(obj, path, keep_scale=False, classify_outliers=False) -> list[str]:
    """Write obj's points (world space + ORIGIN) to a .las/.laz file; returns warnings.
    keep_scale: the imported file's scale even where its grid rounds the cleaning away;
    classify_outliers: flagged outliers get the noise class (las.NOISE_CLASS)."""
    from ..core.formats.points import PointCloud

    path = Path(path)
    reason = object_io.check_point_cloud(obj, use_mesh_vertices=True)
    if reason is not None:
        raise InputError(reason)
    n = object_io.point_count(obj)
    origin = np.asarray(obj.get(ORIGIN, (0.0, 0.0, 0.0)), np.float64).reshape(3)
    local = object_io.read_local_points(obj)
    matrix = np.array(obj.matrix_world, np.float64)
    points = local.astype(np.float64) @ matrix[:3, :3].T + matrix[:3, 3]      # relative to origin
    warnings: list[str] = []
    source = None
    if HEADER in obj:
        header = las.header_from_bytes(base64.b64decode(obj[HEADER]))
        records = _stored_records(obj, header, n)
        if records is None:
            warnings.append(f"'{obj.name}': its LAS record attributes are missing; "
                            "only positions and the visible attributes are written")
            records = np.zeros((n, header.point_format.size), np.uint8)
        view = las.record_view(records, header)
        _apply_visible_fields(obj, view, n, warnings)
        # Points not moved since import (and an unchanged transform) keep their exact integers.
        mid = las.mid_of(origin, header)
        if mid is not None and np.array_equal(matrix, np.eye(4)):
            imported = las.local_positions(las.record_ints(view), mid, header)
            unmoved = np.all(imported.astype(np.float32) == local, axis=1)
            points[unmoved] = imported[unmoved]
        source = las.LasSource(header, records=np.ascontiguousarray(records))
    extra = {}
    if source is None:
        for field in VISIBLE_INT_FIELDS:
            values = _int_attribute(obj.data, field, n)
            if values is not None:
                extra[field] = values
    cloud = PointCloud(points, _world_normals(obj, n), extra, source=source, origin=origin)
    las.write_las(path, cloud, outliers=_outliers(obj, n), keep_scale=keep_scale,
                  classify_outliers=classify_outliers)
    return warnings

"""The command line's --preview: input (left, grey, depth-shaded) and result (right, coloured
by normal or displacement) side by side, rendered with Cycles on the CPU (works headless, in
the bpy wheel and in `blender -b`). Replaces the open file with a scene of its own.
"""
from __future__ import annotations

import contextlib
import warnings
from dataclasses import dataclass
from pathlib import Path

import bpy
import mathutils
import numpy as np

from ..core.formats.points import atomic_paths
from .blendfile import empty_scene, quiet_stdout

PREVIEW_MAX_POINTS = 30000
PREVIEW_SIZE = (960, 480)
OUTLIER_COLOUR = (0.9, 0.1, 0.1)
BACKGROUND = (0.93, 0.93, 0.93, 1.0)


@dataclass
class PreviewItem:
    """One cloud to render: positions before and after, and the result's per-point values."""

    label: str
    before: np.ndarray
    after: np.ndarray
    normals: np.ndarray
    displacement: np.ndarray
    outliers: np.ndarray
    job: object = None           # the command line's job this picture belongs to

    @classmethod
    def of(cls, label, before, result, job=None, max_points=PREVIEW_MAX_POINTS):
        """A random subset of at most max_points (fixed seed) of a cloud and its result."""
        n = len(before)
        keep = slice(None)
        if n > max_points:
            keep = np.sort(np.random.default_rng(0).choice(n, max_points, replace=False))
        return cls(label, np.asarray(before, np.float64)[keep],
                   np.asarray(result.points, np.float64)[keep],
                   np.asarray(result.normals, np.float64)[keep],
                   np.asarray(result.displacement, np.float64)[keep],
                   np.asarray(result.outliers, bool)[keep], job)


@dataclass
class _Layout:
    """Both clouds at unit diagonal around the origin, and the orthographic view of them."""

    before: np.ndarray
    after: np.ndarray
    view: np.ndarray              # the camera looks along -view
    right: np.ndarray
    up: np.ndarray
    offset: float                 # each cloud's shift along `right`
    height: float                 # half the height of the taller cloud on screen
    width: float                  # orthographic scale

    def depth_shade(self, p):
        d = p @ self.view
        span = float(d.max() - d.min()) or 1.0
        return 0.55 + 0.45 * (d - d.min()) / span     # nearer is brighter


def _layout(before, after) -> _Layout:
    both = np.concatenate([before, after])
    lo, hi = both.min(axis=0), both.max(axis=0)
    centre = (lo + hi) / 2.0
    diag = float(np.linalg.norm(hi - lo)) or 1.0
    view = np.array([0.55, -1.0, 0.45])
    view /= np.linalg.norm(view)
    right = np.cross([0.0, 0.0, 1.0], view)
    right /= np.linalg.norm(right)
    up = np.cross(view, right)
    b, r = (before - centre) / diag, (after - centre) / diag
    half = max(np.abs(b @ right).max(), np.abs(r @ right).max(), 1e-3)   # half-width on screen
    height = max(np.abs(b @ up).max(), np.abs(r @ up).max(), 1e-3)
    gap = 0.15 * half + 0.02
    width = 2 * (2 * half + gap) * 1.08
    aspect = PREVIEW_SIZE[0] / PREVIEW_SIZE[1]
    width = max(width, 2 * height * 1.25 * aspect)    # fit the taller side too
    return _Layout(b, r, view, right, up, half + gap / 2, height, width)


def _colours(item: PreviewItem, layout: _Layout, color_by: str):
    """(grey shades of the input, colours of the result), outliers in red in both."""
    grey = np.repeat((0.62 * layout.depth_shade(layout.before))[:, None], 3, axis=1)
    if color_by == "displacement":
        disp = np.asarray(item.displacement, np.float64)
        scale = float(np.percentile(disp, 99)) if len(disp) and disp.max() > 0 else 1.0
        colours = _ramp(disp / (scale or 1.0))
    else:
        nrm = np.asarray(item.normals, np.float64)
        colours = 0.5 + 0.5 * nrm * (0.75 + 0.25 * layout.depth_shade(layout.after))[:, None]
    outliers = np.asarray(item.outliers, bool)
    grey[outliers] = OUTLIER_COLOUR
    colours[outliers] = OUTLIER_COLOUR
    return grey, colours


def render_preview(item: PreviewItem, target: Path, color_by="normal", title="denoised"):
    """Render item to the PNG `target` (atomically)."""
    empty_scene()
    scene = bpy.context.scene
    layout = _layout(item.before, item.after)
    grey, colours = _colours(item, layout, color_by)
    _add_clouds(scene, layout, grey, colours, title)
    _add_camera(scene, layout)
    _add_world(scene)
    _render_settings(scene)
    _render(scene, target)


def _add_clouds(scene, layout, grey, colours, title):
    mat = _emission_material("cljn_preview")
    group = _points_node_group(_splat_radius(layout.after), mat)
    shift, label_up = layout.offset * layout.right, layout.up * (layout.height + 0.03)
    _add_cloud(scene, "before", layout.before - shift, grey, group)
    _add_cloud(scene, "after", layout.after + shift, colours, group)
    for text, where in (("input", -shift), (title, shift)):
        _add_label(scene, text, where + label_up, layout, layout.width * 0.035)


def _add_camera(scene, layout):
    cam_data = bpy.data.cameras.new("cljn_preview_camera")
    cam_data.type = "ORTHO"
    cam_data.ortho_scale = layout.width
    cam_data.clip_end = 20.0
    cam = bpy.data.objects.new("cljn_preview_camera", cam_data)
    scene.collection.objects.link(cam)
    cam.matrix_world = _look_matrix(layout.view * 4.0 + layout.up * 0.03, layout)
    scene.camera = cam


def _add_world(scene):
    world = bpy.data.worlds.new("cljn_preview_world")
    world.use_nodes = True
    bg = world.node_tree.nodes.get("Background")
    if bg is not None:
        bg.inputs["Color"].default_value = BACKGROUND
        bg.inputs["Strength"].default_value = 1.0
    scene.world = world


def _render_settings(scene):
    """Cycles on the CPU, few samples, emission only: fast and the same everywhere."""
    render = scene.render
    render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = 6
    scene.cycles.use_denoising = False
    scene.cycles.use_adaptive_sampling = False
    scene.cycles.max_bounces = 0
    render.resolution_x, render.resolution_y = PREVIEW_SIZE
    render.resolution_percentage = 100
    render.film_transparent = False
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    render.image_settings.file_format = "PNG"
    render.image_settings.color_mode = "RGB"
    render.use_file_extension = False


def _render(scene, target: Path):
    target.parent.mkdir(parents=True, exist_ok=True)
    with atomic_paths(target) as (tmp,):
        scene.render.filepath = str(tmp.resolve())
        with quiet_stdout():
            bpy.ops.render.render(write_still=True)
        if tmp.stat().st_size == 0:
            raise RuntimeError("Cycles wrote an empty image")


def _srgb_to_linear(c):
    c = np.clip(c, 0.0, 1.0)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def _ramp(t):
    """Dark blue -> teal -> yellow for t in [0, 1] (a viridis-like ramp, sRGB)."""
    stops = np.array([[0.27, 0.00, 0.33], [0.23, 0.32, 0.55], [0.13, 0.57, 0.55],
                      [0.37, 0.79, 0.38], [0.99, 0.91, 0.14]])
    t = np.clip(np.asarray(t, np.float64), 0.0, 1.0) * (len(stops) - 1)
    i = np.minimum(t.astype(int), len(stops) - 2)
    f = (t - i)[:, None]
    return stops[i] * (1.0 - f) + stops[i + 1] * f


def _splat_radius(points) -> float:
    """Sphere radius that closes the gaps between neighbours (points at unit diagonal)."""
    from scipy.spatial import cKDTree

    if len(points) < 2:
        return 0.01
    dist, _ = cKDTree(points).query(points, k=2)
    spacing = float(np.median(dist[:, 1]))
    return float(np.clip(0.9 * spacing, 0.0015, 0.02))


def _look_matrix(location, layout):
    m = mathutils.Matrix.Identity(4)
    for i in range(3):
        m[i][0], m[i][1], m[i][2], m[i][3] = layout.right[i], layout.up[i], layout.view[i], location[i]
    return m


@contextlib.contextmanager
def _no_deprecation_warnings():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        yield


def _emission_material(name):
    mat = bpy.data.materials.new(name)
    with _no_deprecation_warnings():
        mat.use_nodes = True
    nt = mat.node_tree
    nt.nodes.clear()
    attr = nt.nodes.new("ShaderNodeAttribute")
    attr.attribute_name = "cljn_color"
    emit = nt.nodes.new("ShaderNodeEmission")
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    nt.links.new(attr.outputs["Color"], emit.inputs["Color"])
    nt.links.new(emit.outputs["Emission"], out.inputs["Surface"])
    return mat


def _points_node_group(radius, mat):
    """Geometry nodes: mesh vertices -> points (spheres in Cycles) with the material."""
    ng = bpy.data.node_groups.new("cljn_preview_points", "GeometryNodeTree")
    ng.interface.new_socket(name="Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    ng.interface.new_socket(name="Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    gin = ng.nodes.new("NodeGroupInput")
    gout = ng.nodes.new("NodeGroupOutput")
    to_points = ng.nodes.new("GeometryNodeMeshToPoints")
    to_points.inputs["Radius"].default_value = radius
    set_mat = ng.nodes.new("GeometryNodeSetMaterial")
    set_mat.inputs["Material"].default_value = mat
    ng.links.new(gin.outputs[0], to_points.inputs["Mesh"])
    ng.links.new(to_points.outputs["Points"], set_mat.inputs["Geometry"])
    ng.links.new(set_mat.outputs["Geometry"], gout.inputs[0])
    return ng


def _add_cloud(scene, name, points, colours, group):
    mesh = bpy.data.meshes.new(f"cljn_preview_{name}")
    mesh.vertices.add(len(points))
    mesh.vertices.foreach_set("co", np.asarray(points, np.float32).ravel())
    rgba = np.ones((len(points), 4), np.float32)
    rgba[:, :3] = _srgb_to_linear(colours)
    attr = mesh.attributes.new("cljn_color", "FLOAT_COLOR", "POINT")
    attr.data.foreach_set("color", rgba.ravel())
    mesh.update()
    obj = bpy.data.objects.new(f"cljn_preview_{name}", mesh)
    scene.collection.objects.link(obj)
    obj.modifiers.new("points", "NODES").node_group = group
    return obj


def _add_label(scene, text, location, layout, size):
    curve = bpy.data.curves.new(f"cljn_label_{text}", "FONT")
    curve.body = text
    curve.align_x = "CENTER"
    curve.size = size
    obj = bpy.data.objects.new(f"cljn_label_{text}", curve)
    scene.collection.objects.link(obj)
    obj.matrix_world = _look_matrix(location, layout)
    mat = bpy.data.materials.new(f"cljn_label_{text}")
    with _no_deprecation_warnings():
        mat.use_nodes = True
    emit = mat.node_tree.nodes.new("ShaderNodeEmission")
    emit.inputs["Color"].default_value = (0.02, 0.02, 0.02, 1.0)
    out = mat.node_tree.nodes.get("Material Output")
    mat.node_tree.links.new(emit.outputs["Emission"], out.inputs["Surface"])
    curve.materials.append(mat)
    return obj

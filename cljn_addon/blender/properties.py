"""The panel's settings, stored per scene as `scene.cljn_denoise` (saved with the .blend)."""

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, StringProperty

MODEL_SOURCES = (
    ("DEFAULT", "Default", "The model file set in the add-on preferences, else the shipped model"),
    ("FILE", "File", "A .safetensors weights file (its .json config beside it)"),
)
# The panel's orientation choices; pipeline.options_from_settings maps them to the engine's.
ORIENTATIONS = (
    ("OUTWARD", "Outward", "Point normals out of the shape"),
    ("CAMERA", "Toward Camera", "Point normals toward the active scene camera (scans)"),
    ("CURSOR", "Toward 3D Cursor", "Point normals toward the 3D cursor"),
    ("NONE", "None", "Leave the sign of each normal as the network gives it"),
)
# The devices (the add-on preferences offer these; the panel adds "Default" = the preferences').
DEVICES = (
    ("AUTO", "Auto", "A GPU when torch sees one, else the CPU"),
    ("CPU", "CPU", "Always the CPU"),
    ("GPU", "GPU", "CUDA or Apple MPS; refuses to run when torch sees no GPU"),
)
PANEL_DEVICES = (("PREFERENCES", "Default", "The device chosen in the add-on preferences"),) + DEVICES
DEVICE_TO_CORE = {"AUTO": "auto", "CPU": "cpu", "GPU": "gpu"}   # -> core.config.DEVICE_CHOICES
# Inference backends (preferences); the panel adds "Default" = the preferences'.
BACKENDS = (
    ("AUTO", "Auto", "torch when it is installed (GPUs, bf16 on CPU), else numpy"),
    ("TORCH", "torch", "torch (Install torch in the preferences); needed for a GPU"),
    ("NUMPY", "numpy", "numpy only, on the CPU: needs nothing beyond what the extension bundles"),
)
PANEL_BACKENDS = (("PREFERENCES", "Default", "The backend chosen in the add-on preferences"),) + BACKENDS
BACKEND_TO_CORE = {"AUTO": "auto", "TORCH": "torch", "NUMPY": "numpy"}   # -> core.config.BACKENDS


class CLJN_PG_settings(bpy.types.PropertyGroup):
    model_source: EnumProperty(name="Model", items=MODEL_SOURCES, default="DEFAULT")
    model_path: StringProperty(
        name="Model File", subtype="FILE_PATH",
        description="Network weights (.safetensors) with their .json config beside them")
    auto_iterations: BoolProperty(
        name="Auto Iterations", default=True,
        description="Choose 1-4 filtering passes from the cloud's estimated noise (fewer at low noise "
                    "keep fine detail and thin parts), stopping once points have moved as far as the "
                    "noise; untick to set Iterations yourself")
    iterations: IntProperty(
        name="Iterations", default=4, min=1, max=20, soft_max=10,
        description="Filtering passes; more removes more noise (4 is the paper's default, 10 for heavy noise)")
    patch_radius: FloatProperty(
        name="Patch Radius", default=5.0, min=0.1, max=50.0, soft_min=1.0, soft_max=20.0,
        subtype="PERCENTAGE", precision=1,
        description="Neighbourhood radius in % of the bounding-box diagonal of the cloud (world space). "
                    "Estimate Normals takes it as the largest and uses the smaller ball that holds one "
                    "patch's points on a dense cloud")
    use_known_noise: BoolProperty(
        name="Known Scanner Noise", default=False,
        description="Use the scanner's noise you give below instead of estimating it from the cloud. "
                    "Tick it when fine relief (carving, texture) reads as noise and gets smoothed away")
    noise_sigma: FloatProperty(
        name="Scanner Noise", default=0.001, min=0.0, soft_max=0.1, subtype="DISTANCE", unit="LENGTH",
        precision=5,
        description="The scanner's noise, one standard deviation, in world units (a spec sheet's range "
                    "precision); sets the pass count, the stop and the motion bound, and how far round each point "
                    "Estimate Normals looks for the surface it came from")
    treat_as_solid: BoolProperty(
        name="Solid Object", default=False,
        description="Denoise Points: handle the object as solid even where its surface reads as a thin "
                    "part's two sides (the report says thin-walled). Tick it for a sculpt whose relief, "
                    "ribs or limbs come out under-cleaned")
    orientation: EnumProperty(name="Orientation", items=ORIENTATIONS, default="OUTWARD")
    device: EnumProperty(name="Device", items=PANEL_DEVICES, default="PREFERENCES")
    backend: EnumProperty(name="Backend", items=PANEL_BACKENDS, default="PREFERENCES")
    use_mesh_vertices: BoolProperty(
        name="Use Vertices of Meshes", default=False,
        description="Also filter the vertices of meshes that have faces (the faces follow the vertices)")


classes = (CLJN_PG_settings,)


def register():
    for cls in classes:
        bpy.utils.register_class(cls)
    bpy.types.Scene.cljn_denoise = bpy.props.PointerProperty(type=CLJN_PG_settings)


def unregister():
    del bpy.types.Scene.cljn_denoise
    for cls in reversed(classes):
        bpy.utils.unregister_class(cls)

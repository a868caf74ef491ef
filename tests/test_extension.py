"""The Blender extension: packaging, install, registration, UI, dependencies, torch + bpy.

Bodies marked @in_blender run inside Blender (bpy wheel) in a subprocess, with the extension
installed from the zip that `make extension` builds (see blender_helpers.py).
"""
from __future__ import annotations

import subprocess
import sys
import sys as _sys
import tomllib
import zipfile
from pathlib import Path
from pathlib import Path as _Path

import pytest

_sys.path.insert(0, str(_Path(__file__).resolve().parent))   # blender_helpers, any import mode

from blender_helpers import PACKAGE, PY, REPO, blender_env, in_blender  # noqa: F401 (fixture)

MANIFEST = REPO / "blender_manifest.toml"


def _blender_ext() -> Path:
    found = sorted((REPO / ".venv").glob("lib/python3*/site-packages/bpy/*/scripts/addons_core/bl_pkg/cli/blender_ext.py"))
    if not found:
        found = sorted(Path(sys.prefix).glob("lib/python3*/site-packages/bpy/*/scripts/addons_core/bl_pkg/cli/blender_ext.py"))
    assert found, "blender_ext.py not found in the bpy wheel"
    return found[0]


def test_zip_is_valid_and_holds_the_package(blender_env):
    manifest = tomllib.loads(MANIFEST.read_text())
    assert manifest["id"] == "cljn_denoise"
    zip_path = blender_env["zip"]
    assert zip_path.name == f"cljn_denoise-{manifest['version']}-linux_x64.zip"
    proc = subprocess.run([PY, str(_blender_ext()), "validate", str(zip_path)], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    names = zipfile.ZipFile(zip_path).namelist()
    # The engine's wheels for this platform, for Blender 4.2-5.0 (cp311) and 5.1+ (cp313),
    # listed in the zip's manifest; no numpy, no torch, no other platform.
    wheels = sorted(n for n in names if n.startswith("wheels/"))
    for package in ("scipy", "safetensors", "laspy", "lazrs"):
        assert any(w.startswith(f"wheels/{package}-") for w in wheels), (package, wheels)
    for tag in ("cp311", "cp313"):
        assert any(tag in w and w.startswith("wheels/scipy-") for w in wheels), (tag, wheels)
    assert not [w for w in wheels if "numpy" in w or "torch" in w or "win_" in w or "macosx" in w], wheels
    zipped = tomllib.loads(zipfile.ZipFile(zip_path).read("blender_manifest.toml").decode())
    assert sorted(zipped["wheels"]) == sorted(f"./{w}" for w in wheels)
    assert zipped["platforms"] == ["linux-x64"]
    for required in ("blender_manifest.toml", "__init__.py", "blender/object_io.py", "blender/operators.py",
                     "core/__init__.py", "core/infer.py"):
        assert required in names, f"{required} missing from the zip"
    assert not [n for n in names if "__pycache__" in n or n.endswith(".pyc") or n.startswith("tests/")]
    # The installed copy is the zip's content.
    installed = blender_env["installed"]
    assert (installed / "blender" / "object_io.py").read_bytes() == zipfile.ZipFile(zip_path).read("blender/object_io.py")


@in_blender(enable=False)
def test_register_unregister_twice_leaves_nothing(bx):
    import sys

    import bpy

    def registered():
        return {
            "scene_prop": hasattr(bpy.types.Scene, "cljn_denoise"),
            "operators": [hasattr(bpy.types, n) for n in ("CLJN_OT_denoise_points", "CLJN_OT_estimate_normals",
                                                           "CLJN_OT_restore_original", "CLJN_OT_train_model",
                                                           "CLJN_OT_install_dependencies")],
            "panel": hasattr(bpy.types, "VIEW3D_PT_cljn_denoise"),
            "prefs": PACKAGE in bpy.context.preferences.addons,
            "menu": any(getattr(f, "__module__", "").startswith(PACKAGE)
                        for f in bpy.types.VIEW3D_MT_object._dyn_ui_initialize()),
        }

    before_path = list(sys.path)
    nothing = {"scene_prop": False, "operators": [False] * 5, "panel": False, "prefs": False, "menu": False}
    everything = {"scene_prop": True, "operators": [True] * 5, "panel": True, "prefs": True, "menu": True}
    assert registered() == nothing, registered()
    for round_ in range(2):
        bx.enable()
        assert registered() == everything, (round_, registered())
        assert "torch" not in sys.modules, "registering the extension imported torch"
        assert bpy.ops.cljn.denoise_points.poll()
        bx.disable()
        assert registered() == nothing, (round_, registered())
        assert sys.path == before_path, "sys.path changed by register/unregister"


class _FakeLayout:
    """Records what draw code asks for and checks it against the registered RNA."""

    def __init__(self, log, icons):
        self.log, self.icons = log, icons
        self.use_property_split = self.use_property_decorate = self.alert = False
        self.scale_y = 1.0

    def _icon(self, kw):
        icon = kw.get("icon")
        assert icon is None or icon in self.icons, f"unknown icon {icon!r}"

    def prop(self, data, name, **kw):
        assert name in data.bl_rna.properties, f"{data.bl_rna.identifier} has no property {name!r}"
        self._icon(kw)
        self.log.append(("prop", name))

    def operator(self, idname, **kw):
        module, _, op = idname.partition(".")
        assert hasattr(getattr(__import__("bpy").ops, module), op), f"unknown operator {idname}"
        assert getattr(getattr(__import__("bpy").ops, module), op).idname() , idname
        self._icon(kw)
        self.log.append(("operator", idname))

    def label(self, text="", **kw):
        self._icon(kw)
        self.log.append(("label", text))

    def separator(self, **kw):
        pass

    def column(self, **kw):
        return _FakeLayout(self.log, self.icons)

    row = box = column


@in_blender
def test_panel_menu_and_preferences_draw(bx):
    import bpy
    import numpy as np

    icons = set(bpy.types.UILayout.bl_rna.functions["label"].parameters["icon"].enum_items.keys())
    panel_cls = bpy.types.VIEW3D_PT_cljn_denoise
    assert (panel_cls.bl_space_type, panel_cls.bl_region_type, panel_cls.bl_category) == ("VIEW_3D", "UI", "CLJN")

    def draw(fn, owner=None):
        log = []
        fake = type("Self", (), {})()
        fake.layout = _FakeLayout(log, icons)
        if owner is not None:   # AddonPreferences.draw(self, ...) calls layout.prop(self, ...)
            fake.bl_rna = owner.bl_rna
        fn(fake, bpy.context)
        return log

    bx.clear_scene()
    obj = bx.make_cloud(np.random.default_rng(0).normal(size=(50, 3)))
    bx.select(obj)
    for source in ("DEFAULT", "FILE"):
        bx.settings.model_source = source
        log = draw(panel_cls.draw)
        props = {name for kind, name in log if kind == "prop"}
        assert {"model_source", "auto_iterations", "iterations", "patch_radius", "use_known_noise", "noise_sigma",
                "treat_as_solid", "orientation", "device", "backend", "use_mesh_vertices"} <= props
        assert ("model_path" in props) == (source == "FILE")
        ops = [name for kind, name in log if kind == "operator"]
        for idname in ("cljn.denoise_points", "cljn.estimate_normals", "cljn.restore_original", "cljn.train_model"):
            assert idname in ops, (idname, ops)
        assert ("label", "1 point cloud(s), 50 points") in log, log

    menu = draw(lambda self, context: [f(self, context) for f in bpy.types.VIEW3D_MT_object._dyn_ui_initialize()
                                       if getattr(f, "__module__", "").startswith(PACKAGE)])
    menu_ops = [name for kind, name in menu if kind == "operator"]
    assert menu_ops[:3] == ["cljn.denoise_points", "cljn.estimate_normals", "cljn.restore_original"], menu_ops

    prefs_log = draw(type(bx.prefs).draw, bx.prefs)
    assert {"default_model_path", "device", "backend", "torch_cpu_only", "pip_extra_args"} <= {
        n for k, n in prefs_log if k == "prop"}
    for name in ("scipy", "safetensors", "laspy", "lazrs"):
        assert ("label", f"{name}: found") in prefs_log, prefs_log
    assert any(k == "label" and n.startswith("torch (optional") and n.endswith("found") for k, n in prefs_log)
    assert [n for k, n in prefs_log if k == "operator"].count("cljn.install_dependencies") == 2   # + Install torch


@in_blender(enable=False)
def test_without_torch_denoise_runs_on_numpy_and_training_says_what_to_press(bx):
    """A Blender without torch: the extension registers, Denoise Points runs on the numpy
    backend, and Train Model says that it needs torch and which button installs it."""
    import sys

    import bpy
    import numpy as np
    import pytest

    for name in ("torch", "scipy", "safetensors"):
        assert name not in sys.modules
    sys.modules["torch"] = None          # `import torch` now fails, as in a Blender without it
    bx.enable()
    deps = __import__(PACKAGE + ".blender.deps", fromlist=["deps"])
    deps.refresh()
    assert deps.missing() == [], deps.missing()
    assert deps.torch_missing()

    bx.clear_scene()
    shapes = __import__(PACKAGE + ".core.evaluation.shapes", fromlist=["shapes"])
    noisy, clean, _ = shapes.sample_shape("sphere", 1500, noise=0.01, seed=2)
    obj = bx.make_cloud(noisy)
    bx.select(obj)
    bx.settings.model_source = "DEFAULT"
    bx.settings.auto_iterations = False
    bx.settings.iterations = 1
    assert bpy.ops.cljn.denoise_points() == {"FINISHED"}
    metrics = __import__(PACKAGE + ".core.evaluation.metrics", fromlist=["metrics"])
    assert metrics.chamfer(bx.world_points(obj), clean) < metrics.chamfer(noisy, clean)
    assert np.allclose(np.linalg.norm(bx.attribute(obj, "cljn_normal"), axis=1), 1.0, atol=1e-4)
    assert sys.modules.get("torch") is None, "torch was imported"

    bx.settings.backend = "TORCH"
    with pytest.raises(RuntimeError, match="needs torch"):
        bpy.ops.cljn.denoise_points()
    bx.settings.backend = "PREFERENCES"

    mesh = bpy.data.meshes.new("Tri")
    mesh.from_pydata(clean[:3].tolist(), [], [(0, 1, 2)])
    mesh_obj = bpy.data.objects.new("Tri", mesh)
    bpy.context.scene.collection.objects.link(mesh_obj)
    bx.select(mesh_obj)
    with pytest.raises(RuntimeError, match="Install torch"):
        bpy.ops.cljn.train_model()


@in_blender
def test_install_dependencies_button_uses_blenders_pip(bx):
    """The Install button's pip run, with a local wheel instead of the network."""
    import base64
    import hashlib
    import importlib
    import os
    import sys
    import zipfile

    import bpy
    import pytest

    wheels = bx.tmp / "wheels"
    wheels.mkdir()
    files = {
        "cljn_dummy_dep/__init__.py": b"VALUE = 42\n",
        "cljn_dummy_dep-1.0.dist-info/METADATA": b"Metadata-Version: 2.1\nName: cljn-dummy-dep\nVersion: 1.0\n",
        "cljn_dummy_dep-1.0.dist-info/WHEEL": b"Wheel-Version: 1.0\nGenerator: test\nRoot-Is-Purelib: true\nTag: py3-none-any\n",
    }
    record = []
    with zipfile.ZipFile(wheels / "cljn_dummy_dep-1.0-py3-none-any.whl", "w") as zf:
        for name, data in files.items():
            zf.writestr(name, data)
            digest = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()
            record.append(f"{name},sha256={digest},{len(data)}")
        record.append("cljn_dummy_dep-1.0.dist-info/RECORD,,")
        zf.writestr("cljn_dummy_dep-1.0.dist-info/RECORD", "\n".join(record) + "\n")

    bx.prefs.pip_extra_args = f"--no-index --find-links {wheels}"
    result = bpy.ops.cljn.install_dependencies(packages="cljn-dummy-dep")
    assert result == {"FINISHED"}, result
    target = bpy.utils.extension_path_user(PACKAGE, path="site-packages")
    assert os.path.isfile(os.path.join(target, "cljn_dummy_dep", "__init__.py")), os.listdir(target)
    assert target in sys.path
    assert not os.path.exists(os.path.join(target, "numpy")), "pip put a second numpy into the target"
    assert importlib.import_module("cljn_dummy_dep").VALUE == 42

    with pytest.raises(RuntimeError, match="Installing dependencies failed: pip failed"):
        bpy.ops.cljn.install_dependencies(packages="cljn-no-such-package")

    bx.prefs.pip_extra_args = ""
    if not bpy.app.online_access:
        with pytest.raises(RuntimeError, match="Online access is off"):
            bpy.ops.cljn.install_dependencies()


@pytest.mark.parametrize("order", ["bpy, torch", "torch, bpy"])
def test_bpy_and_torch_in_one_process(order, tmp_path):
    code = f"""
import {order}
import numpy as np
x = torch.from_numpy(np.arange(6, dtype=np.float32).reshape(2, 3))
assert float(torch.nn.functional.linear(x, torch.eye(3)).sum()) == 15.0
me = bpy.data.meshes.new("m"); me.vertices.add(2)
me.vertices.foreach_set("co", x.numpy().ravel())
assert me.vertices[1].co.z == 5.0
print("ok", bpy.app.version_string, torch.__version__)
"""
    env = dict(__import__("os").environ, BLENDER_USER_RESOURCES=str(tmp_path))
    proc = subprocess.run([PY, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert proc.returncode == 0 and "ok" in proc.stdout, proc.stdout + proc.stderr

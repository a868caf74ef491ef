"""Test helpers for the Blender extension (bpy wheel, headless).

bpy reads BLENDER_USER_RESOURCES when it is imported, so every test body that needs Blender
runs in a fresh subprocess against a throwaway user directory in which the extension was
installed from its built zip the real way (the Install from Disk operator) and is enabled
with addon_utils, exactly as Blender does:

    from blender_helpers import in_blender

    @in_blender
    def test_something(bx):      # runs inside Blender; bx: the helpers below (BlenderTest)
        obj = bx.make_cloud(points)
        ...

The outer test (the one pytest sees) takes the session fixture `blender_env` (zip built with
`make extension`, installed once per session) and pytest's `tmp_path`, runs
`python tests/blender_helpers.py run <test file> <function>` and fails with the inner
traceback when the body raises. Inside, plain `assert` with messages; pytest.raises works.
"""
from __future__ import annotations

import importlib
import importlib.util
import os
import subprocess
import sys
import textwrap
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PY = sys.executable
EXT_ID = "cljn_denoise"
REPO_MODULE = "user_default"
PACKAGE = f"bl_ext.{REPO_MODULE}.{EXT_ID}"
SHIPPED_WEIGHTS = REPO / "cljn_addon" / "weights" / "cljn_small.safetensors"

_INNER = "CLJN_IN_BLENDER"


# ---------------------------------------------------------------------------------------------
# Outer side (the pytest process): build, install once, run bodies in subprocesses.


def build_extension_zip(dist: Path) -> Path:
    """`make extension DIST=dist PLATFORMS=linux-x64` (never remaking the venv): the zip a
    Linux user installs, with its bundled wheels; returns the zip path. Built with the repo's
    .venv when there is one (its bpy 5.0's blender_ext.py), so that the zip under test is the
    same whichever Blender version runs the tests."""
    dist.mkdir(parents=True, exist_ok=True)
    builder = REPO / ".venv" / "bin" / "python"
    proc = subprocess.run(["make", "-s", "-o", ".venv/.requirements-installed", "extension",
                           f"DIST={dist}", "PLATFORMS=linux-x64",
                           f"PY={builder if builder.exists() else PY}"],
                          cwd=REPO, capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"make extension failed:\n{proc.stdout}\n{proc.stderr}")
    zips = sorted(dist.glob(f"{EXT_ID}-*-linux_x64.zip"))
    if len(zips) != 1:
        raise RuntimeError(f"expected one {EXT_ID}-*-linux_x64.zip in {dist}, found {zips}")
    return zips[0]


def blender_subprocess_env(user_resources: Path, **extra) -> dict:
    env = dict(os.environ)
    env["BLENDER_USER_RESOURCES"] = str(user_resources)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO / "tests")] + [p for p in [env.get("PYTHONPATH")] if p])
    env.update({k: str(v) for k, v in extra.items()})
    return env


def run_python(code: str, env: dict, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([PY, "-c", textwrap.dedent(code)], env=env, cwd=REPO,
                          capture_output=True, text=True, timeout=timeout)


def install_extension(zip_path: Path, user_resources: Path) -> Path:
    """Install from disk into the user_default repository, as Blender's Install from Disk does."""
    code = f"""
        import os, bpy
        result = bpy.ops.extensions.package_install_files(
            filepath={str(zip_path)!r}, repo={REPO_MODULE!r}, enable_on_install=True)
        assert result == {{'FINISHED'}}, result
        assert {PACKAGE!r} in bpy.context.preferences.addons, "not enabled after install"
    """
    proc = run_python(code, blender_subprocess_env(user_resources))
    if proc.returncode != 0:
        raise RuntimeError(f"installing the extension failed:\n{proc.stdout}\n{proc.stderr}")
    # The remote repository's directory, so refreshing all repositories does not warn.
    (user_resources / "extensions" / "blender_org").mkdir(parents=True, exist_ok=True)
    installed = user_resources / "extensions" / REPO_MODULE / EXT_ID
    if not (installed / "blender_manifest.toml").exists():
        raise RuntimeError(f"extension not found in {installed} after install:\n{proc.stdout}")
    return installed


_session_env: dict = {}


def _blender_env(tmp_path_factory):
    """Build the zip once and install it into a throwaway user directory (cached per session)."""
    if not _session_env:
        root = tmp_path_factory.mktemp("cljn_blender")
        zip_path = build_extension_zip(root / "dist")
        user_resources = root / "user_resources"
        installed = install_extension(zip_path, user_resources)
        _session_env.update(zip=zip_path, user_resources=user_resources, installed=installed)
    return dict(_session_env)


def _make_fixture():
    import pytest

    return pytest.fixture(scope="session", name="blender_env")(_blender_env)


try:
    blender_env = _make_fixture()   # import it into a test module: `from blender_helpers import blender_env`
except ImportError:                 # inside Blender without pytest: not needed there
    blender_env = None


def in_blender(fn=None, *, enable=True, needs_shipped_model=False, timeout=240):
    """Decorator: run the test body inside Blender in a subprocess (see module docstring)."""
    def decorate(body):
        if os.environ.get(_INNER):
            body._cljn_enable = enable
            return body

        def test(blender_env, tmp_path):
            import pytest

            if needs_shipped_model and not SHIPPED_WEIGHTS.exists():
                pytest.xfail(f"no shipped model yet ({SHIPPED_WEIGHTS.relative_to(REPO)} is missing)")
            module_file = Path(sys.modules[body.__module__].__file__)
            env = blender_subprocess_env(blender_env["user_resources"], **{_INNER: "1"},
                                         CLJN_TEST_TMP=tmp_path)
            proc = subprocess.run([PY, str(Path(__file__)), "run", str(module_file), body.__name__],
                                  env=env, cwd=REPO, capture_output=True, text=True, timeout=timeout)
            sys.stdout.write(proc.stdout)
            if proc.returncode != 0:
                pytest.fail(f"{body.__name__} failed inside Blender (exit {proc.returncode}):\n"
                            f"{proc.stderr[-6000:]}", pytrace=False)

        test.__name__ = body.__name__
        test.__qualname__ = body.__qualname__
        test.__doc__ = body.__doc__
        test.__module__ = body.__module__
        return test

    return decorate(fn) if fn is not None else decorate


# ---------------------------------------------------------------------------------------------
# Inner side (inside Blender).


class BlenderTest:
    """What a test body gets: the enabled extension, its engine, and small scene helpers."""

    def __init__(self, tmp: Path):
        import bpy

        self.bpy = bpy
        self.tmp = tmp
        self.package = PACKAGE
        self._model_path = None

    # The extension's own modules, imported the way Blender loaded them.
    @property
    def ext(self):
        return importlib.import_module(PACKAGE)

    @property
    def core(self):
        return importlib.import_module(PACKAGE + ".core")

    @property
    def object_io(self):
        return importlib.import_module(PACKAGE + ".blender.object_io")

    @property
    def pipeline(self):
        return importlib.import_module(PACKAGE + ".blender.pipeline")

    @property
    def operators(self):
        return importlib.import_module(PACKAGE + ".blender.operators")

    @property
    def settings(self):
        return self.bpy.context.scene.cljn_denoise

    @property
    def prefs(self):
        return self.bpy.context.preferences.addons[PACKAGE].preferences

    def enable(self):
        import addon_utils

        try:
            self.bpy.ops.extensions.repo_refresh_all()
        except (RuntimeError, AttributeError):
            pass
        mod = addon_utils.enable(PACKAGE, default_set=True, handle_error=_raise)
        assert mod is not None, f"addon_utils.enable({PACKAGE!r}) returned None"
        return mod

    def disable(self):
        import addon_utils

        addon_utils.disable(PACKAGE, default_set=True, handle_error=_raise)

    def clear_scene(self):
        bpy = self.bpy
        for obj in list(bpy.data.objects):
            bpy.data.objects.remove(obj)
        bpy.context.view_layer.update()

    def model_file(self, preset="tiny") -> str:
        """An untrained network saved to a temporary file (fast; for mechanics, not accuracy)."""
        path = self.tmp / f"untrained_{preset}.safetensors"
        if not path.exists():
            self.core.save_model(self.core.build_model(preset), path)
        return str(path)

    def use_model_file(self, preset="tiny"):
        self.settings.model_source = "FILE"
        self.settings.model_path = self.model_file(preset)

    def make_cloud(self, points, name="Cloud", kind="MESH", matrix=None):
        """A point-cloud object (a face-less mesh, or a PointCloud) with local coordinates points."""
        import numpy as np

        bpy = self.bpy
        points = np.asarray(points, dtype=np.float32)
        mesh = bpy.data.meshes.new(name)
        mesh.vertices.add(len(points))
        mesh.vertices.foreach_set("co", points.ravel())
        mesh.update()
        obj = bpy.data.objects.new(name, mesh)
        bpy.context.scene.collection.objects.link(obj)
        if matrix is not None:
            from mathutils import Matrix

            obj.matrix_world = Matrix([list(row) for row in np.asarray(matrix)])
        if kind == "POINTCLOUD":
            self.select(obj)
            result = bpy.ops.object.convert(target="POINTCLOUD")
            assert result == {"FINISHED"}, result
            assert obj.type == "POINTCLOUD", obj.type
        return obj

    def select(self, *objects):
        bpy = self.bpy
        for obj in bpy.context.scene.objects:
            obj.select_set(False)
        for obj in objects:
            obj.select_set(True)
        bpy.context.view_layer.objects.active = objects[0] if objects else None

    def attribute(self, obj, name):
        """A POINT attribute as a numpy array ((N, 3) for vectors)."""
        import numpy as np

        attr = obj.data.attributes[name]
        n = len(attr.data)
        if attr.data_type == "FLOAT_VECTOR":
            buf = np.empty(n * 3, np.float32)
            attr.data.foreach_get("vector", buf)
            return buf.reshape(n, 3)
        buf = np.empty(n, bool if attr.data_type == "BOOLEAN" else np.float32)
        attr.data.foreach_get("value", buf)
        return buf

    def attribute_names(self, obj):
        return sorted(a.name for a in obj.data.attributes)

    def local_points(self, obj):
        return self.attribute(obj, "position").copy()

    def world_points(self, obj):
        import numpy as np

        m = np.array(obj.matrix_world, dtype=np.float64)
        return self.local_points(obj).astype(np.float64) @ m[:3, :3].T + m[:3, 3]

    @property
    def normal_attr(self) -> str:
        """Where the normals are: Blender 5.0's custom_normal; 4.x has only cljn_normal."""
        return "custom_normal" if self.bpy.app.version >= (5, 0, 0) else "cljn_normal"

    @property
    def point_cloud_kind(self) -> str:
        """POINTCLOUD where Blender can convert a mesh to one (not 4.2), else MESH."""
        prop = self.bpy.ops.object.convert.get_rna_type().properties["target"]
        return "POINTCLOUD" if "POINTCLOUD" in {i.identifier for i in prop.enum_items} else "MESH"

    def world_normals(self, obj, name=None):
        import numpy as np

        name = name or self.normal_attr
        m3 = np.array(obj.matrix_world, dtype=np.float64)[:3, :3]
        n = self.attribute(obj, name).astype(np.float64) @ np.linalg.inv(m3)
        return n / np.linalg.norm(n, axis=1, keepdims=True)


def _raise(exc):
    raise exc


def _run_inner(test_file: str, name: str) -> int:
    import traceback

    import bpy  # noqa: F401  (first, with BLENDER_USER_RESOURCES already in the environment)

    tmp = Path(os.environ.get("CLJN_TEST_TMP") or "/tmp")
    spec = importlib.util.spec_from_file_location(Path(test_file).stem, test_file)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    body = getattr(module, name)
    bx = BlenderTest(tmp)
    try:
        if getattr(body, "_cljn_enable", True):
            bx.enable()
        body(bx)
    except BaseException:
        traceback.print_exc()
        sys.stderr.flush()
        return 1
    return 0


if __name__ == "__main__":
    if len(sys.argv) == 4 and sys.argv[1] == "run":
        code = _run_inner(sys.argv[2], sys.argv[3])
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)   # skip bpy's atexit teardown noise; the result is the exit code
    sys.exit("usage: blender_helpers.py run TEST_FILE FUNCTION")

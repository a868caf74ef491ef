"""Stock Blender, one zip, offline (issue #14): a Python holding the bpy wheel and nothing else
from requirements.txt (no torch, scipy, safetensors, laspy) installs the Linux zip through
Blender's own Install from Disk, enables it and denoises a cloud. The engine's packages come
from the wheels bundled in the zip; pip is never run.

The bare virtual environment is made once in .cache/venv-bare-bpy-<version> (bpy from the
package index or pip's cache).
"""
from __future__ import annotations

import importlib.metadata
import os
import shutil
import subprocess
import sys
import textwrap
import zipfile
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from blender_helpers import EXT_ID, PACKAGE, REPO, REPO_MODULE, build_extension_zip  # noqa: E402

try:
    BPY_VERSION = importlib.metadata.version("bpy")
except importlib.metadata.PackageNotFoundError:
    BPY_VERSION = None
pytestmark = pytest.mark.skipif(BPY_VERSION is None, reason="no bpy wheel in this Python")

ENGINE_PACKAGES = ("torch", "scipy", "safetensors", "laspy", "lazrs")


@pytest.fixture(scope="module")
def bare_python():
    """A venv with only bpy (and what bpy itself requires)."""
    venv = REPO / ".cache" / f"venv-bare-bpy-{BPY_VERSION}"
    python = venv / "bin" / "python"
    # Marked complete only after pip succeeds: a run stopped mid-install leaves no half venv
    # that the next run would take for a bare Blender.
    complete = venv / ".complete"
    if not complete.exists():
        shutil.rmtree(venv, ignore_errors=True)
        subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
        # numpy<2: what every Blender from 4.2 to 5.0 ships.
        proc = subprocess.run([str(python), "-m", "pip", "install", "--quiet", f"bpy=={BPY_VERSION}", "numpy<2"],
                              capture_output=True, text=True, timeout=1200)
        if proc.returncode != 0:
            pytest.skip(f"could not install bpy {BPY_VERSION} into a bare venv: {proc.stderr[-500:]}")
        complete.touch()
    code = "import importlib.util as u; print([m for m in %r if u.find_spec(m)])" % (ENGINE_PACKAGES,)
    found = subprocess.run([str(python), "-c", code], capture_output=True, text=True, check=True).stdout
    assert found.strip() == "[]", f"the bare venv holds engine packages: {found}"
    return python


@pytest.fixture(scope="module")
def linux_zip(tmp_path_factory):
    return build_extension_zip(tmp_path_factory.mktemp("dist"))


INNER = """
import os, subprocess, sys
calls = []
for name in ("Popen", "run", "call", "check_call", "check_output"):
    real = getattr(subprocess, name)
    def spy(*args, _real=real, **kw):
        calls.append(str(args[0] if args else kw.get("args")))
        return _real(*args, **kw)
    setattr(subprocess, name, spy)

import bpy
import numpy as np
result = bpy.ops.extensions.package_install_files(filepath=ZIP, repo=REPO_MODULE, enable_on_install=True)
assert result == {'FINISHED'}, result
assert PACKAGE in bpy.context.preferences.addons, "not enabled"

deps = __import__(PACKAGE + ".blender.deps", fromlist=["deps"])
deps.refresh()
MISSING = deps.missing()
print("MISSING", MISSING)
rng = np.random.default_rng(0)
clean = rng.normal(size=(3000, 3))
clean /= np.linalg.norm(clean, axis=1, keepdims=True)
noisy = clean + rng.normal(scale=0.02, size=clean.shape)
mesh = bpy.data.meshes.new("Scan")
mesh.vertices.add(len(noisy))
mesh.vertices.foreach_set("co", noisy.astype(np.float32).ravel())
obj = bpy.data.objects.new("Scan", mesh)
bpy.context.scene.collection.objects.link(obj)
obj.select_set(True)
bpy.context.view_layer.objects.active = obj
bpy.context.scene.cljn_denoise.auto_iterations = False
bpy.context.scene.cljn_denoise.iterations = 2
try:
    print("RESULT", bpy.ops.cljn.denoise_points())
except RuntimeError as exc:
    print("ERROR", exc)
    print("PIP_CALLS", [c for c in calls if "pip" in c])
    raise SystemExit(0)
out = np.empty(len(noisy) * 3, np.float32)
mesh.vertices.foreach_get("co", out)
out = out.reshape(-1, 3).astype(np.float64)
err_in = np.mean(np.abs(np.linalg.norm(noisy, axis=1) - 1))
err_out = np.mean(np.abs(np.linalg.norm(out, axis=1) - 1))
normals = np.empty(len(noisy) * 3, np.float32)
mesh.attributes["cljn_normal"].data.foreach_get("vector", normals)
normals = normals.reshape(-1, 3)
outward = np.mean(np.einsum("ij,ij->i", normals, out) > 0)
import scipy, safetensors
print("SURFACE_ERROR", err_in, err_out, "OUTWARD", outward)
print("FROM", scipy.__file__, safetensors.__file__)
print("TORCH", "torch" in sys.modules and sys.modules["torch"] is not None)
print("PIP_CALLS", [c for c in calls if "pip" in c])
"""


def _run_inner(python, zip_path, user_resources):
    user_resources.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, BLENDER_USER_RESOURCES=str(user_resources), PYTHONNOUSERSITE="1")
    env.pop("PYTHONPATH", None)
    code = (f"ZIP = {str(zip_path)!r}\nREPO_MODULE = {REPO_MODULE!r}\nPACKAGE = {PACKAGE!r}\n"
            + textwrap.dedent(INNER))
    proc = subprocess.run([str(python), "-c", code], capture_output=True, text=True, timeout=600,
                          env=env, cwd=str(user_resources))
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    lines = {ln.split(" ", 1)[0]: ln.split(" ", 1)[1] for ln in proc.stdout.splitlines()
             if ln.split(" ", 1)[0] in ("MISSING", "RESULT", "ERROR", "SURFACE_ERROR", "FROM", "TORCH",
                                        "PIP_CALLS")}
    return lines, proc


def test_bare_blender_installs_the_zip_and_denoises_offline(bare_python, linux_zip, tmp_path):
    lines, proc = _run_inner(bare_python, linux_zip, tmp_path / "user")
    assert lines.get("MISSING") == "[]", proc.stdout[-2000:]
    assert lines.get("RESULT") == "{'FINISHED'}", proc.stdout[-2000:] + proc.stderr[-2000:]
    parts = lines["SURFACE_ERROR"].split()
    err_in, err_out, outward = float(parts[0]), float(parts[1]), float(parts[3])
    assert err_out < 0.6 * err_in, (err_in, err_out)
    assert outward > 0.95, outward
    assert str(tmp_path / "user" / "extensions" / ".local") in lines["FROM"], lines["FROM"]
    assert lines["TORCH"] == "False"
    assert lines["PIP_CALLS"] == "[]", lines["PIP_CALLS"]


def test_a_wheel_missing_from_the_zip_is_a_clear_message(bare_python, linux_zip, tmp_path):
    """scipy's wheels taken out of the zip (and its manifest): installs, then the panel's check
    names scipy and Denoise Points says what to press, without a traceback."""
    broken = tmp_path / linux_zip.name
    with zipfile.ZipFile(linux_zip) as src, zipfile.ZipFile(broken, "w", zipfile.ZIP_DEFLATED) as dst:
        for item in src.infolist():
            if "/scipy-" in item.filename or item.filename.startswith("wheels/scipy-"):
                continue
            data = src.read(item.filename)
            if item.filename.endswith("blender_manifest.toml"):
                data = b"\n".join(ln for ln in data.split(b"\n") if b"/scipy-" not in ln)
            dst.writestr(item, data)
    lines, proc = _run_inner(bare_python, broken, tmp_path / "user")
    assert lines.get("MISSING") == "['scipy']", proc.stdout[-2000:] + proc.stderr[-2000:]
    assert "scipy is not installed" in lines.get("ERROR", ""), proc.stdout[-2000:]
    assert "Install Dependencies" in lines["ERROR"]
    assert "Traceback" not in proc.stderr, proc.stderr[-2000:]
    assert EXT_ID in str(broken)

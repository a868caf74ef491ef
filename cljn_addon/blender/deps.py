"""Python dependencies of the engine inside Blender: what is missing and how to install it.

scipy and safetensors (required), laspy and lazrs (LAS/LAZ) and torch (optional: GPUs and
training; the numpy backend runs the network without it) are not bundled with Blender. The
Install Dependencies and Install torch buttons run
Blender's own Python pip (`sys.executable -m pip install --target DIR`) into this extension's
user directory, which `activate()` appends to sys.path at registration. Appending (not
prepending) keeps Blender's own numpy first. No UI code here; no import of torch either, and
bpy only inside the functions that need it: the command line (cli/) runs the same check,
`engine_missing()`, in any Python.
"""
from __future__ import annotations

import importlib
import importlib.util
import os
import shlex
import subprocess
import sys
import tempfile

# Import name -> pip requirement. numpy ships with Blender and is never replaced (see pip_command).
# The engine needs these (its numpy backend runs the network without torch).
REQUIRED = {
    "scipy": "scipy",
    "safetensors": "safetensors",
}
# Optional: GPUs (CUDA/MPS), bf16 on CPU, and training. Installed by its own button.
TORCH = {"torch": "torch"}
# LAS/LAZ import/export and .las/.laz on the command line; installed with the engine's packages,
# not needed to denoise.
LIDAR = {
    "laspy": "laspy>=2.5,<3",
    "lazrs": "lazrs>=0.6,<1",
}
ENGINE_MODULES = ("numpy", *REQUIRED)   # what the engine imports (numpy included)
TORCH_CPU_INDEX = "https://download.pytorch.org/whl/cpu"
PYPI_INDEX = "https://pypi.org/simple"

ADDON_PACKAGE = __package__.rpartition(".")[0]   # "bl_ext.<repo>.cljn_denoise" when installed

_status: dict[str, bool] = {}      # import name -> found (cached for draw code)
_import_errors: dict[str, str] = {}
_added_paths: list[str] = []


class DependencyError(RuntimeError):
    """Installing or importing a dependency failed; the message says what to do."""


def user_dir(sub: str, create: bool = True) -> str:
    """A writable per-user directory of this extension (kept across upgrades)."""
    import bpy

    try:
        return bpy.utils.extension_path_user(ADDON_PACKAGE, path=sub, create=create)
    except (ValueError, KeyError):
        # Loaded as a plain package (not an installed extension): fall back to Blender's config dir.
        return bpy.utils.user_resource("CONFIG", path=os.path.join("cljn_denoise", sub), create=create)


def site_packages_dir(create: bool = False) -> str:
    return user_dir("site-packages", create=create)


def activate() -> None:
    """Make packages installed by the Install button importable (appended to sys.path)."""
    path = site_packages_dir(create=False)
    if path and os.path.isdir(path) and path not in sys.path:
        sys.path.append(path)
        _added_paths.append(path)
    importlib.invalidate_caches()


def deactivate() -> None:
    """Undo activate() (unregister leaves no sys.path entries behind)."""
    while _added_paths:
        path = _added_paths.pop()
        while path in sys.path:
            sys.path.remove(path)


def _findable(name: str) -> bool:
    try:
        return importlib.util.find_spec(name) is not None
    except (ImportError, ValueError):
        return False


def refresh() -> dict[str, bool]:
    """Re-check which dependencies (required and optional) can be found (cheap: no import)."""
    importlib.invalidate_caches()
    _status.clear()
    for name in (*REQUIRED, *TORCH, *LIDAR):
        _status[name] = _findable(name)
    return dict(_status)


def install_folders() -> list[str]:
    """Every folder where an Install Dependencies button may have put packages: this
    extension's site-packages in each extension repository, and the plain-package fallback."""
    import bpy

    folders = []
    root = bpy.utils.user_resource("EXTENSIONS", path=".user")
    if root and os.path.isdir(root):
        for repo in sorted(os.listdir(root)):
            folders.append(os.path.join(root, repo, "cljn_denoise", "site-packages"))
    folders.append(site_packages_dir(create=False))
    return [f for f in folders if f and os.path.isdir(f)]


def engine_missing() -> list[str]:
    """Names of the engine's packages (numpy included) that cannot be imported here. Under
    Blender (the command line run with `blender -b -P`), the folders of the Install
    Dependencies button are appended to sys.path first (appended: Blender's numpy stays first)."""
    importlib.invalidate_caches()
    gone = [m for m in ENGINE_MODULES if not _findable(m)]
    if gone and "bpy" in sys.modules:
        try:
            folders = install_folders()
        except Exception:                                     # noqa: BLE001 - best effort only
            folders = []
        for folder in folders:
            if folder not in sys.path:
                sys.path.append(folder)
        importlib.invalidate_caches()
        gone = [m for m in ENGINE_MODULES if not _findable(m)]
    return gone


def status() -> dict[str, bool]:
    if not _status:
        refresh()
    return dict(_status)


def missing() -> list[str]:
    """Names of required dependencies that cannot be found or failed to import."""
    found = status()
    return [name for name in REQUIRED if not found[name] or name in _import_errors]


def torch_missing() -> bool:
    """True when torch (optional: GPUs and training) cannot be found or failed to import."""
    return not status().get("torch") or "torch" in _import_errors


def check_imports() -> list[str]:
    """Really import each dependency (slow the first time: torch); returns the missing required
    ones (a broken torch is remembered for torch_missing)."""
    refresh()
    _import_errors.clear()
    for name in (*REQUIRED, *TORCH, *LIDAR):
        if not _status[name]:
            continue
        try:
            importlib.import_module(name)
        except Exception as exc:   # a broken install raises all sorts (OSError for DLLs, ...)
            _import_errors[name] = f"{type(exc).__name__}: {exc}"
    return missing()


def import_error(name: str) -> str | None:
    return _import_errors.get(name)


TORCH_MESSAGE = ("torch is not installed in Blender's Python; it is needed for training and for a GPU "
                 "(denoising runs without it on the CPU): press Install torch in Edit > Preferences > "
                 "Add-ons > CLJN Denoise")


def missing_message(names=None) -> str:
    """The plain sentence the panel and the reports show."""
    names = list(names if names is not None else missing())
    if not names:
        return ""
    broken = [n for n in names if n in _import_errors]
    what = ", ".join(names)
    verb = "is" if len(names) == 1 else "are"
    if broken:
        return (f"{what} {verb} installed but fail to import ({_import_errors[broken[0]]}); "
                "press Install Dependencies in the CLJN panel or the add-on preferences to reinstall")
    return (f"{what} {verb} not installed in Blender's Python: press Install Dependencies in the "
            "CLJN panel (or Edit > Preferences > Add-ons > CLJN Denoise)")


def pip_command(packages, target, *, torch_cpu_only=True, extra_args="") -> tuple[list[str], str]:
    """The pip command line and a constraints file pinning Blender's numpy (caller deletes it)."""
    import numpy

    fd, constraints = tempfile.mkstemp(prefix="cljn_constraints_", suffix=".txt")
    with os.fdopen(fd, "w") as fh:
        fh.write(f"numpy=={numpy.__version__}\n")
    cmd = [sys.executable, "-m", "pip", "install", "--upgrade", "--target", target,
           "--disable-pip-version-check", "--no-input", "--progress-bar", "off",
           "--constraint", constraints]
    extra = shlex.split(extra_args or "")
    if torch_cpu_only and "torch" in packages and "--no-index" not in extra:
        cmd += ["--index-url", TORCH_CPU_INDEX, "--extra-index-url", PYPI_INDEX]
    cmd += extra
    cmd += list(packages)
    return cmd, constraints


def needs_network(extra_args: str) -> bool:
    return "--no-index" not in shlex.split(extra_args or "")


def ensure_pip(log=print) -> None:
    """Blender's Python ships ensurepip; bootstrap pip if it is missing."""
    if importlib.util.find_spec("pip") is not None:
        return
    proc = subprocess.run([sys.executable, "-m", "ensurepip", "--upgrade"],
                          capture_output=True, text=True)
    log(proc.stdout + proc.stderr)
    if proc.returncode != 0:
        raise DependencyError(
            "pip is missing from Blender's Python and ensurepip failed: "
            + _last_line(proc.stdout + proc.stderr))


def _last_line(text: str) -> str:
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    errors = [ln for ln in lines if ln.startswith("ERROR")]
    return (errors or lines or ["no output"])[-1]


_PHASES = (("Looking in", 0.02), ("Collecting", 0.1), ("Downloading", 0.3), ("Using cached", 0.3),
           ("Installing collected", 0.85), ("Successfully installed", 1.0))


def install(packages=None, *, torch_cpu_only=True, extra_args="", progress=None, cancel=None,
            log=print) -> str:
    """Run pip into the extension's site-packages; returns the target directory.

    progress(fraction, message); cancel: an Event-like (is_set()); raises DependencyError with
    the last pip error line on failure.
    """
    packages = list(packages or [*REQUIRED.values(), *LIDAR.values()])
    ensure_pip(log)
    target = site_packages_dir(create=True)
    cmd, constraints = pip_command(packages, target, torch_cpu_only=torch_cpu_only,
                                   extra_args=extra_args)
    log("CLJN Denoise: " + " ".join(shlex.quote(c) for c in cmd))
    env = dict(os.environ, PYTHONNOUSERSITE="1")
    output = []
    fraction = 0.0
    try:
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                env=env, bufsize=1)
        try:
            for line in proc.stdout:
                line = line.rstrip()
                output.append(line)
                log(line)
                for prefix, value in _PHASES:
                    if line.startswith(prefix):
                        fraction = max(fraction, value) if value >= 0.85 else min(
                            0.8, max(fraction, value) + 0.02)
                if progress is not None:
                    progress(fraction, line[:120])
                if cancel is not None and cancel.is_set():
                    proc.terminate()
                    break
        finally:
            proc.wait()
    except OSError as exc:
        raise DependencyError(f"could not run pip ({exc})") from None
    finally:
        os.remove(constraints)
    if cancel is not None and cancel.is_set():
        raise DependencyError("installation cancelled")
    if proc.returncode != 0:
        raise DependencyError(
            f"pip failed (exit code {proc.returncode}): {_last_line(chr(10).join(output))}. "
            "The full pip output is in Blender's system console")
    activate()
    refresh()
    _import_errors.clear()
    return target

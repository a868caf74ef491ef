"""Build the Blender extension: one zip per platform, with the engine's wheels bundled.

    python tools/build_extension.py [--dist DIR] [--platforms linux-x64 ...] [--no-wheels]

1. Downloads (once; cached in .cache/wheels, outside git) the wheels of BUNDLED for each
   platform and for the Python of Blender 4.2-5.0 (3.11) and of Blender 5.1+ (3.13), with
   `pip download --only-binary=:all: --platform ... --python-version ...`: files straight from
   the package index, unmodified, as Blender's extension manual asks. numpy is never bundled
   (Blender ships it); torch is never bundled (optional, installed from the preferences).
2. Stages cljn_addon/ + blender_manifest.toml (no caches, no tests), adds the wheels under
   ./wheels/ and writes `wheels = [...]` and `platforms = [...]` into the staged manifest.
3. Validates and builds with Blender's own blender_ext.py (from the bpy wheel):
   `build --split-platforms` writes cljn_denoise-<version>-<platform>.zip per platform.
--no-wheels builds the one platform-independent zip without wheels (as before bundling).
"""
from __future__ import annotations

import argparse
import glob
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
CACHE = REPO / ".cache" / "wheels"
# What the engine needs beyond Blender's own Python and numpy. scipy 1.14.1 is the newest
# with wheels for both 3.11 and 3.13 that accepts the numpy 1.2x of Blender 4.2-5.0.
BUNDLED = ["scipy==1.14.1", "safetensors==0.5.3", "laspy==2.5.4", "lazrs==0.8.2"]
PYTHONS = ("3.11", "3.13")
# Blender platform -> pip platform tags (pip accepts any of them; the oldest that has wheels).
PLATFORMS = {
    "linux-x64": ["manylinux_2_17_x86_64", "manylinux2014_x86_64"],
    "windows-x64": ["win_amd64"],
    "macos-arm64": ["macosx_12_0_arm64", "macosx_11_0_arm64"],
    "macos-x64": ["macosx_10_13_x86_64", "macosx_10_12_x86_64", "macosx_10_9_x86_64"],
}


def run(cmd, **kw):
    proc = subprocess.run(cmd, capture_output=True, text=True, **kw)
    if proc.returncode != 0:
        sys.stderr.write(proc.stdout + proc.stderr)
        raise SystemExit(f"failed: {' '.join(map(str, cmd))}")
    return proc


def download_wheels(platform: str, python: str) -> list[Path]:
    """The bundled wheels for one platform and Python (cached)."""
    target = CACHE / f"{platform}-py{python}"
    stamp = target / ".complete"
    wanted = "\n".join(BUNDLED)
    if stamp.exists() and stamp.read_text() == wanted:
        return sorted(target.glob("*.whl"))
    if target.exists():
        shutil.rmtree(target)
    target.mkdir(parents=True)
    cmd = [sys.executable, "-m", "pip", "download", "--quiet", "--no-deps", "--only-binary=:all:",
           "--python-version", python, "--implementation", "cp", "-d", str(target)]
    for tag in PLATFORMS[platform]:
        cmd += ["--platform", tag]
    run(cmd + BUNDLED)
    stamp.write_text(wanted)
    return sorted(target.glob("*.whl"))


def blender_ext() -> Path:
    found = sorted(glob.glob(str(Path(sys.prefix) / "lib" / "python3*" / "site-packages" / "bpy" / "*"
                                 / "scripts" / "addons_core" / "bl_pkg" / "cli" / "blender_ext.py")))
    if not found:
        raise SystemExit("blender_ext.py not found in the bpy wheel of this Python (pip install bpy)")
    return Path(found[0])


def stage(root: Path) -> Path:
    staged = root / "cljn_denoise"
    shutil.copytree(REPO / "cljn_addon", staged,
                    ignore=shutil.ignore_patterns("__pycache__", "*.pyc", "tests"))
    shutil.copy2(REPO / "blender_manifest.toml", staged / "blender_manifest.toml")
    return staged


def add_wheels(staged: Path, platforms) -> list[str]:
    """Copy the wheels in and list them (and the platforms) in the staged manifest."""
    (staged / "wheels").mkdir()
    names: list[str] = []
    for platform in platforms:
        for python in PYTHONS:
            for wheel in download_wheels(platform, python):
                if wheel.name not in names:
                    shutil.copy2(wheel, staged / "wheels" / wheel.name)
                    names.append(wheel.name)
    manifest = staged / "blender_manifest.toml"
    text = manifest.read_text()
    block = ("\n# Added by tools/build_extension.py: the engine's wheels, per platform.\n"
             f"platforms = [{', '.join(repr(p).replace(chr(39), chr(34)) for p in platforms)}]\n"
             "wheels = [\n" + "".join(f'  "./wheels/{n}",\n' for n in sorted(names)) + "]\n")
    # Top-level keys must come before the first [table].
    first_table = re.search(r"^\[", text, flags=re.M)
    cut = first_table.start() if first_table else len(text)
    manifest.write_text(text[:cut] + block.lstrip("\n") + "\n" + text[cut:])
    return names


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dist", default=str(REPO / "dist"))
    parser.add_argument("--platforms", nargs="+", default=list(PLATFORMS), choices=list(PLATFORMS))
    parser.add_argument("--no-wheels", action="store_true")
    args = parser.parse_args(argv)
    dist = Path(args.dist)
    dist.mkdir(parents=True, exist_ok=True)
    ext = blender_ext()
    with tempfile.TemporaryDirectory() as tmp:
        staged = stage(Path(tmp))
        if not args.no_wheels:
            add_wheels(staged, args.platforms)
        run([sys.executable, str(ext), "validate", str(staged)])
        cmd = [sys.executable, str(ext), "build", "--source-dir", str(staged), "--output-dir", str(dist)]
        if not args.no_wheels:
            cmd.append("--split-platforms")
        proc = run(cmd)
        sys.stdout.write(proc.stdout)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

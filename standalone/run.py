"""CLJN Denoise, headless.

    python standalone/run.py COMMAND ARGS...                 (Python 3.11 with the bpy wheel)
    blender -b -P standalone/run.py -- COMMAND ARGS...       (Blender 4.2+; arguments after --)

Commands: denoise, normals, train, eval, demo, bench (`run.py COMMAND --help` for each).
Exit codes: 0 success, 1 internal error, 2 bad input or usage, 3 some inputs of a batch
failed, 130 interrupted. Everything happens in cljn_addon.cli; this file only finds it.
"""
import os
import sys

_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if _ROOT not in sys.path:
    sys.path.insert(0, _ROOT)

# Decide before importing anything else: under Blender, bpy is already imported.
_IN_BLENDER = "bpy" in sys.modules

from cljn_addon.cli import argv_from_sys, main  # noqa: E402

if __name__ == "__main__":
    _code = main(argv_from_sys(sys.argv, in_blender=_IN_BLENDER or None))
    sys.stdout.flush()
    sys.stderr.flush()
    sys.exit(_code)

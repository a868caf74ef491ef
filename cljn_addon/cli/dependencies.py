"""Before a command runs: are the engine's packages importable here? (The check itself is the
extension's, blender/deps.py, which also knows where its Install button puts them.)"""
from __future__ import annotations

import sys


def engine_missing_message() -> str | None:
    """None when the engine's packages import here, else the line that says how to get them."""
    from ..blender import deps

    gone = deps.engine_missing()
    if not gone:
        return None
    if "bpy" in sys.modules:
        return f"error: {deps.missing_message(gone)}"
    return f"error: {', '.join(gone)} not installed in this Python: pip install -r requirements.txt"

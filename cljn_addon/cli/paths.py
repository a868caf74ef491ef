"""Default data locations of a source checkout: the shared data folder beside the repository.

Only the command line uses these; the engine takes every path as an argument.
"""
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[2]
SHARED_DATA = REPO_ROOT.parent / "shared" / "data"
DEFAULT_TRAIN_DIR = SHARED_DATA / "meshes" / "train"
DEFAULT_VALIDATION_DIR = SHARED_DATA / "meshes" / "validation"

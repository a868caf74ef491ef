"""Fixtures shared by several test modules."""
import pytest


@pytest.fixture(scope="session")
def model_path(tmp_path_factory):
    """An untrained tiny model saved to disk, for tests that only need a valid weights file."""
    from cljn_addon import core

    path = tmp_path_factory.mktemp("model") / "tiny.safetensors"
    core.save_model(core.build_model("tiny"), path)
    return path


@pytest.fixture(scope="session")
def column_head_relief():
    """(vertices, faces, clean, clean normals, noisy) of column_head at 20K points and 0.6%
    noise: carving at the noise's own scale, uneven over the shape. Skips where the validation
    meshes are absent."""
    import numpy as np

    from cljn_addon.cli.paths import DEFAULT_VALIDATION_DIR
    from cljn_addon.core.evaluation.evaluate import prepare_shape
    from cljn_addon.core.formats.meshes import read_mesh

    path = DEFAULT_VALIDATION_DIR / "column_head.off"
    if not path.exists():
        pytest.skip(f"{path} absent")
    v, f, clean, normals = prepare_shape(*read_mesh(path), 20000, 1)
    return v, f, clean, normals, clean + np.random.default_rng(7).normal(scale=0.006, size=clean.shape)

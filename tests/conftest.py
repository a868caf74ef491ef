"""Fixtures shared by several test modules."""
import pytest


@pytest.fixture(scope="session")
def model_path(tmp_path_factory):
    """An untrained tiny model saved to disk, for tests that only need a valid weights file."""
    from cljn_addon import core

    path = tmp_path_factory.mktemp("model") / "tiny.safetensors"
    core.save_model(core.build_model("tiny"), path)
    return path

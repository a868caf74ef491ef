"""Weights files, without torch: where a model file and its JSON config are, and whether the
tensors in the file are the ones its config implies. Both backends load through here
(model.load_model for torch, numpy_net.load_numpy_net for numpy), so a file is refused the
same way, with the same message, whichever runs it.
"""
from __future__ import annotations

import json
from pathlib import Path

from .config import DEFAULT_WEIGHTS, ModelConfig
from .errors import ModelMismatchError, ModelNotFoundError


def config_path_for(weights_path) -> Path:
    return Path(weights_path).with_suffix(".json")


def locate(path=None) -> tuple[Path, Path, ModelConfig]:
    """(weights file, config file, config) of `path`, or of the shipped model when None."""
    if path is None:
        path = DEFAULT_WEIGHTS
        if not path.exists():
            raise ModelNotFoundError(
                f"No trained default model ships with this build yet (expected {path}). "
                "Train one with `python standalone/run.py train` and pass its weights file.")
    path = Path(path)
    if not path.exists():
        raise ModelNotFoundError(f"Model file not found: {path}")
    cfg_path = config_path_for(path)
    if not cfg_path.exists():
        raise ModelMismatchError(f"Model config missing: {cfg_path} must sit beside {path.name}")
    try:
        config = ModelConfig.from_dict(json.loads(cfg_path.read_text()))
    except (ValueError, TypeError) as exc:
        raise ModelMismatchError(f"Model config {cfg_path} is not valid: {exc}") from None
    return path, cfg_path, config


def read_state(path, load_file) -> dict:
    """The tensors of a safetensors file through `load_file` (safetensors.torch or .numpy)."""
    from safetensors import SafetensorError

    try:
        return load_file(str(path))
    except (SafetensorError, OSError, ValueError) as exc:
        raise ModelMismatchError(f"{path} is not a readable safetensors weights file: {exc}") from None


def _linear_bn(prefix, index, c_in, c_out, shapes):
    shapes[f"{prefix}.{index}.weight"] = (c_out, c_in)
    shapes[f"{prefix}.{index}.bias"] = (c_out,)
    for name in ("weight", "bias", "running_mean", "running_var"):
        shapes[f"{prefix}.{index + 1}.{name}"] = (c_out,)
    shapes[f"{prefix}.{index + 1}.num_batches_tracked"] = ()


def _mlp_shapes(prefix, c_in, hidden, c_out, dropout, shapes):
    """Names and shapes of model._mlp: [Linear, BN, ReLU, (Dropout)] per hidden, then Linear."""
    index = 0
    for c in hidden:
        _linear_bn(prefix, index, c_in, c, shapes)
        index += 4 if dropout else 3
        c_in = c
    shapes[f"{prefix}.{index}.weight"] = (c_out, c_in)
    shapes[f"{prefix}.{index}.bias"] = (c_out,)


def expected_tensors(config: ModelConfig) -> dict:
    """{tensor name: shape} of CLJNNet(config)'s state dict, computed without torch."""
    shapes: dict = {}
    c_in = 3
    for i, c in enumerate(config.encoder_channels):
        _linear_bn("encoder.mlp", 3 * i, c_in, c, shapes)
        c_in = c
    heads = list(config.head_channels)
    _mlp_shapes("head.mlp", config.feature_dim, heads[:-1], heads[-1], 0.0, shapes)
    _mlp_shapes("regressor.mlp", config.feature_dim, config.regressor_channels, 6, config.dropout, shapes)
    return shapes


def check_tensors(path, cfg_path, config: ModelConfig, state: dict) -> None:
    """ModelMismatchError naming the first difference between the file's tensors and the config's."""
    expected = expected_tensors(config)
    missing = sorted(set(expected) - set(state))
    unexpected = sorted(set(state) - set(expected))
    if missing or unexpected:
        parts = []
        if missing:
            parts.append(f"missing {len(missing)} tensor(s), e.g. {missing[0]}")
        if unexpected:
            parts.append(f"{len(unexpected)} unexpected tensor(s), e.g. {unexpected[0]}")
        raise ModelMismatchError(f"{Path(path).name} does not match its config {Path(cfg_path).name} "
                                 f"(preset {config.preset!r}): " + "; ".join(parts))
    for key, shape in expected.items():
        if tuple(state[key].shape) != tuple(shape):
            raise ModelMismatchError(
                f"{Path(path).name} does not match its config {Path(cfg_path).name}: tensor {key} has shape "
                f"{tuple(state[key].shape)}, the config needs {tuple(shape)}")

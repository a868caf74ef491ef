"""The inference network in numpy: the same weights file, no torch.

The regression branch (encoder f, regressor h) with BatchNorm folded into each Linear layer,
as model.InferenceNet does in torch: per-point Linear+ReLU rows as float32 matrix products,
a max-pool over each patch, then the regressor and tanh. Weights come from the safetensors
file through safetensors' numpy API (no pickle); the tensor names and shapes a config implies
are derived here without torch, so a file that does not match its config is refused the same
way as by model.load_model. Training needs torch; inference does not.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .config import DEFAULT_WEIGHTS, ModelConfig
from .errors import ModelMismatchError, ModelNotFoundError

PATCHES_PER_BLOCK = 64   # ~8K rows: each layer's output stays in cache for its bias and ReLU


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


def _folded(state, prefix, hidden_count, step):
    """[(W^T, b)] of an MLP with BN folded: hidden layers, then the last plain Linear."""
    layers = []
    for k in range(hidden_count):
        i = k * step
        w = state[f"{prefix}.{i}.weight"].astype(np.float64)
        b = state[f"{prefix}.{i}.bias"].astype(np.float64)
        gamma, beta = state[f"{prefix}.{i + 1}.weight"], state[f"{prefix}.{i + 1}.bias"]
        mean, var = state[f"{prefix}.{i + 1}.running_mean"], state[f"{prefix}.{i + 1}.running_var"]
        scale = gamma.astype(np.float64) / np.sqrt(var.astype(np.float64) + 1e-5)
        layers.append((np.ascontiguousarray((w * scale[:, None]).T, np.float32),
                       ((b - mean) * scale + beta).astype(np.float32)))
    last = hidden_count * step
    if f"{prefix}.{last}.weight" in state:
        layers.append((np.ascontiguousarray(state[f"{prefix}.{last}.weight"].T, np.float32),
                       state[f"{prefix}.{last}.bias"].astype(np.float32)))
    return layers


class NumpyNet:
    """Regression branch of a CLJNNet in numpy (eval mode, BatchNorm folded)."""

    backend = "numpy"

    def __init__(self, config: ModelConfig, state: dict):
        self.config = config
        self.encoder = _folded(state, "encoder.mlp", len(config.encoder_channels), 3)
        step = 4 if config.dropout else 3
        self.regressor = _folded(state, "regressor.mlp", len(config.regressor_channels), step)

    def chunk_size(self) -> int:
        """Patches gathered per call: the torch path's, so that both draw the same random
        patch samples and give the same result."""
        from .infer import _chunk_size

        return _chunk_size(self)

    def _features(self, patches):
        b, n, _ = patches.shape
        x = patches.reshape(b * n, 3)
        for w, bias in self.encoder[:-1]:
            x = x @ w
            x += bias
            np.maximum(x, 0.0, out=x)
        # max(ReLU(xW + b)) = ReLU(max(xW) + b): the widest layer's bias and ReLU after pooling.
        w, bias = self.encoder[-1]
        x = (x @ w).reshape(b, n, -1).max(axis=1)
        x += bias
        return np.maximum(x, 0.0, out=x)

    def __call__(self, patches: np.ndarray):
        """(B, n, 3) float32 patches -> (displacement (B, 3), unit normal (B, 3)), float32."""
        patches = np.ascontiguousarray(patches, np.float32)
        x = np.concatenate([self._features(patches[s:s + PATCHES_PER_BLOCK])
                            for s in range(0, len(patches), PATCHES_PER_BLOCK)])
        for w, bias in self.regressor[:-1]:
            x = x @ w
            x += bias
            np.maximum(x, 0.0, out=x)
        w, bias = self.regressor[-1]
        out = np.tanh(x @ w + bias)
        normal = out[:, 3:]
        normal = normal / np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-8)
        return out[:, :3], normal


def load_numpy_net(path=None) -> NumpyNet:
    """The shipped model (path None) or a weights file, for the numpy backend; refuses a
    missing file, a missing or invalid config and tensors that do not match it."""
    from safetensors import SafetensorError
    from safetensors.numpy import load_file

    if path is None:
        path = DEFAULT_WEIGHTS
        if not path.exists():
            raise ModelNotFoundError(f"No trained default model ships with this build yet (expected {path}).")
    path = Path(path)
    if not path.exists():
        raise ModelNotFoundError(f"Model file not found: {path}")
    cfg_path = path.with_suffix(".json")
    if not cfg_path.exists():
        raise ModelMismatchError(f"Model config missing: {cfg_path} must sit beside {path.name}")
    try:
        config = ModelConfig.from_dict(json.loads(cfg_path.read_text()))
    except (ValueError, TypeError) as exc:
        raise ModelMismatchError(f"Model config {cfg_path} is not valid: {exc}") from None
    try:
        state = load_file(str(path))
    except (SafetensorError, OSError, ValueError) as exc:
        raise ModelMismatchError(f"{path} is not a readable safetensors weights file: {exc}") from None
    expected = expected_tensors(config)
    missing = sorted(set(expected) - set(state))
    unexpected = sorted(set(state) - set(expected))
    wrong = sorted(k for k in set(expected) & set(state) if tuple(state[k].shape) != expected[k])
    if missing or unexpected or wrong:
        parts = []
        if missing:
            parts.append(f"missing {', '.join(missing[:3])}" + ("..." if len(missing) > 3 else ""))
        if unexpected:
            parts.append(f"unexpected {', '.join(unexpected[:3])}" + ("..." if len(unexpected) > 3 else ""))
        for k in wrong[:3]:
            parts.append(f"{k} has shape {tuple(state[k].shape)}, the config needs {expected[k]}")
        raise ModelMismatchError(f"{path} does not match its config {cfg_path.name} ({'; '.join(parts)})")
    return NumpyNet(config, state)

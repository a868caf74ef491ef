"""The inference network in numpy: the same weights file, no torch.

The regression branch (encoder f, regressor h) with BatchNorm folded into each Linear layer,
as model.InferenceNet does in torch: per-point Linear+ReLU rows as float32 matrix products,
a max-pool over each patch, then the regressor and tanh. Weights come from the safetensors
file through safetensors' numpy API (no pickle); the tensor names and shapes a config implies
are derived without torch (core/weights.py), so a file that does not match its config is
refused the same way as by model.load_model. Training needs torch; inference does not.
"""
from __future__ import annotations

import numpy as np

from . import weights
from .config import ModelConfig

PATCHES_PER_BLOCK = 64   # ~8K rows: each layer's output stays in cache for its bias and ReLU


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
    """The shipped model (path None) or a weights file, for the numpy backend; refused exactly
    as model.load_model refuses it (core/weights.py)."""
    from safetensors.numpy import load_file

    path, cfg_path, config = weights.locate(path)
    state = weights.read_state(path, load_file)
    weights.check_tensors(path, cfg_path, config, state)
    return NumpyNet(config, state)

"""Encoder f, projection head g and regressor h (METHOD.md, Networks); weights I/O.

The per-point shared MLP is written as Linear layers on (B*n, C) rows, which is the same
function as Conv1d with kernel 1 and runs as one matrix product per layer.
"""
from __future__ import annotations

import json
from pathlib import Path

import torch
from torch import nn

from . import weights
from .config import DEFAULT_WEIGHTS, ModelConfig, get_preset  # noqa: F401 (DEFAULT_WEIGHTS: re-exported)
from .weights import config_path_for


class Encoder(nn.Module):
    """Shared per-point MLP with BatchNorm + ReLU after every layer, then max-pool."""

    def __init__(self, channels):
        super().__init__()
        layers, c_in = [], 3
        for c_out in channels:
            layers += [nn.Linear(c_in, c_out), nn.BatchNorm1d(c_out), nn.ReLU(inplace=True)]
            c_in = c_out
        self.mlp = nn.Sequential(*layers)

    def forward(self, patches: torch.Tensor) -> torch.Tensor:   # (B, n, 3) -> (B, C)
        b, n, _ = patches.shape
        per_point = self.mlp(patches.reshape(b * n, 3))
        return per_point.reshape(b, n, -1).amax(dim=1)


def _mlp(c_in, hidden, c_out, dropout=0.0):
    layers = []
    for c in hidden:
        layers += [nn.Linear(c_in, c), nn.BatchNorm1d(c), nn.ReLU(inplace=True)]
        if dropout:
            layers.append(nn.Dropout(dropout))
        c_in = c
    layers.append(nn.Linear(c_in, c_out))
    return nn.Sequential(*layers)


class ProjectionHead(nn.Module):
    """g: feature -> hidden -> projection, no activation on the last layer."""

    def __init__(self, feature_dim, channels):
        super().__init__()
        self.mlp = _mlp(feature_dim, channels[:-1], channels[-1])

    def forward(self, features):
        return self.mlp(features)


class Regressor(nn.Module):
    """h: feature -> hidden (BN+ReLU+Dropout) -> 6, tanh. Output: displacement, normal."""

    def __init__(self, feature_dim, channels, dropout):
        super().__init__()
        self.mlp = _mlp(feature_dim, channels, 6, dropout)
        # Start at the classic baseline: zero displacement, normal along the PCA z axis, so
        # training only has to learn corrections (METHOD.md, lessons of the probe).
        last = self.mlp[-1]
        nn.init.normal_(last.weight, std=1e-3)
        with torch.no_grad():
            last.bias.copy_(torch.tensor([0.0, 0.0, 0.0, 0.0, 0.0, 1.0]))

    def forward(self, features):
        return torch.tanh(self.mlp(features))


class CLJNNet(nn.Module):
    def __init__(self, config: ModelConfig):
        super().__init__()
        self.config = config
        self.encoder = Encoder(config.encoder_channels)
        self.head = ProjectionHead(config.feature_dim, config.head_channels)
        self.regressor = Regressor(config.feature_dim, config.regressor_channels, config.dropout)

    def project(self, patches):
        """Contrastive branch: L2-normalised projection z = g(f(P))."""
        return nn.functional.normalize(self.head(self.encoder(patches)).float(), dim=1)

    def forward(self, patches):
        """Regression branch: (displacement in radius units, unit normal), both (B, 3)."""
        out = self.regressor(self.encoder(patches)).float()
        return out[:, :3], nn.functional.normalize(out[:, 3:], dim=1, eps=1e-8)


def _fold_batchnorm(seq: nn.Sequential) -> nn.Sequential:
    """Linear followed by eval-mode BatchNorm becomes one Linear; Dropout (eval) is dropped."""
    layers, mods = [], list(seq)
    i = 0
    while i < len(mods):
        m = mods[i]
        if isinstance(m, nn.Linear) and i + 1 < len(mods) and isinstance(mods[i + 1], nn.BatchNorm1d):
            bn = mods[i + 1]
            scale = bn.weight / torch.sqrt(bn.running_var + bn.eps)
            fused = nn.Linear(m.in_features, m.out_features)
            fused.weight.data = m.weight.data * scale[:, None]
            fused.bias.data = (m.bias.data - bn.running_mean) * scale + bn.bias.data
            layers.append(fused)
            i += 2
            continue
        if not isinstance(m, nn.Dropout):
            layers.append(m)
        i += 1
    return nn.Sequential(*layers)


class InferenceNet(nn.Module):
    """The regression branch with BatchNorm folded into the Linear layers (same outputs in
    eval mode, ~20% faster on CPU). Built once per model by `inference_net`."""

    def __init__(self, model: "CLJNNet"):
        super().__init__()
        self.config = model.config
        with torch.no_grad():
            self.encoder = _fold_batchnorm(model.encoder.mlp)
            self.regressor = _fold_batchnorm(model.regressor.mlp)

    def forward(self, patches):
        b, n, _ = patches.shape
        feats = self.encoder(patches.reshape(b * n, 3)).reshape(b, n, -1).amax(dim=1)
        out = torch.tanh(self.regressor(feats)).float()
        return out[:, :3], nn.functional.normalize(out[:, 3:], dim=1, eps=1e-8)


def inference_net(model: "CLJNNet") -> InferenceNet:
    return InferenceNet(model.eval()).eval().to(next(model.parameters()).device)


def build_model(config="small") -> CLJNNet:
    """An untrained network for a preset name or a ModelConfig."""
    if isinstance(config, str):
        config = get_preset(config)
    return CLJNNet(config)


def save_model(model: CLJNNet, path, extra_metadata: dict | None = None) -> Path:
    """Write weights (safetensors, no pickle) and the JSON config beside them, atomically."""
    from safetensors.torch import save_file

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    metadata = {"config": model.config.to_json()}
    for key, value in (extra_metadata or {}).items():
        metadata[key] = value if isinstance(value, str) else json.dumps(value)
    tmp = path.with_name(path.name + ".tmp")
    save_file(state, str(tmp), metadata=metadata)
    tmp.replace(path)
    cfg_tmp = config_path_for(path).with_name(config_path_for(path).name + ".tmp")
    cfg_tmp.write_text(model.config.to_json() + "\n")
    cfg_tmp.replace(config_path_for(path))
    return path


def load_model(path=None, device="cpu") -> CLJNNet:
    """The shipped default model (path None) or the given weights file, in eval mode.

    Refuses, with a message that names the problem, a missing file, a missing or unreadable
    config, and weights whose tensors do not match the config (core/weights.py).
    """
    from safetensors.torch import load_file

    path, cfg_path, config = weights.locate(path)
    state = weights.read_state(path, load_file)
    weights.check_tensors(path, cfg_path, config, state)
    model = CLJNNet(config)
    model.load_state_dict(state)
    return model.to(device).eval()

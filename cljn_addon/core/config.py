"""Network architecture presets. The JSON config stored beside the weights is `ModelConfig`."""
from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path

# The shipped model: weights (safetensors) with their JSON config beside them.
WEIGHTS_DIR = Path(__file__).resolve().parent.parent / "weights"
DEFAULT_WEIGHTS = WEIGHTS_DIR / "cljn_small.safetensors"

# Engine option values (one table each; the CLI's choices and the engine's checks use them).
ORIENTATIONS = ("outward", "viewpoint", "none")
DEVICE_CHOICES = ("auto", "cpu", "cuda", "gpu", "mps")
# Inference backends: torch (GPU, bf16 on CPU) or numpy (no torch needed); auto takes torch
# when it is installed.
BACKENDS = ("auto", "torch", "numpy")


@dataclass(frozen=True)
class ModelConfig:
    """Architecture of encoder f, projection head g and regressor h (METHOD.md, Networks)."""

    preset: str = "small"
    points_per_patch: int = 128
    encoder_channels: tuple = (64, 128, 256, 512)      # 3 -> ... -> feature size, BN+ReLU after each
    head_channels: tuple = (512, 256, 128)             # feature -> ... -> projection (no act. on last)
    regressor_channels: tuple = (256, 128, 64)         # feature -> ... -> 6, BN+ReLU+Dropout between
    dropout: float = 0.3
    patch_radius_fraction: float = 0.05                 # r = 5% of the bbox diagonal
    format_version: int = 1

    @property
    def feature_dim(self) -> int:
        return self.encoder_channels[-1]

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2, sort_keys=True)

    @classmethod
    def from_dict(cls, data: dict) -> "ModelConfig":
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"unknown model config keys: {', '.join(unknown)}")
        kwargs = {k: (tuple(v) if isinstance(v, list) else v) for k, v in data.items()}
        return cls(**kwargs)


# The paper's networks, exactly as METHOD.md.
PAPER = ModelConfig(
    preset="paper",
    points_per_patch=500,
    encoder_channels=(64, 128, 256, 512, 1024),
    head_channels=(1024, 512, 256),
    regressor_channels=(512, 256, 128, 64),
)

# Sized for 2 CPU cores: 128 points per patch and an encoder that stops at 512 channels.
# ~10K patches/s forward in bf16 here versus ~470/s for the paper preset (METHOD.md), at the
# cost of a coarser view of each patch (128 samples instead of 500).
SMALL = ModelConfig()

# Used by tests only: trains in seconds.
TINY = ModelConfig(
    preset="tiny",
    points_per_patch=64,
    encoder_channels=(32, 64, 128),
    head_channels=(128, 64),
    regressor_channels=(64, 32),
)

PRESETS = {"paper": PAPER, "small": SMALL, "tiny": TINY}


def get_preset(name: str) -> ModelConfig:
    try:
        return PRESETS[name]
    except KeyError:
        raise ValueError(f"unknown preset {name!r}; choose one of {', '.join(PRESETS)}") from None


@dataclass
class LossConfig:
    """Joint loss weights (METHOD.md, Regressor training) and the NT-Xent temperature."""

    alpha: float = 0.9
    beta: float = 0.01
    delta: float = 0.3
    gamma: int = 12
    temperature: float = 0.01


ROTATION_ANGLES_DEG = (0, 15, 30, 45, 60, 90, 105, 120, 135, 150, 180)
TRAIN_NOISE_LEVELS = (0.0, 0.0025, 0.005, 0.01, 0.015, 0.025)   # fraction of the bbox diagonal
# Ours: the same range covered evenly, so low noise (where moving too much hurts) is as
# present in training as high noise.
TRAIN_NOISE_LEVELS_DENSE = (0.0, 0.0025, 0.005, 0.0075, 0.01, 0.0125, 0.015, 0.02, 0.025)
NOISE_LEVEL_SETS = {"paper": TRAIN_NOISE_LEVELS, "dense": TRAIN_NOISE_LEVELS_DENSE}
TEST_NOISE_LEVELS = (0.006, 0.008, 0.011, 0.015, 0.020)
INFLATION_NEIGHBOURS = 100
LRMA_NEIGHBOURS = 20
MIN_BALL_POINTS = 3   # fewer points in the ball: an outlier, flagged and not moved


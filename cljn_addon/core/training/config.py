"""Training settings: `TrainConfig` (paper values as defaults), the quick schedule and the cache
folder. Imports neither torch nor numpy, so the command line can build its options from it."""
from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

DEFAULT_CACHE = Path(os.environ.get("CLJN_CACHE", Path.home() / ".cache" / "cljn_denoise"))


@dataclass
class TrainConfig:
    """Paper values are the defaults; the CPU recipe in the model card scales the schedule."""

    preset: str = "small"
    points_per_shape: int = 100_000
    patches_per_shape: int = 8192           # per epoch (paper code)
    contrastive_epochs: float = 150
    contrastive_batch: int = 512            # pairs
    contrastive_lr: float = 3e-4
    weight_decay: float = 1e-4
    regression_epochs: float = 30
    regression_batch: int = 12
    regression_optimizer: str = "sgd"       # paper: SGD lr 1e-2, momentum 0.9
    regression_lr: float = 1e-2
    momentum: float = 0.9
    finetune_encoder: bool = False          # paper: encoder frozen in stage 2
    loss: str = "joint"                     # or "fixed" (the ablation)
    normal_target: str = "nearest"          # paper: clean point nearest the prediction; or "index"
    normal_loss: str = "paper"              # paper: 1 - d cos^2 - (1-d) cos^g; or "squared_angle"
    gt_points: int = 256                    # clean points per ground-truth patch
    gt_side: str = "all"                    # paper: every clean point of the ball; or "own" (see data.py)
    noise_levels: str = "paper"             # paper: 0, .25, .5, 1, 1.5, 2.5%; or "dense" (9 levels)
    seed: int = 0
    init_weights: str = ""                  # start from a trained model (e.g. to fine-tune further)
    checkpoint_minutes: float = 5.0
    max_minutes: float = 0.0                # > 0: a wall-clock budget; the cosine decay follows the
                                            # clock and the running stage ends when it is spent
    data_workers: int = 0                   # > 0: processes build the regressor's batches (a GPU
                                            # outruns one core's patch gathering)
    batch_builder: str = "auto"             # "numpy" (k-d trees on the CPU), "device" (torch on the
                                            # training device: device_batches.py) or "auto" (device
                                            # when training on a CUDA GPU)
    bf16: bool = True
    device: str = "auto"

    def stage_steps(self, n_shapes):
        patches = n_shapes * self.patches_per_shape
        return (math.ceil(self.contrastive_epochs * patches / self.contrastive_batch),
                math.ceil(self.regression_epochs * patches / self.regression_batch))


# Small sane defaults for Blender's Train Model button and for tests.
QUICK = dict(points_per_shape=20_000, patches_per_shape=1024, contrastive_epochs=2,
             contrastive_batch=128, regression_epochs=4, regression_batch=128,
             regression_optimizer="adam", regression_lr=1e-3, finetune_encoder=True,
             checkpoint_minutes=2.0)

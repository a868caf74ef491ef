"""Speed benchmark: network patches per second and seconds for a 100K-point cloud,
4 iterations, per preset and backend (untrained weights: speed does not depend on their
values). cli/bench.py prints the table."""
from __future__ import annotations

import os
import time

import numpy as np

from ..config import get_preset
from ..infer import denoise, predictor
from .shapes import sample_shape


def patches_per_second(model, device, batch=1024, seconds=5.0):
    """The network alone (torch or numpy backend) on random patches of the model's size."""
    predict, _, _ = predictor(model, device)
    x = np.random.default_rng(0).normal(size=(batch, model.config.points_per_patch, 3)).astype(np.float32)
    predict(x)                                    # warm-up
    done, t0 = 0, time.time()
    while time.time() - t0 < seconds:
        predict(x)
        done += batch
    return done / (time.time() - t0)


def peak_rss_gib():
    import resource
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20   # Linux: KiB


def machine_line(device_name="auto") -> str:
    from ..options import torch_available

    line = f"{os.cpu_count()} CPU cores, numpy {np.__version__}"
    if torch_available():
        import torch

        from ..device import cpu_bf16_supported, pick_device

        device = pick_device(device_name)
        bf16 = "on" if device.type != "cpu" or cpu_bf16_supported() else "off"
        line += (f"; torch {torch.__version__} on {device}, threads {torch.get_num_threads()}, "
                 f"bf16 autocast {bf16}")
    return line


def bench_cloud(points):
    """The cloud every preset is timed on: a noisy torus."""
    noisy, _, _ = sample_shape("torus", points, noise=0.01, seed=0)
    return noisy


def bench_model(name, backend):
    """An untrained network of a preset for a backend (numpy: the same weights, converted)."""
    import torch

    from ..model import build_model
    from ..numpy_net import NumpyNet

    torch.manual_seed(0)
    model = build_model(get_preset(name)).eval()
    if backend == "numpy":
        return NumpyNet(model.config, {k: v.numpy() for k, v in model.state_dict().items()})
    return model


def bench_preset(name, noisy, iterations=4, device="auto", full=True, backend="torch") -> dict:
    """One table row: network patches/s and (full=True) the seconds of a whole denoise."""
    model = bench_model(name, backend)
    if backend == "numpy":
        device = "cpu"
    rate = patches_per_second(model, device, batch=1024 if name != "paper" else 128)
    row = {"preset": name, "backend": backend, "points_per_patch": model.config.points_per_patch,
           "patches_per_second": rate}
    if full:
        t0 = time.time()
        denoise(noisy, model, iterations=iterations, device=device)
        row.update(seconds=time.time() - t0, peak_gib=peak_rss_gib())
    else:
        row["estimated_seconds"] = len(noisy) * iterations / rate
    return row

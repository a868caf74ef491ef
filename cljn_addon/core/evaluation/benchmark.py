"""Speed benchmark: network patches per second and seconds for a 100K-point cloud,
4 iterations, per preset (untrained weights: speed does not depend on their values).
cli/bench.py prints the table."""
from __future__ import annotations

import os
import time

import torch

from ..config import get_preset
from ..device import autocast, cpu_bf16_supported, pick_device
from ..infer import denoise
from ..model import build_model, inference_net
from .shapes import sample_shape


def patches_per_second(model, device, batch=1024, seconds=5.0):
    net = inference_net(model.to(device).eval())
    x = torch.randn(batch, model.config.points_per_patch, 3, device=device)
    with torch.inference_mode(), autocast(device):
        net(x)                                    # warm-up
        done, t0 = 0, time.time()
        while time.time() - t0 < seconds:
            net(x)
            done += batch
    return done / (time.time() - t0)


def peak_rss_gib():
    import resource
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20   # Linux: KiB


def machine_line(device) -> str:
    bf16 = "on" if device.type != "cpu" or cpu_bf16_supported() else "off"
    return (f"device {device}, {os.cpu_count()} CPU cores, torch {torch.__version__}, threads "
            f"{torch.get_num_threads()}, bf16 autocast {bf16}")


def bench_cloud(points):
    """The cloud every preset is timed on: a noisy torus."""
    noisy, _, _ = sample_shape("torus", points, noise=0.01, seed=0)
    return noisy


def bench_preset(name, noisy, iterations=4, device="auto", full=True) -> dict:
    """One table row: network patches/s and (full=True) the seconds of a whole denoise."""
    torch.manual_seed(0)
    model = build_model(get_preset(name))
    rate = patches_per_second(model, pick_device(device), batch=1024 if name != "paper" else 128)
    row = {"preset": name, "points_per_patch": model.config.points_per_patch, "patches_per_second": rate}
    if full:
        t0 = time.time()
        denoise(noisy, model, iterations=iterations, device=device)
        row.update(seconds=time.time() - t0, peak_gib=peak_rss_gib())
    else:
        row["estimated_seconds"] = len(noisy) * iterations / rate
    return row

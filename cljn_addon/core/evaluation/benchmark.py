"""Speed benchmark: network patches per second and seconds for a 100K-point cloud,
4 iterations, per preset (untrained weights: speed does not depend on their values)."""
from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np
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


def main(argv=None):
    parser = argparse.ArgumentParser(prog="run.py bench", description=__doc__)
    parser.add_argument("--presets", nargs="+", default=["small", "paper"])
    parser.add_argument("--points", type=int, default=100_000)
    parser.add_argument("--iterations", type=int, default=4)
    parser.add_argument("--device", default="auto")
    parser.add_argument("--skip-full", nargs="*", default=["paper"], metavar="PRESET",
                        help="presets timed on the network only (the paper preset's full run takes ~15 min here)")
    args = parser.parse_args(argv)
    device = pick_device(args.device)
    print(f"device {device}, {os.cpu_count()} CPU cores, torch {torch.__version__}, threads "
          f"{torch.get_num_threads()}, bf16 autocast {'on' if device.type != 'cpu' or cpu_bf16_supported() else 'off'}")
    noisy, _, _ = sample_shape("torus", args.points, noise=0.01, seed=0)
    print(f"| preset | points/patch | network patches/s | {args.points // 1000}K points x {args.iterations} iterations |")
    print("|---|---|---|---|")
    for name in args.presets:
        torch.manual_seed(0)
        model = build_model(get_preset(name))
        rate = patches_per_second(model, device, batch=1024 if name != "paper" else 128)
        if name in args.skip_full:
            full = f"~{args.points * args.iterations / rate:.0f} s (network time only, estimated)"
        else:
            t0 = time.time()
            denoise(noisy, model, iterations=args.iterations, device=args.device)
            full = f"{time.time() - t0:.1f} s (peak memory of this process so far {peak_rss_gib():.2f} GiB)"
        print(f"| {name} | {model.config.points_per_patch} | {rate:,.0f} | {full} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The CUDA path (users with NVIDIA GPUs): the same denoise as on the CPU, to bf16's precision.
Skips where torch sees no CUDA device (CI); run on a GPU machine with `pytest tests/test_cuda.py`."""
import numpy as np
import pytest
import torch

from cljn_addon import core
from cljn_addon.core.evaluation.metrics import chamfer
from cljn_addon.core.evaluation.shapes import sample_shape

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")


def test_denoise_on_cuda_matches_the_cpu():
    noisy, clean, _ = sample_shape("stepped_block", 20_000, noise=0.008, seed=4)
    model = core.load_model(None)
    runs = {dev: core.denoise(noisy, model, iterations="auto", orientation="outward", seed=0, device=dev)
            for dev in ("cuda", "cpu")}
    assert "cuda" in runs["cuda"].ran_on and "cpu" in runs["cpu"].ran_on
    cd = {dev: chamfer(r.points, clean) for dev, r in runs.items()}
    assert cd["cuda"] < 0.7 * chamfer(noisy, clean)      # 0.55x here at 20K points
    assert abs(cd["cuda"] - cd["cpu"]) < 0.05 * cd["cpu"], cd
    # Same normals, up to bf16 rounding, and the same outward sign.
    cos = np.einsum("ij,ij->i", runs["cuda"].normals, runs["cpu"].normals)
    assert np.median(cos) > 0.999 and (cos > 0).mean() > 0.995
    # Positions agree point by point to a small share of the noise.
    moved = np.linalg.norm(runs["cuda"].points - runs["cpu"].points, axis=1)
    assert np.median(moved) < 0.1 * 0.008


def test_normals_only_on_cuda_matches_the_cpu():
    noisy, _, _ = sample_shape("box", 20_000, noise=0.006, seed=5)
    model = core.load_model(None)
    runs = {dev: core.estimate_normals(noisy, model, orientation="outward", seed=0, device=dev)
            for dev in ("cuda", "cpu")}
    cos = np.einsum("ij,ij->i", runs["cuda"].normals, runs["cpu"].normals)
    assert np.median(cos) > 0.999 and (cos > 0).mean() > 0.995


def test_training_batches_on_cuda_match_the_cpu_builder():
    """The device batch builder (what `train` uses on a CUDA GPU) draws on the GPU what it draws
    on the CPU: the same shapes, ball statistics and frames (the random streams differ)."""
    import time

    from cljn_addon.core.training.data import load_clean_cloud, make_training_shape
    from cljn_addon.core.training.device_batches import DeviceBatches

    shapes = [make_training_shape(s, *load_clean_cloud(s, 100_000, 5), 128, 0.05, 11)
              for s in ("shape:thin_plate", "shape:box", "shape:star_prism")]
    on = {dev: DeviceBatches(shapes, dev, seed=3) for dev in ("cuda", "cpu")}
    got = {dev: b.regression(1024, 256, b.generator("regression", 0), own_side=True) for dev, b in on.items()}
    for a, b in zip(got["cuda"], got["cpu"]):
        assert a.is_cuda and a.shape == b.shape and a.dtype == b.dtype
    for i in (0, 1):
        mean = {dev: got[dev][i].norm(dim=2).mean().item() for dev in got}
        assert abs(mean["cuda"] / mean["cpu"] - 1) < 0.03, mean
    torch.cuda.synchronize()
    t0 = time.time()
    for step in range(20):
        on["cuda"].regression(1024, 256, on["cuda"].generator("regression", step), own_side=True)
    torch.cuda.synchronize()
    print(f"device batches: {20 * 1024 / (time.time() - t0):,.0f} patches/s")

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

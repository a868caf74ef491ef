"""Device choice and mixed precision, shared by inference and training."""
from __future__ import annotations

import contextlib

import torch

from .config import DEVICE_CHOICES
from .errors import InputError


def pick_device(name: str = "auto") -> torch.device:
    """'auto' takes CUDA, then MPS, then the CPU; 'gpu' takes whichever GPU exists."""
    name = (name or "auto").lower()
    if name not in DEVICE_CHOICES:
        raise InputError(f"unknown device {name!r}; choose one of {', '.join(DEVICE_CHOICES)}")
    has_cuda = torch.cuda.is_available()
    has_mps = getattr(torch.backends, "mps", None) is not None and torch.backends.mps.is_available()
    if name in ("auto", "gpu"):
        if has_cuda:
            return torch.device("cuda")
        if has_mps:
            return torch.device("mps")
        if name == "gpu":
            raise InputError("device 'gpu' was asked for, but neither CUDA nor MPS is available")
        return torch.device("cpu")
    if name == "cuda" and not has_cuda:
        raise InputError("device 'cuda' was asked for, but CUDA is not available")
    if name == "mps" and not has_mps:
        raise InputError("device 'mps' was asked for, but MPS is not available")
    return torch.device(name)


def cpu_bf16_supported() -> bool:
    try:
        return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):
        return False


def autocast(device: torch.device, enabled: bool = True):
    """bf16 autocast on CPUs with native bf16 and on CUDA; fp32 elsewhere (MPS included)."""
    if enabled and device.type == "cpu" and cpu_bf16_supported():
        return torch.autocast("cpu", dtype=torch.bfloat16)
    if enabled and device.type == "cuda" and torch.cuda.is_bf16_supported():
        return torch.autocast("cuda", dtype=torch.bfloat16)
    return contextlib.nullcontext()

"""Choosing the compute device: CUDA, then Apple MPS, then CPU (or what the user names)."""

from __future__ import annotations

import torch

from .errors import NeulfError


def pick_device(name: str | None = None) -> torch.device:
    if name:
        try:
            device = torch.device(name)
        except RuntimeError:
            raise NeulfError(f"unknown device '{name}'; use cpu, cuda, cuda:N or mps.") from None
        if device.type == "cuda" and not torch.cuda.is_available():
            raise NeulfError("CUDA was asked for but this torch build sees no CUDA GPU; use --device cpu.")
        if device.type == "mps" and not torch.backends.mps.is_available():
            raise NeulfError("MPS was asked for but is not available on this machine; use --device cpu.")
        return device
    if torch.cuda.is_available():
        return torch.device("cuda")
    if getattr(torch.backends, "mps", None) is not None and torch.backends.mps.is_available():
        return torch.device("mps")
    return torch.device("cpu")


def describe_device(device: torch.device) -> str:
    if device.type == "cuda":
        return f"cuda ({torch.cuda.get_device_name(device)})"
    if device.type == "cpu":
        return f"cpu ({torch.get_num_threads()} threads)"
    return device.type

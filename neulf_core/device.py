"""Choosing the compute device: CUDA, then Apple MPS, then CPU (or what the user names)."""

from __future__ import annotations

import torch

from .errors import NeulfError

# Device types where torch.autocast takes float16 in every torch this project supports (older
# torch refuses to build an autocast object for MPS at all): half-precision rendering
# (render.PRECISIONS) and the fast field's float32 geometry branch under it.
HALF_DEVICES = ("cuda", "cpu")

# The device types the renderer and training run on (pick_device refuses others).
SUPPORTED_DEVICES = ("cpu", "cuda", "mps")


def pick_device(name: str | None = None) -> torch.device:
    if name:
        try:
            device = torch.device(name)
        except (RuntimeError, TypeError, ValueError):
            raise NeulfError(f"unknown device '{name}'; use cpu, cuda, cuda:N or mps.") from None
        # torch knows more device types (xpu, meta, hpu, ...) than this project renders and
        # trains on; they fail later inside torch with its own words, or give no pixels (meta).
        if device.type not in SUPPORTED_DEVICES:
            raise NeulfError(f"device '{name}' is not supported; use cpu, cuda, cuda:N or mps.")
        if device.type == "cuda" and not torch.cuda.is_available():
            raise NeulfError("CUDA was asked for but this torch build sees no CUDA GPU; use --device cpu.")
        if device.type == "cuda" and device.index is not None and device.index >= torch.cuda.device_count():
            raise NeulfError(f"device '{name}': this machine has {torch.cuda.device_count()} CUDA GPU(s), numbered "
                             "from 0; use cuda, cuda:0 or --device cpu.")
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


# glibc's mallopt parameters (malloc.h) and the values chosen for rendering and training.
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
_MMAP_THRESHOLD = 32 << 20   # glibc's upper limit on 64-bit systems
_TRIM_THRESHOLD = 256 << 20  # the freed heap a process keeps for reuse
_allocator_tuned: bool | None = None


def keep_freed_cpu_memory() -> bool:
    """Let the C allocator reuse the memory a CPU render or training step frees instead of
    handing it back.

    A render's chunks (and training's steps) allocate and free the same few-MB buffers over
    and over.  By default glibc serves such buffers with fresh mmaps or trims them off the
    heap, so every chunk page-faults its buffers in again: 4,000-13,000 faults and about 10 %
    of the CPU time of a 480x270 frame (docs/BENCHMARKS.md).  Buffers up to 32 MB from the
    heap, and up to 256 MB of freed heap kept, make that zero.  Once per process; glibc
    (Linux) only, a no-op elsewhere.  Returns whether the setting is in effect."""
    global _allocator_tuned
    if _allocator_tuned is None:
        _allocator_tuned = _set_glibc_malloc_thresholds()
    return _allocator_tuned


def _set_glibc_malloc_thresholds() -> bool:
    import ctypes
    import platform

    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    # Both at once: setting one alone turns off glibc's adaptive threshold, which is worse.
    return bool(mallopt(_M_MMAP_THRESHOLD, _MMAP_THRESHOLD)) and bool(mallopt(_M_TRIM_THRESHOLD, _TRIM_THRESHOLD))

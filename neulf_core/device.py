"""Choosing the compute device: CUDA, then Apple MPS, then CPU (or what the user names)."""

from __future__ import annotations

import sys
from functools import lru_cache

import torch
import torch.nn.functional as F

from .errors import NeulfError

# Device types where torch.autocast takes float16 in every torch this project supports (older
# torch refuses to build an autocast object for MPS at all): half-precision rendering
# (render.PRECISIONS) and the fast field's float32 geometry branch under it.
HALF_DEVICES = ("cuda", "cpu")

# The device types the renderer and training run on (pick_device refuses others).
SUPPORTED_DEVICES = ("cpu", "cuda", "mps")

# The fields read their textures with grid_sample and border padding, and training needs its
# backward.  Some torch builds lack it on MPS ("MPS: Unsupported Border padding mode") or give
# it wrong there: found by mps_shortfall, before a run fails or trains on wrong gradients.
MPS_SHORTFALL = ("this torch's MPS cannot run grid_sample with border padding (or its gradient) as the CPU does, "
                 "and the light field needs it")
MPS_SHORTFALL_FIX = "use --device cpu, or upgrade torch"


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
        if mps_shortfall(device):
            raise NeulfError(f"{MPS_SHORTFALL}: {MPS_SHORTFALL_FIX}.")
        return device
    if torch.cuda.is_available():
        return torch.device("cuda")
    if getattr(torch.backends, "mps", None) is not None and torch.backends.mps.is_available():
        if not mps_shortfall(torch.device("mps")):
            return torch.device("mps")
        print(f"note: {MPS_SHORTFALL}; using the CPU (upgrade torch to use MPS).", file=sys.stderr)
    return torch.device("cpu")


def mps_shortfall(device: torch.device) -> bool:
    """Whether `device` is MPS and its torch build falls short of what the core asks of it
    (border-padded grid_sample and its backward, as the CPU computes them).  Other devices:
    False.  Probed once per process and device."""
    return device.type == "mps" and _border_sampling_differs_on(str(device))


@lru_cache(maxsize=None)
def _border_sampling_differs_on(name: str) -> bool:
    return border_sampling_differs(torch.device(name))


def border_sampling_differs(device: torch.device, reference: torch.device = torch.device("cpu")) -> bool:
    """Whether a tiny bilinear grid_sample with border padding, forward and backward (to the
    texture and to the grid, as training takes both), fails on `device` or differs there from
    `reference`'s."""
    texture = torch.arange(12, dtype=torch.float32).reshape(1, 1, 3, 4) ** 1.5 / 12
    # Points inside, and outside on either side (where border padding differs from zeros), none
    # exactly on the edge (where the gradient has two right answers).
    grid = torch.tensor([[[[-1.3, -0.2], [0.25, 0.55], [0.7, -0.9]], [[1.4, 1.2], [-0.6, 1.7], [0.1, -1.6]]]])
    upstream = torch.tensor([1.0, -2.0, 0.5, 3.0, -1.5, 2.5]).reshape(1, 1, 2, 3)  # (a gradient of no symmetry)
    try:
        found = [_sampled_and_gradients(texture, grid, upstream, where) for where in (reference, device)]
    except (RuntimeError, NotImplementedError, TypeError):  # what torch raises for an op a device lacks
        return True
    return not all(torch.allclose(a, b, rtol=1e-4, atol=1e-5) for a, b in zip(*found))


def _sampled_and_gradients(texture, grid, upstream, device: torch.device) -> list[torch.Tensor]:
    found = []
    for align_corners in (True, False):  # (the fields' texture reads, the classic plane sweep's)
        # (Copies, fresh each time: a CPU tensor's .to("cpu") is the tensor itself, whose gradient would add up.)
        texture_d, grid_d = (x.to(device, copy=True).requires_grad_() for x in (texture, grid))
        sampled = F.grid_sample(texture_d, grid_d, mode="bilinear", padding_mode="border", align_corners=align_corners)
        (sampled * upstream.to(device)).sum().backward()
        found += [x.detach().cpu() for x in (sampled, texture_d.grad, grid_d.grad)]
    return found


def release_cached_memory() -> None:
    """Hand back the blocks the GPU allocators keep cached (CUDA's and MPS's both keep what a
    failed try freed): after running out of memory, before a smaller try."""
    if torch.cuda.is_available():
        torch.cuda.empty_cache()
    if torch.backends.mps.is_available():
        torch.mps.empty_cache()


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

"""A stand-in for Apple's MPS device in CPU-only tests: float64 on the device fails as it does there.

MPS has no float64: torch refuses to make a float64 tensor on it or to convert one of its
tensors to float64.  CUDA and the CPU take float64, so a `.double()` of a device tensor passes
every test on them and fails for the first Mac user.  No Mac runs the tests, so this stand-in
plays the refusal on the CPU.

The stand-in device is `cpu:0` (STAND_IN): torch runs it as the CPU, but it is named apart from
the plain `cpu` the code brings results back to (`.cpu()`, `.to("cpu")`), so the host and the
device can be told apart.  A TorchFunctionMode follows every torch call made while it is on:

- a call's results are on the device when the call names `cpu:0` (a factory's `device=`,
  `.to(...)`) or takes a tensor on the device (a parameter moved by `Module.to` counts), unless
  the call itself brings them to the host;
- a float64 result on the device raises TypeError with MPS's words (MPS_FLOAT64), and so does
  `.numpy()` of a device tensor, as on any accelerator.

What it cannot see: tensors made inside torch's C++ (autograd's gradients, torch.load's
map_location) are on the device to it only once a traced call takes or makes them.
"""

from __future__ import annotations

import weakref

import torch
from torch.overrides import TorchFunctionMode
from torch.utils._pytree import tree_flatten

STAND_IN = torch.device("cpu", 0)
HOST = torch.device("cpu")
# torch's words on MPS (aten/src/ATen/mps), so a test's failure reads like the Mac user's.
MPS_FLOAT64 = ("Cannot convert a MPS Tensor to float64 dtype as the MPS framework doesn't support float64. "
               "Please use float32 instead.")
NOT_ON_HOST = "can't convert mps:0 device type tensor to numpy. Use Tensor.cpu() to copy the tensor to host memory first."


def _tensors(tree) -> list[torch.Tensor]:
    leaves, _ = tree_flatten(tree)
    return [leaf for leaf in leaves if isinstance(leaf, torch.Tensor)]


def _as_device(value) -> torch.device | None:
    if isinstance(value, torch.device):
        return value
    if isinstance(value, str):
        try:
            return torch.device(value)
        except RuntimeError:
            return None
    return None


class MpsLike(TorchFunctionMode):
    """`with MpsLike() as mode:` code run on device STAND_IN meets float64 refused as on MPS.

    `refused` lists the refusals' calls (a test can check one was made when code catches it)."""

    def __init__(self):
        super().__init__()
        self._on_device: dict[int, weakref.ref] = {}
        self.refused: list[str] = []
        self.device_results = 0  # results it saw on the device (none: the code never used the stand-in)

    # ------------------------------------------------------------------ which tensors are on the device

    def is_on_device(self, tensor: torch.Tensor) -> bool:
        ref = self._on_device.get(id(tensor))
        return ref is not None and ref() is tensor

    def _mark(self, tensor: torch.Tensor) -> None:
        key = id(tensor)

        def forget(ref, key=key):  # (only its own entry: the id may be another tensor's by now)
            if self._on_device.get(key) is ref:
                del self._on_device[key]

        self._on_device[key] = weakref.ref(tensor, forget)

    def _destination(self, func, args, kwargs) -> str | None:
        """"device", "host" or None (where the inputs are) for the results of `func`."""
        if func is torch.Tensor.cpu:
            return "host"
        named = [kwargs.get("device")]
        if func is torch.Tensor.to:
            named += list(args[1:]) + [kwargs.get("other")]
        for value in named:
            if isinstance(value, torch.Tensor):  # .to(other): where `other` is
                return "device" if self.is_on_device(value) else "host"
            device = _as_device(value)
            if device is not None:
                return "device" if device == STAND_IN else "host"
        return None

    # ------------------------------------------------------------------ the refusals

    def _refuse(self, func, message: str):
        self.refused.append(getattr(func, "__name__", str(func)))
        raise TypeError(message)

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        inputs_on_device = any(self.is_on_device(t) for t in _tensors((args, kwargs)))
        if func in (torch.Tensor.numpy, torch.Tensor.__array__) and inputs_on_device:
            self._refuse(func, NOT_ON_HOST)
        result = func(*args, **kwargs)
        destination = self._destination(func, args, kwargs) or ("device" if inputs_on_device else "host")
        if destination == "host":
            if args and result is args[0] and self.is_on_device(result):
                # On the CPU `.cpu()` hands back the tensor itself: a host alias keeps the two apart.
                result = result.view_as(result)
            return result
        for tensor in _tensors(result):
            if tensor.dtype == torch.float64:
                self._refuse(func, MPS_FLOAT64)
            self._mark(tensor)
            self.device_results += 1
        if func is torch.Tensor.to and isinstance(args[0], torch.nn.Parameter):
            self._mark(args[0])  # Module.to keeps the parameter and swaps its data for the moved copy
        return result

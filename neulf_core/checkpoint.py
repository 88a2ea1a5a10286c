"""Model folders and checkpoints: written atomically, checked on load.

MODEL_DIR/checkpoint.pt holds everything to render and to resume (float32 weights, slab,
optimizer and random state, progress); MODEL_DIR/model.pt is the render-only copy to ship
(feature grids as 8-bit codes, other large weights as float16, no optimizer state: 1.6 MB
for the default field at 480x270 against a 19 MB checkpoint); MODEL_DIR/model.json is the same metadata
for people and other programs (no weights).  All are written to a temporary file in the same
folder and renamed over the old one, so a crash or SIGKILL mid-write leaves the previous
files intact.
"""

from __future__ import annotations

import io
import json
import shlex
import zipfile
from pathlib import Path

import torch

from .errors import NeulfError
from .files import atomic_write_bytes
# (the names and readers live in the torch-free model_files; they are imported from here too)
from .model_files import (CHECKPOINT_FORMAT, CHECKPOINT_NAME, METADATA_NAME, MODEL_NAME,  # noqa: F401
                          read_metadata, render_path)

FORMAT = CHECKPOINT_FORMAT
VERSION = 1
MODEL_FORMAT = "neulf-model"
# Tensors smaller than this stay float32 in model.pt: the decoders are a few kB, and their
# rounding would be the only fp16 error that reaches the colour without interpolation.
HALF_MIN_ELEMENTS = 4096
# Feature grids (tensors of 3 or more dimensions: textures, planes, layers; any size) go into
# model.pt as 8-bit codes with a per-channel offset and step: their values are interpolated before a
# decoder reads them, and 255 levels per channel cost 0.0003-0.009 dB of held-out PSNR
# (docs/BENCHMARKS.md), for half the bytes of float16.  Matrices (the MLP presets' layers)
# stay float16: a rounding error there reaches every output.
GRID_MIN_DIMS = 3
# The field's weights before the unseen texels were filled at the end of a run: what a
# resumed run trains on (train._train); "state_dict" holds them filled, for rendering.
TRAINING_STATE_KEY = "state_dict_before_fill"
NOT_FOR_RENDERING = ("state_dict", "optimizer", "rng", TRAINING_STATE_KEY)


def _torch_bytes(obj) -> bytes:
    buffer = io.BytesIO()
    torch.save(obj, buffer)
    return buffer.getvalue()


def save_checkpoint(model_dir: Path, payload: dict) -> Path:
    """checkpoint.pt, then model.pt, then model.json: a crash in between leaves the
    checkpoint the newer file, and loading for rendering then takes it (render_path)."""
    payload = {"format": FORMAT, "version": VERSION, **payload}
    path = Path(model_dir) / CHECKPOINT_NAME
    atomic_write_bytes(path, _torch_bytes(payload))
    save_render_model(model_dir, payload)
    _write_metadata(model_dir, payload)
    return path


def _write_metadata(model_dir: Path, payload: dict) -> None:
    metadata = {k: v for k, v in payload.items() if k not in NOT_FOR_RENDERING}
    atomic_write_bytes(Path(model_dir) / METADATA_NAME, json.dumps(metadata, indent=2, default=_json_value).encode())


def restore_metadata(model_dir: Path) -> bool:
    """model.json written again from checkpoint.pt where it is missing or cannot be read (deleted,
    damaged, edited); True if it was.  Its readers without torch (Blender's Python) take a model's
    progress from it: Train had read a damaged one as step 0, and added its budget to that."""
    model_dir = Path(model_dir).expanduser()
    if read_metadata(model_dir) or not (model_dir / CHECKPOINT_NAME).is_file():
        return False
    _write_metadata(model_dir, load_checkpoint(model_dir))
    return True


def _json_value(value) -> str:
    """model.json's text for what JSON cannot hold: a tensor (the pose corrections, the photos'
    colour transforms) is named by its shape, not printed -- torch's print shortens large ones
    with "...", which read as the values; the values are in model.pt and checkpoint.pt."""
    if isinstance(value, torch.Tensor):
        return f"tensor of shape {list(value.shape)} (in model.pt)"
    return str(value)


def half_state_dict(state_dict: dict) -> dict:
    """Large float tensors as float16 (planes and MLP layers: half the bytes, no measurable
    PSNR cost, docs/BENCHMARKS.md); small ones, non-float ones, and any that float16 would
    overflow stay as they are."""
    out = {}
    for name, tensor in state_dict.items():
        tensor = tensor.detach().cpu()
        if tensor.is_floating_point() and tensor.numel() >= HALF_MIN_ELEMENTS:
            half = tensor.to(torch.float16)
            if bool(torch.isfinite(half).all()) or not bool(torch.isfinite(tensor).all()):
                tensor = half
        out[name] = tensor
    return out


def quantise_grid(tensor: torch.Tensor) -> dict:
    """8-bit codes of a feature grid (B, C, ...) with one offset and step per (B, C) channel."""
    tensor = tensor.detach().float().cpu()
    spatial = tuple(range(2, tensor.dim()))
    offset, top = tensor.amin(dim=spatial, keepdim=True), tensor.amax(dim=spatial, keepdim=True)
    step = (top - offset).clamp_min(1e-12) / 255.0
    codes = torch.round((tensor - offset) / step).clamp(0, 255).to(torch.uint8)
    return {"codes": codes, "offset": offset, "step": step}


def dequantise_grid(entry: dict) -> torch.Tensor:
    return entry["codes"].float() * entry["step"] + entry["offset"]


def compact_state_dict(state_dict: dict) -> tuple[dict, dict]:
    """What model.pt stores: (state_dict with float16 and float32 tensors, {name: 8-bit grid})."""
    grids = {name: quantise_grid(tensor) for name, tensor in state_dict.items()
             if tensor.is_floating_point() and tensor.dim() >= GRID_MIN_DIMS and bool(torch.isfinite(tensor).all())}
    dense = half_state_dict({name: tensor for name, tensor in state_dict.items() if name not in grids})
    return dense, grids


def save_render_model(model_dir: Path, payload: dict) -> Path:
    """MODEL_DIR/model.pt: what rendering needs (metadata, 8-bit grids, float16 weights), no optimizer."""
    model = {k: v for k, v in payload.items() if k not in NOT_FOR_RENDERING}
    dense, grids = compact_state_dict(payload["state_dict"])
    model.update(format=MODEL_FORMAT, version=VERSION, state_dict=dense, grids=grids)
    path = Path(model_dir) / MODEL_NAME
    atomic_write_bytes(path, _torch_bytes(model))
    return path


def remove_stale_temporaries(model_dir: Path) -> None:
    """Delete half-written files a killed training left (atomic_write_bytes's temporaries);
    called only while holding the folder's training lock, so no writer is active."""
    for leftover in Path(model_dir).glob(".*.tmp"):
        leftover.unlink(missing_ok=True)


def checkpoint_path(model_dir: Path) -> Path:
    model_dir = Path(model_dir).expanduser()
    if model_dir.is_file():
        return model_dir
    return model_dir / CHECKPOINT_NAME


def saved_scene_record(model_dir) -> dict | None:
    """model.json's record of the scene a model trained on (its photos' folder and sizes), or None."""
    return read_metadata(model_dir).get("scene")


def load_checkpoint(model_dir: Path, map_location="cpu") -> dict:
    """The full checkpoint (for resuming)."""
    path = checkpoint_path(model_dir)
    payload = _read(path, model_dir, map_location)
    if payload.get("format") == MODEL_FORMAT:
        raise NeulfError(f"{model_dir} is a render-only model file (no optimizer state); resuming needs its {CHECKPOINT_NAME}.")
    problem = (what_is_missing(payload, RENDER_FIELDS) or what_is_missing(payload, RESUME_FIELDS)
               or _slab_problem(payload["slab"]) or _progress_problem(payload["progress"])
               or (None if isinstance(payload["scene"].get("fingerprint"), str) else "its scene has no fingerprint")
               or _weights_problem(payload, ("state_dict", TRAINING_STATE_KEY)))
    if problem:
        raise damaged_checkpoint(path, problem)
    return payload


def damaged_checkpoint(path: Path, problem: str) -> NeulfError:
    """The one-line message for a checkpoint that cannot be resumed, saying what is wrong in it."""
    # (deleting checkpoint.pt alone would leave model.pt, which a new training refuses to overwrite)
    return NeulfError(f"the checkpoint {path} is damaged ({problem}); restore it from a backup, or train into "
                      f"another --out folder (or delete {path.name} and {MODEL_NAME} there) to start again.")


def load_for_render(model_dir: Path, map_location="cpu") -> dict:
    """model.pt or checkpoint.pt (see render_path); either has the metadata and state_dict
    (model.pt's 8-bit grids are decoded here; its float16 tensors load_state_dict converts
    to float32 once)."""
    path = render_path(model_dir)
    payload = _read(path, model_dir, map_location)
    grids = payload.pop("grids", None) or {}
    problem = what_is_missing(payload, RENDER_FIELDS) or _slab_problem(payload["slab"])
    if not problem:
        try:
            payload["state_dict"].update({name: dequantise_grid(entry) for name, entry in grids.items()})
            problem = _weights_problem(payload, ("state_dict",))
        except (KeyError, TypeError, AttributeError, RuntimeError) as exc:
            problem = f"{type(exc).__name__}: {exc}"
    if problem:
        remedy = (f"delete {MODEL_NAME} to render from {CHECKPOINT_NAME}, or train again" if path.name == MODEL_NAME
                  and (path.parent / CHECKPOINT_NAME).is_file() else "restore it from a backup, or train again")
        raise NeulfError(f"the model file {path} is damaged ({problem}); {remedy}.")
    return payload


# What a checkpoint must hold, and of which type, for rendering, and on top for resuming: a
# checkpoint edited or damaged by hand had stopped in a KeyError or TypeError deep inside the
# renderer or the trainer.
RENDER_FIELDS = {"field": str, "field_config": dict, "slab": dict, "state_dict": dict, "scene": dict}
RESUME_FIELDS = {"train_config": dict, "progress": dict, "optimizer": dict}
# Entries that may be absent, but are read as dicts where present.
OPTIONAL_DICTS = ("rig", "pose_check", "members_rule", "autosize")


def what_is_missing(payload: dict, fields: dict) -> str | None:
    """Which of `fields` (name: type) `payload` lacks or holds as another type, in words; None if none."""
    for name, kind in fields.items():
        if name not in payload:
            return f"it has no {name!r}"
        if not isinstance(payload[name], kind):
            return f"its {name!r} is a {type(payload[name]).__name__}, not a {kind.__name__}"
    for name in OPTIONAL_DICTS:
        if payload.get(name) is not None and not isinstance(payload[name], dict):
            return f"its {name!r} is a {type(payload[name]).__name__}, not a dict"
    return None


def _slab_problem(slab: dict) -> str | None:
    """Why the checkpoint's light slab cannot be read back, or None."""
    from .slab import Slab

    try:
        Slab.from_dict(slab)
    except (TypeError, ValueError) as exc:
        return f"its light slab cannot be read ({type(exc).__name__}: {exc})"
    return None


def _progress_problem(progress: dict) -> str | None:
    """What is wrong with a checkpoint's progress record (the step, time and history a resume goes on from)."""
    step, elapsed = progress.get("step"), progress.get("elapsed")
    if isinstance(step, bool) or not isinstance(step, int) or step < 0:
        return f"its step is {step!r}, not a count of steps"
    if isinstance(elapsed, bool) or not isinstance(elapsed, (int, float)):
        return f"its training time is {elapsed!r}, not a number of seconds"
    if not isinstance(progress.get("history"), list):
        return "its progress has no history list"
    return None


def _weights_problem(payload: dict, keys: tuple[str, ...]) -> str | None:
    """Which weights are not tensors, or not finite (NaN or infinite: a diverged training, or a
    damaged file): rendered, they had made a black picture and NaN depth without a word, and a
    resume had failed in an IndexError.  A trained field's weights are all finite (the fields
    hold no infinite parameters or buffers)."""
    for key in keys:
        weights = payload.get(key)
        if weights is None and key != "state_dict":
            continue  # (a checkpoint without the weights before the fill)
        if not isinstance(weights, dict):
            return f"its {key!r} is not a dict of weights"
        for name, tensor in weights.items():
            if not isinstance(tensor, torch.Tensor):
                return f"its weight {name} is a {type(tensor).__name__}, not a tensor"
            if tensor.is_floating_point() and not bool(torch.isfinite(tensor).all()):
                return (f"its weight {name} holds NaN or infinite values: the training that wrote it diverged, "
                        "or the file was damaged")
    return None


def _beside_its_checkpoint(path: Path) -> bool:
    """Whether `path` is a model.pt with a checkpoint.pt beside it (the training state survives:
    model.pt is only its render copy, so starting again would throw the training away)."""
    return path.name == MODEL_NAME and (path.parent / CHECKPOINT_NAME).is_file()


def _damaged_member(path: Path) -> str | None:
    """What is wrong inside the checkpoint's zip (a member whose CRC fails, or one zipfile cannot
    read at all), or None: torch.load does not check the CRCs, so flipped bytes inside the
    weights would otherwise load silently."""
    try:
        with zipfile.ZipFile(path) as archive:
            member = archive.testzip()
    except (zipfile.BadZipFile, OSError, EOFError, ValueError):
        return None  # not a readable zip at all: torch.load reports it below
    except (NotImplementedError, RuntimeError) as exc:
        # (flipped bytes in a member's header read as another zip version, a compression or an
        # encryption: zipfile's NotImplementedError had escaped as a traceback)
        return f"a member cannot be read ({exc})"
    return f"{member} fails its checksum" if member else None


def _read(path: Path, model_dir: Path, map_location) -> dict:
    if not Path(model_dir).expanduser().exists():
        raise NeulfError(f"model folder {model_dir} does not exist; train one with: python -m neulf_core train SCENE --out "
                         f"{shlex.quote(str(model_dir))}")
    if not path.is_file():
        from .lock import training_holder

        holder = training_holder(model_dir)
        if holder is not None:  # (its first checkpoint is still to come)
            raise NeulfError(f"{model_dir} is being trained (process {holder['pid']}) and has no checkpoint yet: wait "
                             "for its first one (every 60 s by default), then render it.")
        if any((Path(model_dir) / name).exists() for name in ("sparse", "images", "poses_bounds.npy")):
            raise NeulfError(f"{model_dir} is a scene folder (photos and camera poses), not a model: give the model "
                             f"folder training wrote (train's --out), or train one with: python -m neulf_core train "
                             f"{shlex.quote(str(model_dir))} --out MODEL_DIR")
        raise NeulfError(f"{model_dir} holds no trained model ({CHECKPOINT_NAME} missing); train one with: python -m "
                         f"neulf_core train SCENE --out {shlex.quote(str(model_dir))}")
    if Path(model_dir).expanduser().is_file() and path.suffix.lower() != ".pt" and not zipfile.is_zipfile(path):
        # (a photo or poses_bounds.npy given by mistake: not a damaged checkpoint to delete)
        raise NeulfError(f"{path} is not a NeuLF model: give the model folder training wrote (train's --out), or its "
                         f"{MODEL_NAME} or {CHECKPOINT_NAME}.")
    damaged = _damaged_member(path)
    try:
        if damaged:
            raise ValueError(damaged)
        payload = torch.load(path, map_location=map_location, weights_only=False)
    except PermissionError:  # (a file we may not read is not a damaged one: deleting it would lose a good model)
        raise NeulfError(f"cannot read {path}: permission denied; give your account read access to it (for example: "
                         f"chmod u+r {shlex.quote(str(path))}), or run as the user who trained it.") from None
    except Exception as exc:
        remedy = (f"restore it from a backup, or delete {path.name} (or train into another --out) to start again"
                  if not _beside_its_checkpoint(path) else
                  f"delete it: rendering then reads {CHECKPOINT_NAME} beside it, and training writes it again")
        what = "model file" if path.name == MODEL_NAME else "checkpoint"
        raise NeulfError(
            f"the {what} {path} is truncated or corrupted ({type(exc).__name__}{': ' + damaged if damaged else ''}); "
            f"{remedy}."
        ) from None
    if not isinstance(payload, dict) or payload.get("format") not in (FORMAT, MODEL_FORMAT):
        raise NeulfError(f"{path} is not a NeuLF checkpoint.")
    if payload.get("version") != VERSION:
        raise NeulfError(
            f"{path} was written by another version of neulf_core (checkpoint version {payload.get('version')}, "
            f"this one reads {VERSION}); retrain the model with this version."
        )
    return payload

"""What a model folder holds, by name, and the two questions every reader asks of it: which
file a render loads, and what model.json says.  Torch-free, so Blender's own Python (which
has no torch) answers them as the core does: a reader deciding for itself had refused the
render-only model (model.pt alone) the core renders.

MODEL_DIR/checkpoint.pt  everything to render and to resume (checkpoint.py writes it)
MODEL_DIR/model.pt       the render-only copy to ship
MODEL_DIR/model.json     the metadata, for people and other programs (no weights)
MODEL_DIR/members.json, MODEL_DIR/members/N/  a model of several members (members.py)
"""

from __future__ import annotations

import json
from pathlib import Path

CHECKPOINT_NAME = "checkpoint.pt"
METADATA_NAME = "model.json"
MODEL_NAME = "model.pt"
CHECKPOINT_FORMAT = "neulf-checkpoint"  # the "format" of checkpoint.pt, and of model.json beside it


def render_path(model_dir) -> Path:
    """The file to render from: model.pt, unless checkpoint.pt is newer (a crash between
    the two writes, or a checkpoint replaced by hand) or model.pt is missing."""
    model_dir = Path(model_dir).expanduser()
    if model_dir.is_file():
        return model_dir
    small, full = model_dir / MODEL_NAME, model_dir / CHECKPOINT_NAME
    if small.is_file() and (not full.is_file() or small.stat().st_mtime_ns >= full.stat().st_mtime_ns):
        return small
    return full


def has_render_model(model_dir) -> bool:
    """Whether the folder holds a model to render (its checkpoint, or model.pt alone)."""
    return render_path(model_dir).is_file()


def can_resume(model_dir) -> bool:
    """Whether training can continue the folder's model (model.pt alone cannot: no optimizer state)."""
    return (Path(model_dir).expanduser() / CHECKPOINT_NAME).is_file()


def read_metadata(model_dir) -> dict:
    """model.json as a dict, or {} where there is none readable (a new folder, one a user tidied)."""
    try:
        metadata = json.loads((Path(model_dir).expanduser() / METADATA_NAME).read_text())
    except (OSError, ValueError):
        return {}
    return metadata if isinstance(metadata, dict) and well_formed(metadata) else {}


def foreign_metadata(model_dir) -> bool:
    """Whether the folder holds a model.json no NeuLF training wrote (another program's -- a
    TensorFlow.js model, say -- or one damaged past reading).  A new training into the folder
    would replace it: the file is the user's, so the folder is refused instead.  (Our own
    model.json is rewritten from the checkpoint beside it; this asks of a folder without one.)"""
    path = Path(model_dir).expanduser() / METADATA_NAME
    if not path.is_file():
        return False
    try:
        metadata = json.loads(path.read_text())
    except (OSError, ValueError):
        return True
    return not (isinstance(metadata, dict) and metadata.get("format") == CHECKPOINT_FORMAT)


# model.json's entries that its readers take as dicts.
DICT_ENTRIES = ("train_config", "scene", "progress", "members_rule", "pose_check", "starts", "rig", "slab")


def well_formed(metadata: dict) -> bool:
    """Whether model.json's entries have the types its readers expect.  One edited or damaged by
    hand (a "scene" that is a string, photo sizes that are not pairs) is read as none at all,
    as an unreadable one is: it is only a copy of the checkpoint's metadata for people and other
    programs, the checkpoint holds the truth (resuming checks the photos against it), and the
    next checkpoint writes it again.  (Its readers had stopped in an AttributeError.)"""
    if any(metadata.get(name) is not None and not isinstance(metadata[name], dict) for name in DICT_ENTRIES):
        return False
    scene = metadata.get("scene") or {}
    sizes = scene.get("photo_sizes")
    return (isinstance(scene.get("images"), (str, type(None)))
            and (sizes is None or isinstance(sizes, dict) and all(_is_size(size) for size in sizes.values())))


def _is_size(size) -> bool:
    return (isinstance(size, list) and len(size) == 2
            and all(isinstance(n, int) and not isinstance(n, bool) and n > 0 for n in size))

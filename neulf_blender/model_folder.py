"""A scene's model folder as Blender sees it: its path (stored relative to the .blend, read
relative to it or to a linked scene's library), whether it holds a model to render, the panel's
status line from its model.json, and attaching one to a scene.  What a folder holds is the
core's answer (neulf_core.model_files), never decided here."""

from __future__ import annotations

import os
from pathlib import Path

import bpy

from . import capture, tasks
from .jobs import pose_text
from .preferences import get_core
from ..neulf_core.errors import NeulfError
from ..neulf_core.lock import training_holder
from ..neulf_core.members import member_dir, member_folders, read_state
from ..neulf_core.model_files import METADATA_NAME, can_resume, foreign_metadata, has_render_model, read_metadata


DEFAULT_MODEL_NAME = "neulf_model"  # (Train's folder inside the capture's where the Model field is empty)
RENDER_ONLY = "a render-only model (model.pt without its checkpoint.pt): it renders; to train, choose another folder"


def abspath(path: str, library=None) -> str:
    """A '//' path made absolute: relative to the open .blend, or to `library`'s file for data
    linked from it (a linked scene's model sits beside the file it was saved in)."""
    return os.path.normpath(bpy.path.abspath(path, library=library)) if path else ""


def chosen_path(path: str) -> str:
    """abspath for a path an operator is given: a '//' path in a .blend never saved has no folder
    to be relative to (Blender leaves it relative to its working folder, where a model had been
    trained and then lost its link), so it is refused, as is any other relative path."""
    full = abspath(path)
    if full and not os.path.isabs(full):
        if path.startswith("//"):
            raise NeulfError(f"'{path}' is relative to the .blend, which is not saved yet: save the .blend first, or "
                             "choose the folder in the file browser.")
        raise NeulfError(f"'{path}' is not a full path (it would be read from Blender's working folder): choose the "
                         "folder in the file browser.")
    return full


def scene_model_dir(scene) -> str:
    """The scene's model folder, absolute ("" where it has none)."""
    return abspath(scene.neulf.model_dir, scene.library)


def is_model_of(scene, path: str) -> bool:
    """Whether `path` (absolute) is the scene's model folder."""
    return bool(scene.neulf.model_dir) and scene_model_dir(scene) == os.path.normpath(path)


def refuse_linked(scene, what: str) -> None:
    """Linked data cannot be changed for good (the library's file holds it): said, not half done."""
    if scene.library is not None:
        raise NeulfError(f"the scene {scene.name} is linked from {abspath(scene.library.filepath)}: "
                         f"{what} in that file (or make the scene local: Object > Relations > Make Local).")


def model_dir(scene) -> str:
    path = scene_model_dir(scene)
    if not path:
        default = default_model_dir(scene)
        if default and has_render_model(default):  # (the capture imported into a second scene: Train continues it)
            raise NeulfError(f"no NeuLF model in this scene; the capture's folder holds one, {default}: Load Model "
                             "it to render here (Train would continue it).")
        raise NeulfError("no NeuLF model: train one (Train NeuLF) or load a model folder (Load Model).")
    if not Path(path).is_dir():
        raise NeulfError(f"the model folder {path} does not exist: move a .blend together with its model folder, "
                         "or point Load Model at the model.")
    if not has_render_model(path):
        if training_holder(path) is not None:  # (this Blender's Train, or another process's)
            raise NeulfError(f"the training of {path} has not saved its first checkpoint yet (it saves every minute): "
                             "render once it has, or press Cancel, which saves it now.")
        raise NeulfError(f"{path} holds no trained model (neither checkpoint.pt nor model.pt); train it or load "
                         "another folder.")
    return path


def default_model_dir(scene) -> str:
    """Where Train puts a scene's model when its Model field is empty: inside the capture's folder
    ("" for a scene with no capture)."""
    scene_dir = abspath(scene.neulf.scene_dir, scene.library)
    return str(Path(scene_dir) / DEFAULT_MODEL_NAME) if scene_dir else ""


def store_path(path: str) -> str:
    """Relative to the .blend when it is saved (so moving both keeps the link)."""
    if bpy.data.filepath:
        try:
            return bpy.path.relpath(path)
        except ValueError:  # another drive on Windows
            return path
    return path


def progress_text(progress: dict) -> str:
    """One line for the panel from model.json's progress: where the model is and what Train does next."""
    status, step = progress.get("status", "?"), progress.get("step", "?")
    if status == "finished":
        return f"finished at step {step}"
    if status == "cancelled":
        return f"stopped at step {step} (checkpoint saved); Train continues it"
    if status == "training":  # the last periodic checkpoint: its process ended without the final save
        return f"interrupted at step {step} (last checkpoint); Train continues it"
    return f"{status} at step {step}"


def saved_progress_text(path: str, meta: dict) -> str:
    """progress_text of the model folder `path` (its model.json `meta`): the first member's, or,
    where a later member is unfinished (training stopped in it), that member's -- the first's
    "finished" had read as nothing left to train."""
    try:
        state = read_state(Path(path))
    except NeulfError as exc:  # (a damaged members.json: the panel says so, as render and Train will)
        return str(exc)
    if state and state["count"] > 1 and meta.get("progress", {}).get("status") == "finished":
        finished = {int(m) for m in state.get("finished", [])}
        for member in range(2, state["count"] + 1):
            if member not in finished:
                progress = read_metadata(member_dir(path, member)).get("progress")
                where = progress_text(progress) if progress else "not started; Train continues it"
                return f"member {member} of {state['count']} {where}"
    return progress_text(meta.get("progress", {}))


def model_status(path: str, meta: dict) -> str:
    """saved_progress_text, and the pose corrections where the model has them."""
    return saved_progress_text(path, meta) + pose_text(meta.get("pose_corrections"))


TRAINED_ELSEWHERE = "being trained by another process"  # how the panel's line starts (see below)


def trained_elsewhere_text(owner: dict, progress: dict) -> str:
    """The panel's line while another process (a training an earlier Blender started, or one
    from a terminal) trains the model folder: Train would be refused until it stops."""
    at = f" at step {progress['step']}" if "step" in progress else ""
    return f"{TRAINED_ELSEWHERE} (pid {owner['pid']} on {owner['host']}){at}; when it stops, Train continues it"


def model_not_found(path: str) -> str:
    """The start of the status of a scene whose model folder `path` has gone."""
    return f"model folder not found: {path};"


def refresh_model_status(scene) -> str:
    """The scene's `last_status` (shown in the panel) from its model folder, e.g. when a .blend
    is opened after Blender quit during training: the folder, not the .blend, knows how far
    training got.  Returns the status line."""
    props = scene.neulf
    if not props.model_dir:
        return props.last_status
    path = scene_model_dir(scene)
    training = tasks.get("train")
    if training is not None and training.running and is_model_of(scene, training.model_dir):
        return props.last_status  # this session's own job reports its progress
    if not Path(path).is_dir():
        props.last_status = f"{model_not_found(path)} move it back or use Load Model"
        return props.last_status
    meta = read_metadata(path)
    owner = training_holder(path)
    if owner is not None:  # e.g. the .blend reopened while the training Blender left behind saves
        props.last_status = trained_elsewhere_text(owner, meta.get("progress", {}))
        from .handlers import watch_other_trainings  # (handlers imports this module)

        watch_other_trainings()  # the panel follows it and says when it has stopped
        return props.last_status
    if not meta or not has_render_model(path):
        props.last_status = f"no checkpoint in {path} yet; Train starts the model"
        return props.last_status
    if not can_resume(path):  # (the core renders it, and refuses to train over it)
        props.last_status = RENDER_ONLY
        return props.last_status
    progress = meta.get("progress", {})
    props.last_status = model_status(path, meta)
    if progress.get("val_psnr") is not None:
        props.last_psnr = float(progress["val_psnr"])
    return props.last_status


def restore_metadata(context, path: str) -> str:
    """Where the model's model.json (or a member's) is missing or damaged beside its checkpoint,
    the core writes it again from checkpoint.pt: Blender's Python, which cannot read the
    checkpoint (no torch), takes the model's progress from it -- Train had read a damaged one
    as step 0 and trained only what was left of the new budget.  A line saying so, or ""."""
    if not path.strip() or training_holder(path) is not None or not _metadata_lost(path):
        return ""  # (a training writes it at its next checkpoint)
    written = get_core(context).call("restore_metadata", model_dir=path)
    return (f"model.json was missing or damaged: written again from checkpoint.pt in {', '.join(written)}"
            if written else "")


def _metadata_lost(path: str) -> bool:
    try:
        state = read_state(Path(path))
    except NeulfError:
        return False  # (members.json damaged: rendering and Train say so)
    return any(can_resume(folder) and not read_metadata(folder) for folder in member_folders(Path(path), state))


def readable_model(context, path: str) -> dict:
    """model.json of the model folder `path`, which the scene can take; else a NeulfError."""
    refuse_linked(context.scene, "load its model")
    if not path.strip():
        raise NeulfError("choose the model folder (the one training wrote, holding model.json).")
    meta = read_metadata(path)
    if not can_resume(path) and foreign_metadata(path):  # (another program's model.json: Train would replace it)
        meta = {}
    if not meta:
        if (Path(path) / METADATA_NAME).is_file():
            raise NeulfError(f"{path}/model.json cannot be read (damaged or not a NeuLF model's): copy the model "
                             "folder again from where it came, or train a new model into another folder.")
        if training_holder(path) is not None:
            raise NeulfError(f"the training of {path} has not saved its first checkpoint yet (it saves every minute): "
                             "load it once it has.")
        raise NeulfError(f"{path} holds no NeuLF model (model.json missing).")
    return meta


def attach_model(context, path: str) -> dict:
    """Store the model folder (relative to the .blend) and show its slab."""
    meta = readable_model(context, path)
    props = context.scene.neulf
    props.model_dir = store_path(path)
    progress = meta.get("progress", {})
    if progress.get("val_psnr") is not None:
        props.last_psnr = float(progress["val_psnr"])
    props.last_status = RENDER_ONLY if has_render_model(path) and not can_resume(path) else model_status(path, meta)
    collection, root = capture.find_capture(context.scene)
    fingerprint = meta.get("scene", {}).get("fingerprint")
    if collection is not None and meta.get("slab") and fingerprint in (None, props.fingerprint):
        capture.set_slab_planes(collection, root, meta["slab"])
    return meta


def scenes_of_model(path: str) -> list:
    """The open file's scenes whose model folder is `path`."""
    return [scene for scene in bpy.data.scenes if scene.library is None and is_model_of(scene, path)]

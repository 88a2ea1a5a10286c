"""Application handlers.  On save, each scene's folders (capture, images, model) are written
relative to where the .blend is saved: Save As into another folder, or a first save of a file
that imported and trained before it had a place, keeps them pointing at the same folders (and
moving the .blend together with them keeps the link).  On file load, each scene's training
status is read again from its model folder: after Blender quit (or crashed) while training, the .blend holds whatever it
had when it was saved, while the model folder's model.json holds the progress of the last
checkpoint.  The panel then says how far the model got, and Train continues it.  Where another
process still trains the folder (the training an earlier Blender left behind, saving its last
steps), a timer re-reads the status until that process has stopped."""

import os

import bpy
from bpy.app.handlers import persistent

from .model_folder import TRAINED_ELSEWHERE, abspath, refresh_model_status, store_path

PATH_PROPERTIES = ("scene_dir", "images_dir", "model_dir")
_saving: dict = {}  # (scene, property) -> absolute folder, from save_pre to save_post


def relative_to(path: str, blend_file: str) -> str:
    """`path` as Blender's '//' path relative to the folder of `blend_file` (absolute where
    none exists: another drive on Windows)."""
    try:
        relative = os.path.relpath(path, os.path.dirname(os.path.abspath(blend_file)))
    except ValueError:
        return path
    return "//" + relative.replace(os.sep, "/")


@persistent
def on_save_pre(filepath="", *_args):
    """The folders as the file being written sees them (a Save Copy too)."""
    on_save_post()  # (a save that failed on Blender 4.2, which calls no handler after it: restored now)
    if not filepath:  # (the startup file)
        return
    for scene in bpy.data.scenes:
        if scene.library is not None:  # (a linked scene is its library's to save)
            continue
        for name in PATH_PROPERTIES:
            value = getattr(scene.neulf, name)
            if value:
                _saving[(scene.name, name)] = absolute = abspath(value)  # (as the file open until now reads it)
                setattr(scene.neulf, name, relative_to(absolute, filepath))


@persistent
def on_save_post(*_args):
    """The folders relative to the file now open (the one saved, or after Save Copy the one
    that was open)."""
    for (scene_name, name), absolute in _saving.items():
        scene = bpy.data.scenes.get(scene_name)
        if scene is not None:
            setattr(scene.neulf, name, store_path(absolute))
    _saving.clear()


@persistent
def on_load_pre(*_args):
    """Jobs started in the file being closed keep running (a training keeps its model folder up
    to date); what they do when they end is matched to the new file's data (tasks.py)."""
    from . import tasks

    tasks.opened_files += 1


@persistent
def on_load_post(*_args):
    for scene in bpy.data.scenes:
        try:
            if scene.neulf.model_dir:
                refresh_model_status(scene)
        except Exception as exc:  # noqa: BLE001 - a handler must never break file loading
            print(f"NeuLF: cannot read the model status of scene {scene.name!r}: {exc}")


WATCH_INTERVAL = 2.0


def other_training_tick():
    """Timer: re-read the status of every scene whose model folder another process trains; the
    panel follows that training and, once it has stopped, says that Train continues it."""
    busy = False
    for scene in bpy.data.scenes:
        try:
            if scene.neulf.model_dir:
                busy |= refresh_model_status(scene).startswith(TRAINED_ELSEWHERE)
        except Exception as exc:  # noqa: BLE001 - a timer must not raise
            print(f"NeuLF: cannot read the model status of scene {scene.name!r}: {exc}")
    for window in bpy.context.window_manager.windows:
        for area in window.screen.areas:
            if area.type in ("VIEW_3D", "PROPERTIES"):
                area.tag_redraw()
    return WATCH_INTERVAL if busy else None


def watch_other_trainings():
    """Start `other_training_tick` (in the UI; background scripts call refresh_model_status)."""
    if not bpy.app.background and not bpy.app.timers.is_registered(other_training_tick):
        bpy.app.timers.register(other_training_tick, first_interval=WATCH_INTERVAL, persistent=True)


def _save_handlers():
    """(handler, list) pairs; a save that fails restores the folders as one that succeeds does
    (save_post_fail: Blender 4.4+; 4.2 has none)."""
    pairs = [(on_save_pre, bpy.app.handlers.save_pre), (on_save_post, bpy.app.handlers.save_post)]
    if hasattr(bpy.app.handlers, "save_post_fail"):
        pairs.append((on_save_post, bpy.app.handlers.save_post_fail))
    return pairs


def register():
    for handler, handlers in _save_handlers():
        if handler not in handlers:
            handlers.append(handler)
    if on_load_pre not in bpy.app.handlers.load_pre:
        bpy.app.handlers.load_pre.append(on_load_pre)
    if on_load_post not in bpy.app.handlers.load_post:
        bpy.app.handlers.load_post.append(on_load_post)


def unregister():
    for handler, handlers in _save_handlers():
        while handler in handlers:
            handlers.remove(handler)
    if bpy.app.timers.is_registered(other_training_tick):
        bpy.app.timers.unregister(other_training_tick)
    while on_load_pre in bpy.app.handlers.load_pre:
        bpy.app.handlers.load_pre.remove(on_load_pre)
    while on_load_post in bpy.app.handlers.load_post:
        bpy.app.handlers.load_post.remove(on_load_post)


CLASSES = ()

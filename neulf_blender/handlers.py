"""Application handlers.  On file load, each scene's training status is read again from its
model folder: after Blender quit (or crashed) while training, the .blend holds whatever it
had when it was saved, while the model folder's model.json holds the progress of the last
checkpoint.  The panel then says how far the model got, and Train continues it.  Where another
process still trains the folder (the training an earlier Blender left behind, saving its last
steps), a timer re-reads the status until that process has stopped."""

import bpy
from bpy.app.handlers import persistent


@persistent
def on_load_post(*_args):
    from .operators import refresh_model_status

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
    from .operators import TRAINED_ELSEWHERE, refresh_model_status

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


def register():
    if on_load_post not in bpy.app.handlers.load_post:
        bpy.app.handlers.load_post.append(on_load_post)


def unregister():
    if bpy.app.timers.is_registered(other_training_tick):
        bpy.app.timers.unregister(other_training_tick)
    while on_load_post in bpy.app.handlers.load_post:
        bpy.app.handlers.load_post.remove(on_load_post)


CLASSES = ()

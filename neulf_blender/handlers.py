"""Application handlers.  On file load, each scene's training status is read again from its
model folder: after Blender quit (or crashed) while training, the .blend holds whatever it
had when it was saved, while the model folder's model.json holds the progress of the last
checkpoint.  The panel then says how far the model got, and Train continues it."""

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


def register():
    if on_load_post not in bpy.app.handlers.load_post:
        bpy.app.handlers.load_post.append(on_load_post)


def unregister():
    while on_load_post in bpy.app.handlers.load_post:
        bpy.app.handlers.load_post.remove(on_load_post)


CLASSES = ()

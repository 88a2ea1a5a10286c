"""NeuLF for Blender: import captures, train and render neural light fields.

Modules: convert (camera maths, numpy only), jobs (processes, no bpy), core (where
neulf_core runs), capture (Blender objects), properties, model_folder (a scene's model folder
and its status line), operators, video_settings (Render Video's output and what it puts back),
focus (focus_at and the click-to-focus eyedropper), panel, engine (the NeuLF render engine),
viewport (the viewport preview's renderer thread), compositing (CG objects into the light
field), preferences, tasks (job polling), handlers (on file load, the training status is read
again from the model folder).  Nothing here
imports bpy at import time, so the Blender-free parts can be tested without Blender.
"""


def _modules():
    from . import engine, focus, operators, panel, preferences, properties

    return properties, preferences, operators, focus, panel, engine


def register():
    import bpy

    from . import handlers

    properties, preferences, operators, focus, panel, engine = _modules()
    for module in (properties, preferences, operators, focus, panel, engine):
        for cls in module.CLASSES:
            bpy.utils.register_class(cls)
    properties.register()
    engine.register()
    handlers.register()
    bpy.types.TOPBAR_MT_file_import.append(operators.menu_import)


def unregister():
    import bpy

    from . import core, handlers, tasks

    properties, preferences, operators, focus, panel, engine = _modules()
    handlers.unregister()
    tasks.cancel_all()
    core.shutdown()
    bpy.types.TOPBAR_MT_file_import.remove(operators.menu_import)
    engine.unregister()
    properties.unregister()
    for module in (engine, panel, focus, operators, preferences, properties):
        for cls in reversed(module.CLASSES):
            bpy.utils.unregister_class(cls)

"""NeuLF for Blender: the extension's entry point (registration only; see neulf_blender/).

No bpy import here: pytest and `import neulf_core` from the repository root must not need it.
"""


def register():
    from .neulf_blender import register as register_addon

    register_addon()


def unregister():
    from .neulf_blender import unregister as unregister_addon

    unregister_addon()

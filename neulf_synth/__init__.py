"""Synthetic forward-facing test scene for NeuLF, rendered with Blender Cycles via `bpy`.

Used by the demo, the end-to-end tests and stability studies: it renders a small
table-top scene from a planar camera rig and writes exact ground truth (intrinsics, poses,
depth, object index, a COLMAP model). See `generate.py` for the output layout.

This package imports bpy; `neulf_core` must never import it.
"""

__all__ = ["generate_scene"]


def __getattr__(name):
    # Lazy, so that `import neulf_synth` (e.g. for the CLI's --help or `layout`) needs no bpy.
    if name == "generate_scene":
        from .generate import generate_scene
        return generate_scene
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

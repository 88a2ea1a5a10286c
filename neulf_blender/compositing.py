"""CG objects composited into the light field: a second scene renders the user's CG objects
(Cycles, transparent film, Z pass) through the same camera, and the light field scene's
compositor puts them in front of or behind the light field pixel by pixel (Z Combine), with
both depths in the same scene units along the camera's axis (F12's Z pass, engine.py)."""

from __future__ import annotations

import bpy

from ..neulf_core.errors import NeulfError

CG_COLLECTION = "NeuLF CG Objects"
TREE_NAME = "NeuLF Compositing"
NODE_PREFIX = "NeuLF "
RENDER_SETTINGS = ("resolution_x", "resolution_y", "resolution_percentage", "pixel_aspect_x", "pixel_aspect_y")
FRAME_SETTINGS = ("frame_start", "frame_end", "frame_step")


def cg_scene_name(scene) -> str:
    return f"{scene.name} CG"


def set_up(scene) -> bpy.types.Scene:
    """Make (or bring up to date) the CG scene and the light field scene's compositor; returns
    the CG scene.  Everything in the collection CG_COLLECTION renders as CG."""
    if scene.camera is None:
        raise NeulfError("set a scene camera first (Use Capture Camera, or Scene > Camera): the CG renders "
                         "through the same camera as the light field.")
    tree = _compositor_tree(scene)
    collection = _cg_collection(scene)
    cg = bpy.data.scenes.get(cg_scene_name(scene))
    if cg is None:
        cg = bpy.data.scenes.new(cg_scene_name(scene))
        cg.render.engine = "CYCLES"  # (renders headless and on any machine; the user may choose EEVEE)
        cg.world = scene.world
    if scene.camera.name not in cg.collection.objects:
        cg.collection.objects.link(scene.camera)
    if collection.name not in cg.collection.children:
        cg.collection.children.link(collection)
    cg.camera = scene.camera
    _follow_render_settings(cg, scene)
    cg.render.film_transparent = True  # the light field shows where no CG object is
    cg.view_layers[0].use_pass_z = True
    scene.view_layers[0].use_pass_z = True
    _build_nodes(tree, scene, cg)
    return cg


def out_of_step(scene) -> str | None:
    """What no longer matches between this scene and its CG scene (size, frames, camera), which
    Z Combine needs pixel for pixel; None where they match or there is no CG scene."""
    cg = bpy.data.scenes.get(cg_scene_name(scene))
    if cg is None or cg is scene:
        return None
    differ = [name for name in RENDER_SETTINGS if getattr(cg.render, name) != getattr(scene.render, name)]
    differ += [name for name in FRAME_SETTINGS if getattr(cg, name) != getattr(scene, name)]
    if cg.camera != scene.camera:
        differ.append("camera")
    if not differ:
        return None
    return (f"the CG scene '{cg.name}' differs from this one in {', '.join(differ)}: press Composite CG Objects "
            "again, so that the CG lines up with the light field")


def _cg_collection(scene) -> bpy.types.Collection:
    collection = bpy.data.collections.get(CG_COLLECTION)
    if collection is None:
        collection = bpy.data.collections.new(CG_COLLECTION)
    if collection.name not in scene.collection.children:
        scene.collection.children.link(collection)
    return collection


def _follow_render_settings(cg, scene) -> None:
    for name in RENDER_SETTINGS:
        setattr(cg.render, name, getattr(scene.render, name))
    for name in FRAME_SETTINGS:
        setattr(cg, name, getattr(scene, name))
    cg.render.fps, cg.render.fps_base = scene.render.fps, scene.render.fps_base


def _compositor_tree(scene):
    """The scene's compositor node tree, made where it has none; refused where the user built
    one of their own (this would replace it)."""
    if hasattr(scene, "compositing_node_group"):  # Blender 5.0: a node group
        tree = scene.compositing_node_group
        if tree is None:
            tree = bpy.data.node_groups.new(TREE_NAME, "CompositorNodeTree")
            scene.compositing_node_group = tree
    else:  # Blender 4.2: the scene's own tree
        scene.use_nodes = True
        tree = scene.node_tree
    if any(not _ours_or_default(node) for node in tree.nodes):
        raise NeulfError("this scene already has a compositor node tree of its own: set up the CG compositing in "
                         "a copy of the scene, or clear its compositor nodes first.")
    return tree


def _ours_or_default(node) -> bool:
    """A node this module made, or one of the two Blender puts in a new tree."""
    return node.name.startswith(NODE_PREFIX) or node.bl_idname in ("CompositorNodeRLayers", "CompositorNodeComposite")


def _build_nodes(tree, scene, cg) -> None:
    tree.nodes.clear()
    plate = _node(tree, "CompositorNodeRLayers", "Light Field", (-400, 200))
    plate.scene, plate.layer = scene, scene.view_layers[0].name
    objects = _node(tree, "CompositorNodeRLayers", "CG", (-400, -200))
    objects.scene, objects.layer = cg, cg.view_layers[0].name
    combine = _node(tree, "CompositorNodeZcombine", "Z Combine", (0, 0))
    links = tree.links
    links.new(plate.outputs["Image"], combine.inputs[0])
    links.new(plate.outputs["Depth"], combine.inputs[1])
    links.new(objects.outputs["Image"], combine.inputs[2])
    links.new(objects.outputs["Depth"], combine.inputs[3])
    if "Use Alpha" in combine.inputs:  # 5.0: inputs; 4.2: properties
        combine.inputs["Use Alpha"].default_value = True
    else:
        combine.use_alpha = True
    if hasattr(scene, "compositing_node_group"):
        if not tree.interface.items_tree:
            tree.interface.new_socket(name="Image", in_out="OUTPUT", socket_type="NodeSocketColor")
        output = _node(tree, "NodeGroupOutput", "Output", (300, 0))
    else:
        output = _node(tree, "CompositorNodeComposite", "Output", (300, 0))
    links.new(combine.outputs[0], output.inputs[0])


def _node(tree, kind: str, label: str, location):
    node = tree.nodes.new(kind)
    node.name = node.label = NODE_PREFIX + label
    node.location = location
    return node

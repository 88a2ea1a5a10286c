"""CG objects composited into the light field: a second scene renders the user's CG objects
(Cycles, transparent film, Z pass) through the same camera, and the light field scene's
compositor puts them in front of or behind the light field pixel by pixel (Z Combine), with
both depths in the same scene units along the camera's axis (F12's Z pass, engine.py).

The light field scene holds pointers to its CG scene and CG collection (scene.neulf), so
renaming either keeps the link; the CG scene is marked, so it is never set up as a light field
scene itself and a scene the user made under the same name is never taken over."""

from __future__ import annotations

import bpy

from ..neulf_core.errors import NeulfError

TREE_NAME = "NeuLF Compositing"
TREE_MARK = "neulf_compositing"  # a custom property on the node trees this module builds
NODE_PREFIX = "NeuLF "
RENDER_SETTINGS = ("resolution_x", "resolution_y", "resolution_percentage", "pixel_aspect_x", "pixel_aspect_y",
                   "use_border", "border_min_x", "border_max_x", "border_min_y", "border_max_y", "use_crop_to_border",
                   "use_multiview", "views_format")
FRAME_SETTINGS = ("frame_start", "frame_end", "frame_step")
CG_SAMPLES = 64  # a new scene's Cycles default (4096) makes every CG frame minutes long on a CPU
# In Blender 4.2's scene tree, the nodes a new tree holds (and the viewer a click adds): replaced.
DEFAULT_NODES = ("CompositorNodeRLayers", "CompositorNodeComposite", "CompositorNodeViewer")


def set_up(scene, view_layer) -> bpy.types.Scene:
    """Make (or bring up to date) the CG scene and the light field scene's compositor for the
    light field's `view_layer`; returns the CG scene."""
    if scene.neulf.is_cg_scene:
        raise NeulfError(f"{scene.name} renders the CG of another scene: run Composite CG Objects in the light "
                         "field's scene.")
    if scene.camera is None:
        raise NeulfError("set a scene camera first (Use Capture Camera, or Scene > Camera): the CG renders "
                         "through the same camera as the light field.")
    tree = _compositor_tree(scene)
    collection = _cg_collection(scene)
    cg = _cg_scene(scene)
    if scene.camera.name not in cg.collection.objects:
        cg.collection.objects.link(scene.camera)
    if collection not in cg.collection.children_recursive:
        cg.collection.children.link(collection)
    cg.camera = scene.camera
    _follow_camera_markers(cg, scene)
    _follow_render_settings(cg, scene)
    cg.render.film_transparent = True  # the light field shows where no CG object is
    cg.view_layers[0].use_pass_z = True
    view_layer.use_pass_z = True
    _build_nodes(tree, scene, view_layer, cg)
    return cg


def out_of_step(scene) -> str | None:
    """What no longer matches between this scene and its CG scene (size, frames, camera), which
    Z Combine needs pixel for pixel; None where they match or there is no CG scene."""
    cg = scene.neulf.cg_scene
    if cg is None or scene.neulf.is_cg_scene:
        return None
    differ = [name for name in RENDER_SETTINGS if getattr(cg.render, name) != getattr(scene.render, name)]
    differ += [name for name in FRAME_SETTINGS if getattr(cg, name) != getattr(scene, name)]
    if _views(cg) != _views(scene):
        differ.append("stereoscopy views")
    if _camera_switches(cg) != _camera_switches(scene):
        differ.append("camera markers")
    elif not _camera_switches(scene) and cg.camera != scene.camera:
        # (with markers, each scene's camera follows its markers only as it renders a frame)
        differ.append("camera")
    if not differ:
        return None
    return (f"the CG scene '{cg.name}' differs from this one in {', '.join(differ)}: press Composite CG Objects "
            "again, so that the CG lines up with the light field")


def _cg_scene(scene) -> bpy.types.Scene:
    """This scene's CG scene: the one it points to, else a new one (its name made unique by
    Blender where a scene of the user's has it)."""
    cg = scene.neulf.cg_scene
    if cg is None:
        cg = bpy.data.scenes.new(f"{scene.name} CG")
        cg.neulf.is_cg_scene = True
        cg.render.engine = "CYCLES"  # (renders headless and on any machine; the user may choose EEVEE)
        cg.cycles.samples, cg.cycles.use_denoising = CG_SAMPLES, True
        cg.world = scene.world  # the CG is lit by the light field scene's world and the collection's lights
        scene.neulf.cg_scene = cg
    return cg


def _cg_collection(scene) -> bpy.types.Collection:
    """This scene's CG collection (one per light field scene), linked into it where it is not
    already, at any depth."""
    collection = scene.neulf.cg_collection
    if collection is None:
        collection = bpy.data.collections.new(f"{scene.name} CG Objects")
        scene.neulf.cg_collection = collection
    if collection not in scene.collection.children_recursive:
        scene.collection.children.link(collection)
    return collection


def _camera_switches(scene) -> list:
    """The scene's timeline markers bound to a camera, as (frame, camera) in frame order: Blender
    switches the scene's camera at each of them as it renders an animation."""
    return sorted(((marker.frame, marker.camera) for marker in scene.timeline_markers if marker.camera is not None),
                  key=lambda switch: (switch[0], switch[1].name))


def _follow_camera_markers(cg, scene) -> None:
    """The light field scene's camera switches copied into the CG scene (its own camera-bound
    markers replaced), with their cameras linked into it, so each frame's CG renders through the
    camera the light field renders through."""
    for marker in [marker for marker in cg.timeline_markers if marker.camera is not None]:
        cg.timeline_markers.remove(marker)
    for frame, camera in _camera_switches(scene):
        cg.timeline_markers.new(f"{NODE_PREFIX}{camera.name}", frame=frame).camera = camera
        if camera.name not in cg.collection.objects:
            cg.collection.objects.link(camera)


def _views(scene) -> list:
    """The scene's stereoscopy views as Blender renders them (name, in use, camera suffix)."""
    return [(view.name, view.use, view.camera_suffix) for view in scene.render.views]


def _follow_render_settings(cg, scene) -> None:
    for name in RENDER_SETTINGS:
        setattr(cg.render, name, getattr(scene.render, name))
    for view in scene.render.views:  # (each eye of the CG, as the light field renders it)
        copy = cg.render.views.get(view.name) or cg.render.views.new(view.name)
        copy.use, copy.camera_suffix = view.use, view.camera_suffix
    for view in [view for view in cg.render.views if view.name not in scene.render.views]:
        cg.render.views.remove(view)
    for name in FRAME_SETTINGS:
        setattr(cg, name, getattr(scene, name))
    cg.render.fps, cg.render.fps_base = scene.render.fps, scene.render.fps_base


def _compositor_tree(scene):
    """A compositor node tree of this module's for the scene.  Blender 5.0: a node group of its
    own, assigned to the scene (a group of the user's stays in the file, kept by a fake user).
    Blender 4.2: the scene's own tree, refused where it holds nodes of the user's (it would be
    replaced), before anything is changed."""
    if hasattr(scene, "compositing_node_group"):
        tree = scene.compositing_node_group
        if tree is not None and tree.get(TREE_MARK) and tree.users <= 1:
            return tree
        if tree is not None and not tree.get(TREE_MARK):
            tree.use_fake_user = True
        tree = bpy.data.node_groups.new(TREE_NAME, "CompositorNodeTree")
        tree[TREE_MARK] = True
        scene.compositing_node_group = tree
        return tree
    tree = scene.node_tree
    if tree is not None and any(not _ours_or_default(node) for node in tree.nodes):
        raise NeulfError("this scene already has a compositor node tree of its own: set up the CG compositing in "
                         "a copy of the scene, or clear its compositor nodes first.")
    scene.use_nodes = True
    return scene.node_tree


def _ours_or_default(node) -> bool:
    """A node this module made, or one Blender puts in a new tree."""
    return node.name.startswith(NODE_PREFIX) or node.bl_idname in DEFAULT_NODES


def _build_nodes(tree, scene, view_layer, cg) -> None:
    tree.nodes.clear()
    plate = _node(tree, "CompositorNodeRLayers", "Light Field", (-400, 200))
    plate.scene, plate.layer = scene, view_layer.name
    objects = _node(tree, "CompositorNodeRLayers", "CG", (-400, -200))
    objects.scene, objects.layer = cg, cg.view_layers[0].name
    combine = _node(tree, "CompositorNodeZcombine", "Z Combine", (0, 0))
    links = tree.links  # (inputs by index: 4.2 names both images "Image", 5.0 "A" and "B")
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

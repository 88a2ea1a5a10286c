"""Builds the synthetic scene in the current Blender session, ready to render views.

Render settings aim at three things: plain sRGB images (Standard view transform, no look,
exposure 0, gamma 1, no dithering, no metadata stamps), determinism (fixed Cycles seed and
sample count, same pixels on every run) and speed on a small CPU (few light bounces,
adaptive sampling, persistent data between the views of a rig).
"""

from __future__ import annotations

import math

import bpy
from mathutils import Vector

from . import layout
from .materials import ShaderGraph, build_environment, create_materials

SUN_STRENGTH = 2.2  # W/m^2
SUN_ANGLE = math.radians(3.0)  # slightly soft shadows
# Sun from behind the cameras, above and to the left, so the objects are lit from the front.
SUN_ROTATION = (math.radians(50.0), math.radians(-20.0), math.radians(-25.0))
WORLD_STRENGTH = 0.6

GROUND_TRUTH_OUTPUT_NODE = "GroundTruthOutput"
# Render Layers socket -> name of the EXR file item it is written to.
GROUND_TRUTH_PASSES = {"Depth": "Depth", "Object Index": "ObjectIndex"}


def reset_to_empty_scene() -> bpy.types.Scene:
    # Factory startup data, so a user's startup.blend cannot leak settings into the scene;
    # unlike read_factory_settings this keeps enabled add-ons (e.g. the NeuLF add-on) alive.
    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
    return bpy.context.scene


def configure_render(scene, size: tuple[int, int], samples: int, seed: int, variant: str) -> None:
    render = scene.render
    render.engine = "CYCLES"
    render.resolution_x, render.resolution_y = size
    render.resolution_percentage = 100
    render.pixel_aspect_x = render.pixel_aspect_y = 1.0
    render.film_transparent = False
    render.use_motion_blur = False
    render.use_border = False
    render.dither_intensity = 0.0  # dithering would add noise to the 8-bit images
    # Re-rendering the same scene from another camera then skips rebuilding the BVH.
    render.use_persistent_data = True
    _disable_metadata(render)
    _configure_cycles(scene.cycles, samples, seed, variant)
    _configure_color_management(scene)
    _configure_png_output(render.image_settings)


def _disable_metadata(render) -> None:
    """No date, render time, host name ... in the files, so re-renders are byte-identical."""
    for name in dir(render):
        if name.startswith("use_stamp"):
            setattr(render, name, False)


def _configure_cycles(cycles, samples: int, seed: int, variant: str) -> None:
    cycles.device = "CPU"
    cycles.film_exposure = 1.0  # per-view exposure goes through view_settings.exposure
    cycles.samples = samples
    cycles.seed = seed
    cycles.use_animated_seed = False
    # Adaptive sampling with an explicit minimum: Cycles' automatic minimum for this threshold
    # exceeds 32 samples, which would switch adaptivity off. Halves the render time here.
    cycles.use_adaptive_sampling = True
    cycles.adaptive_threshold = 0.02
    cycles.adaptive_min_samples = min(8, samples)
    # OpenImageDenoise runs headless here, but on CPU its output differed between two
    # processes rendering the same view (measured with bpy 5.0.1) and it added ~65% render
    # time; it would also smooth the fine textures. So: no denoising.
    cycles.use_denoising = False
    cycles.use_light_tree = False  # one sun and the world: nothing for the tree to gain
    cycles.caustics_reflective = False
    cycles.caustics_refractive = False
    cycles.sample_clamp_indirect = 10.0  # clamp fireflies from the glossy/glass paths
    # Diffuse surfaces carry their own fill light (materials.FILL_LIGHT), so only direct light
    # is traced for them: no indirect diffuse noise, far fewer rays.
    cycles.diffuse_bounces = 0
    cycles.volume_bounces = 0
    cycles.transparent_max_bounces = 0
    if variant == "shiny":
        # A mirror and a solid glass object need a few more bounces to look right:
        # entering and leaving the glass takes two transmission events.
        cycles.glossy_bounces = 3
        cycles.transmission_bounces = 6
        cycles.max_bounces = 8
    else:
        cycles.glossy_bounces = 0
        cycles.transmission_bounces = 0
        cycles.max_bounces = 0


def _configure_color_management(scene) -> None:
    scene.display_settings.display_device = "sRGB"
    view = scene.view_settings
    view.view_transform = "Standard"
    view.look = "None"
    view.exposure = 0.0
    view.gamma = 1.0
    view.use_curve_mapping = False


def _configure_png_output(image_settings) -> None:
    image_settings.file_format = "PNG"
    image_settings.color_mode = "RGB"
    image_settings.color_depth = "8"
    image_settings.compression = 15  # fast; the images are small


def add_world(scene) -> None:
    world = bpy.data.worlds.new("SynthWorld")
    if world.node_tree is None:  # Blender < 5.0 creates node trees only on request
        world.use_nodes = True
    build_environment(ShaderGraph(world.node_tree, "Generated", "ShaderNodeOutputWorld"),
                      WORLD_STRENGTH)
    scene.world = world  # before the Cycles settings below: their callbacks use scene.world
    # The sky shows up only in mirror reflections and through glass. Diffuse surfaces get
    # their sky-like fill from their materials instead, without sampling noise.
    world.cycles_visibility.diffuse = False
    world.cycles.sampling_method = "NONE"


def add_sun(scene) -> None:
    light = bpy.data.lights.new("Sun", type="SUN")
    light.energy = SUN_STRENGTH
    light.angle = SUN_ANGLE
    sun = bpy.data.objects.new("Sun", light)
    sun.rotation_euler = SUN_ROTATION
    scene.collection.objects.link(sun)


def add_objects(scene, variant: str, texture_factor: float, arrangement: int = 0) -> dict[str, bpy.types.Object]:
    materials = create_materials(variant, texture_factor)
    objects = {}
    for spec in layout.scene_objects(arrangement):
        obj = bpy.data.objects.new(spec.name, _build_mesh(spec))
        obj.location = spec.location
        obj.rotation_euler = spec.rotation
        obj.pass_index = spec.pass_index
        obj.data.materials.append(materials[spec.material])
        scene.collection.objects.link(obj)
        if spec.kind == "monkey":
            _smooth_with_subdivision(obj)
        objects[spec.name] = obj
    return objects


def _build_mesh(spec: layout.ObjectSpec) -> bpy.types.Mesh:
    if spec.kind == "quad":
        return _quad_mesh(spec.name, spec.size["width"], spec.size["height"])
    return _primitive_mesh(spec)


def _quad_mesh(name: str, width: float, height: float) -> bpy.types.Mesh:
    """A single rectangle in the local XY plane, normal +Z."""
    w, h = width / 2.0, height / 2.0
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata([(-w, -h, 0.0), (w, -h, 0.0), (w, h, 0.0), (-w, h, 0.0)], [], [(0, 1, 2, 3)])
    return mesh


def _primitive_mesh(spec: layout.ObjectSpec) -> bpy.types.Mesh:
    """Create a primitive at the origin with the operator, then keep only its mesh."""
    size = spec.size
    if spec.kind == "sphere":
        # Fine tessellation keeps the facets within ~1e-4 of the true sphere.
        bpy.ops.mesh.primitive_uv_sphere_add(radius=size["radius"], segments=96, ring_count=48)
    elif spec.kind == "cylinder":
        bpy.ops.mesh.primitive_cylinder_add(radius=size["radius"], depth=size["depth"],
                                            vertices=64)
    elif spec.kind == "cube":
        bpy.ops.mesh.primitive_cube_add(size=size["size"])
    elif spec.kind == "monkey":
        bpy.ops.mesh.primitive_monkey_add(size=2.0 * size["scale"])
    else:
        raise ValueError(f"unknown object kind {spec.kind!r}")
    temporary = bpy.context.active_object
    mesh = temporary.data
    mesh.name = spec.name
    bpy.data.objects.remove(temporary)
    if spec.kind in ("sphere", "cylinder"):
        mesh.shade_smooth()
    return mesh


def _smooth_with_subdivision(obj) -> None:
    modifier = obj.modifiers.new("Subdivision", type="SUBSURF")
    modifier.levels = modifier.render_levels = 2
    obj.data.shade_smooth()


def add_camera(scene, name: str, position, look_at) -> bpy.types.Object:
    """A camera at `position` aimed at `look_at`, world Z up, with the rig's shared lens."""
    data = bpy.data.cameras.new(name)
    data.lens = layout.LENS_MM
    data.sensor_width = layout.SENSOR_WIDTH_MM
    data.sensor_fit = "HORIZONTAL"
    data.clip_start = 0.05
    data.clip_end = 100.0
    camera = bpy.data.objects.new(name, data)
    camera.location = Vector(position)
    direction = Vector(look_at) - Vector(position)
    camera.rotation_euler = direction.to_track_quat("-Z", "Y").to_euler()
    scene.collection.objects.link(camera)
    return camera


def add_ground_truth_outputs(scene) -> bpy.types.Node:
    """Compositor: the image goes to the render output, depth and object index to EXR files.

    Cycles writes these data passes from each pixel's first sample (not averaged), so object
    edges keep the depth of one surface instead of a blend of two.
    """
    view_layer = scene.view_layers[0]
    view_layer.use_pass_z = True
    view_layer.use_pass_object_index = True
    tree = bpy.data.node_groups.new("SynthCompositor", "CompositorNodeTree")
    scene.compositing_node_group = tree
    layers = tree.nodes.new("CompositorNodeRLayers")
    tree.interface.new_socket(name="Image", in_out="OUTPUT", socket_type="NodeSocketColor")
    group_output = tree.nodes.new("NodeGroupOutput")
    tree.links.new(layers.outputs["Image"], group_output.inputs[0])

    file_output = tree.nodes.new("CompositorNodeOutputFile")
    file_output.name = GROUND_TRUTH_OUTPUT_NODE
    file_output.format.media_type = "IMAGE"
    file_output.format.file_format = "OPEN_EXR"
    file_output.format.color_depth = "32"  # full float: depth must survive exactly
    file_output.format.exr_codec = "ZIP"
    for socket_name, item_name in GROUND_TRUTH_PASSES.items():
        file_output.file_output_items.new("FLOAT", item_name)
        tree.links.new(layers.outputs[socket_name], file_output.inputs[item_name])
    return file_output


def build_scene(variant: str, size: tuple[int, int], samples: int, seed: int,
                texture_factor: float, arrangement: int = 0) -> tuple[bpy.types.Scene, dict]:
    scene = reset_to_empty_scene()
    configure_render(scene, size, samples, seed, variant)
    add_world(scene)
    add_sun(scene)
    objects = add_objects(scene, variant, texture_factor, arrangement)
    add_ground_truth_outputs(scene)
    return scene, objects

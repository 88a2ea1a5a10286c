"""Procedural materials of the synthetic scene (Cycles shader nodes).

Every surface carries rich, multi-scale, colourful texture so that SIFT finds plenty of
distinctive features even at 320x240 and structure-from-motion registers every view.
All textures use Object coordinates, so their frequencies are in cycles per scene unit
and do not depend on mesh UVs; `texture_factor` multiplies every frequency (the `fine`
variant). The `shiny` variant swaps two materials for a mirror metal and a refracting glass.
"""

from __future__ import annotations

import bpy

# Colours are linear RGB. Textured albedos stay roughly within [0.15, 0.8] so that the bright
# lighting neither clips nor leaves textures too dark to carry features.
WALL_MORTAR = (0.55, 0.55, 0.5, 1.0)
WALL_BRICK_BASE = (0.6, 0.3, 0.18, 1.0)
FLOOR_LIGHT = (0.55, 0.38, 0.2, 1.0)
FLOOR_DARK = (0.22, 0.13, 0.07, 1.0)
CUBE_A = (0.7, 0.12, 0.08, 1.0)
CUBE_B = (0.75, 0.6, 0.08, 1.0)
METAL_TINT = (0.9, 0.85, 0.78, 1.0)
GLASS_TINT = (0.95, 0.98, 1.0, 1.0)
SKY_COLOR = (0.75, 0.8, 0.9, 1.0)

# Fill light: emitted radiance per unit albedo (see ShaderGraph.diffuse).
FILL_LIGHT = 0.18
MIRROR_ROUGHNESS = 0.05
GLASS_IOR = 1.45


class ShaderGraph:
    """Small helper to add nodes and wire them with little ceremony.

    `add(type, **inputs)` sets unlinked inputs to values and links inputs given as output
    sockets. Input names are socket identifiers (spaces replaced by underscores), which are
    unique even on nodes such as Mix that repeat display names per data type.
    """

    def __init__(self, node_tree: bpy.types.ShaderNodeTree, coordinates: str = "Object",
                 output_type: str = "ShaderNodeOutputMaterial"):
        self.nodes = node_tree.nodes
        self.links = node_tree.links
        self.nodes.clear()
        self.coords = self.nodes.new("ShaderNodeTexCoord").outputs[coordinates]
        self.output = self.nodes.new(output_type)

    def add(self, node_type: str, properties: dict | None = None, **inputs) -> bpy.types.Node:
        """New node: `properties` are node attributes (set first), `inputs` socket values/links."""
        node = self.nodes.new(node_type)
        for name, value in (properties or {}).items():
            setattr(node, name, value)
        for key, value in inputs.items():
            socket = self._input(node, key)
            if isinstance(value, bpy.types.NodeSocket):
                self.links.new(value, socket)
            else:
                socket.default_value = value
        return node

    @staticmethod
    def _input(node: bpy.types.Node, key: str) -> bpy.types.NodeSocket:
        for socket in node.inputs:
            if socket.identifier == key or socket.identifier == key.replace("_", " "):
                return socket
        raise KeyError(f"{node.bl_idname} has no input {key!r}")

    def texture(self, node_type: str, scale: float, **inputs) -> bpy.types.Node:
        return self.add(node_type, Vector=self.coords, Scale=scale, **inputs)

    def mix(self, a, b, factor, blend: str = "MIX") -> bpy.types.NodeSocket:
        node = self.add("ShaderNodeMix", {"data_type": "RGBA", "blend_type": blend},
                        Factor_Float=factor, A_Color=a, B_Color=b)
        return next(socket for socket in node.outputs if socket.identifier == "Result_Color")

    def surface(self, shader_output: bpy.types.NodeSocket) -> None:
        self.links.new(shader_output, self.output.inputs["Surface"])

    def diffuse(self, color) -> None:
        """Lambertian surface (Diffuse BSDF, roughness 0) plus a fill-light term.

        The fill term is emission equal to albedo x FILL_LIGHT: a noise-free stand-in for
        sky light. It is view-independent like the BSDF, so the surface stays Lambertian,
        and it lets the scene render cleanly without indirect bounces (much faster).
        """
        bsdf = self.add("ShaderNodeBsdfDiffuse", Color=color, Roughness=0.0)
        fill = self.add("ShaderNodeEmission", Color=color, Strength=FILL_LIGHT)
        total = self.add("ShaderNodeAddShader")
        self.links.new(bsdf.outputs["BSDF"], total.inputs[0])
        self.links.new(fill.outputs["Emission"], total.inputs[1])
        self.surface(total.outputs["Shader"])


def _pastel(graph: ShaderGraph, color, amount: float = 0.2) -> bpy.types.NodeSocket:
    """Blend towards light grey so random texture colours are never near black."""
    return graph.mix(color, (0.8, 0.8, 0.8, 1.0), amount)


def _detail(graph: ShaderGraph, color, scale: float, amount: float = 0.35) -> bpy.types.NodeSocket:
    """Overlay fine coloured noise: texture inside otherwise flat patches."""
    noise = graph.texture("ShaderNodeTexNoise", scale, Detail=2.0, Roughness=0.6)
    return graph.mix(color, noise.outputs["Color"], amount, blend="OVERLAY")


def build_wall(graph: ShaderGraph, f: float) -> None:
    patches = graph.texture("ShaderNodeTexVoronoi", 1.2 * f)
    bricks = graph.texture("ShaderNodeTexBrick", 1.6 * f,
                           Color1=_pastel(graph, patches.outputs["Color"]),
                           Color2=WALL_BRICK_BASE, Mortar=WALL_MORTAR,
                           Mortar_Size=0.025, Bias=0.1)
    graph.diffuse(_detail(graph, bricks.outputs["Color"], 9.0 * f))


def build_floor(graph: ShaderGraph, f: float) -> None:
    boards = graph.texture("ShaderNodeTexChecker", 1.5 * f, Color1=FLOOR_LIGHT, Color2=FLOOR_DARK)
    grain = graph.texture("ShaderNodeTexWave", 2.5 * f, Distortion=6.0, Detail=4.0)
    color = graph.mix(boards.outputs["Color"], grain.outputs["Color"], 0.3, blend="OVERLAY")
    graph.diffuse(_detail(graph, color, 12.0 * f))


def build_sphere(graph: ShaderGraph, f: float) -> None:
    cells = graph.texture("ShaderNodeTexVoronoi", 9.0 * f)
    graph.diffuse(_detail(graph, _pastel(graph, cells.outputs["Color"]), 30.0 * f, 0.5))


def build_monkey(graph: ShaderGraph, f: float) -> None:
    swirls = graph.texture("ShaderNodeTexMagic", 2.5 * f, Distortion=2.0)
    graph.diffuse(_detail(graph, _pastel(graph, swirls.outputs["Color"]), 15.0 * f))


def build_cylinder(graph: ShaderGraph, f: float) -> None:
    bands = graph.texture("ShaderNodeTexWave", 2.0 * f, Distortion=3.0, Detail=3.0)
    noise = graph.texture("ShaderNodeTexNoise", 3.0 * f, Detail=3.0)
    color = graph.mix(_pastel(graph, noise.outputs["Color"], 0.2), bands.outputs["Color"], 0.4,
                      blend="MULTIPLY")
    graph.diffuse(_detail(graph, color, 18.0 * f))


def build_cube(graph: ShaderGraph, f: float) -> None:
    checks = graph.texture("ShaderNodeTexChecker", 3.0 * f, Color1=CUBE_A, Color2=CUBE_B)
    cells = graph.texture("ShaderNodeTexVoronoi", 6.0 * f)
    color = graph.mix(checks.outputs["Color"], _pastel(graph, cells.outputs["Color"]), 0.35)
    graph.diffuse(_detail(graph, color, 20.0 * f))


def build_environment(graph: ShaderGraph, strength: float) -> None:
    """World shader: a patchwork of sky colours around the scene.

    Only mirror reflections and glass show it (see blender_scene.add_world); patches make
    those reflections change with the viewpoint, as a real surrounding would.
    """
    patches = graph.texture("ShaderNodeTexVoronoi", 5.0)
    color = graph.mix(SKY_COLOR, patches.outputs["Color"], 0.35)
    background = graph.add("ShaderNodeBackground", Color=color, Strength=strength)
    graph.surface(background.outputs["Background"])


def build_mirror(graph: ShaderGraph, f: float) -> None:
    graph.surface(graph.add("ShaderNodeBsdfPrincipled", Base_Color=METAL_TINT, Metallic=1.0,
                            Roughness=MIRROR_ROUGHNESS).outputs["BSDF"])


def build_glass(graph: ShaderGraph, f: float) -> None:
    graph.surface(graph.add("ShaderNodeBsdfPrincipled", Base_Color=GLASS_TINT, Metallic=0.0,
                            Roughness=0.0, IOR=GLASS_IOR, Transmission_Weight=1.0).outputs["BSDF"])


LAMBERTIAN_BUILDERS = {
    "wall": build_wall,
    "floor": build_floor,
    "sphere": build_sphere,
    "monkey": build_monkey,
    "cylinder": build_cylinder,
    "cube": build_cube,
}
# In the shiny variant the near sphere becomes a mirror and the monkey glass: the two
# objects whose appearance then depends most strongly on the viewpoint.
SHINY_OVERRIDES = {"sphere": build_mirror, "monkey": build_glass}


def appearance(variant: str, slot: str) -> str:
    """'mirror', 'glass' or 'diffuse': how the material in `slot` reflects light."""
    if variant == "shiny" and slot in SHINY_OVERRIDES:
        return SHINY_OVERRIDES[slot].__name__.removeprefix("build_")
    return "diffuse"


def material_builders(variant: str) -> dict:
    builders = dict(LAMBERTIAN_BUILDERS)
    if variant == "shiny":
        builders.update(SHINY_OVERRIDES)
    return builders


def create_materials(variant: str, texture_factor: float) -> dict[str, bpy.types.Material]:
    """Create one material per slot name used in `layout.scene_objects()`."""
    materials = {}
    for name, build in material_builders(variant).items():
        material = bpy.data.materials.new(name)
        if material.node_tree is None:  # Blender < 5.0 creates node trees only on request
            material.use_nodes = True
        build(ShaderGraph(material.node_tree), texture_factor)
        materials[name] = material
    return materials

"""The add-on's settings on the scene: one PropertyGroup, `scene.neulf`."""

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, PointerProperty, StringProperty

from ..neulf_core import presets as core_presets  # (torch-free)

def _relative_path_options() -> set:
    """Blender 4.5+ warns about '//' paths unless the property says it supports them; 4.2
    rejects the option, and only when the class registers (bpy.props defers the check), so
    ask RNA whether properties know the flag."""
    if "is_path_supports_blend_relative" in bpy.types.Property.bl_rna.properties:
        return {"PATH_SUPPORTS_BLEND_RELATIVE"}
    return set()


PATH_OPTIONS = _relative_path_options()

# The core's presets that Blender offers, described in the core's words (a description typed
# here had gone stale when `fast` changed field).  Not offered: `auto` (a search of sizes
# before training: the CLI's) and `planes` (an earlier field, kept for comparison).
OFFERED_PRESETS = {"fast": "Fast", "authors": "Authors", "paper": "Paper"}
PRESETS = [(name, label, core_presets.PRESETS[name].description[:1].upper() + core_presets.PRESETS[name].description[1:])
           for name, label in OFFERED_PRESETS.items()]
# "Depth from Photos" (the sweep teacher); numbered so that a .blend saved when it was a
# checkbox reads on as Auto (1, its old default) or Off (0).
TEACHER_CHOICES = [
    ("OFF", "Off", "Never", 0),
    ("AUTO", "Auto", "The preset's choice: on for Fast, off for the authors' and the paper's networks (their recipes)", 1),
    ("ON", "On", "Always", 2),
]
# "Varying Exposure": what `train` gets (operators.start_training; Auto passes nothing, the trainer decides).
APPEARANCE_CHOICES = [
    ("AUTO", "Auto", "On when neighbouring photos differ in exposure by 0.1 stops or more"),
    ("ON", "On", "Always learn a colour correction per photo"),
    ("OFF", "Off", "Never: every photo has the same exposure and white balance"),
]
# "Refine Poses": likewise (Auto: the trainer refines for its first 100 steps, 200 where unsure, and keeps refining
# only where the corrections say the poses are off).
POSE_CHOICES = [
    ("AUTO", "Auto", "Refine the camera poses only where the first training steps find them off"),
    ("ON", "On", "Always learn a correction of each photo's camera pose"),
    ("OFF", "Off", "Never: the reconstruction's poses are exact"),
]
# "Back Surface": likewise (Auto: on for deep scenes, far/near above 3).
BACK_SURFACE_CHOICES = [
    ("AUTO", "Auto", "A second surface behind each ray's first on deep scenes (far/near depth ratio above 3)"),
    ("ON", "On", "Always: worth trying on a subject well in front of its background, whatever the depth range"),
    ("OFF", "Off", "Never: one surface per ray, about a quarter less time per step"),
]
# What an Auto / On / Off choice passes to the trainer (None: the trainer decides).
CHOICE_OPTION = {"AUTO": None, "ON": True, "OFF": False}


class NeulfSceneSettings(bpy.types.PropertyGroup):
    scene_dir: StringProperty(name="Capture", subtype="DIR_PATH", options=PATH_OPTIONS,
                              description="COLMAP scene (sparse/0 and images/) or LLFF folder of the imported capture")
    images_dir: StringProperty(name="Images", subtype="DIR_PATH", options=PATH_OPTIONS,
                               description="Images folder when it is not SCENE/images (optional)")
    model_dir: StringProperty(name="Model", subtype="DIR_PATH", options=PATH_OPTIONS,
                              description="Trained NeuLF model folder (stored relative to the .blend); empty: "
                                          "Train makes neulf_model in the scene folder")
    capture_collection: PointerProperty(type=bpy.types.Collection, name="Capture Collection",
                                        description="Collection of the imported capture")
    root: PointerProperty(type=bpy.types.Object, name="Root",
                          description="Root empty of the capture: move it to orient the scene")
    # .blend files saved before the pointers above name the collection and the root instead
    # (a name breaks when the user renames either, or copies the scene): read, never written.
    collection_name: StringProperty(options={"HIDDEN"})
    root_name: StringProperty(options={"HIDDEN"})
    cg_scene: PointerProperty(type=bpy.types.Scene, name="CG Scene",
                              description="The scene Composite CG Objects renders the CG objects in")
    cg_collection: PointerProperty(type=bpy.types.Collection, name="CG Objects",
                                   description="The objects Composite CG Objects puts into the light field")
    is_cg_scene: BoolProperty(name="CG Scene", default=False, options={"HIDDEN"},
                              description="This scene renders another scene's CG objects (compositing.py)")
    fingerprint: StringProperty(description="Identifies the imported reconstruction")

    import_points: BoolProperty(name="Sparse Points", default=True, description="Import the sparse 3D points")
    train_minutes: FloatProperty(name="Minutes", default=5.0, min=0.05, soft_max=120.0,
                                 description="Training time to add (continues a trained model)")
    train_steps: IntProperty(name="Steps", default=0, min=0,
                             description="Training steps to add instead of minutes (0: use minutes)")
    preset: EnumProperty(name="Preset", items=PRESETS, default="fast")
    sweep_teacher: EnumProperty(name="Depth from Photos", default="AUTO", items=TEACHER_CHOICES,
                                description="Guide early training with the depth a plane sweep finds in the photos: "
                                            "better depth for click-to-focus and a sharper image on the scenes measured")
    depth_layers: IntProperty(name="Depth Layers", default=-1, min=-1, max=core_presets.MAX_DEPTH_LAYERS,
                              description="Fast preset: depth layers for sharper depth edges on shallow "
                                          "scenes; worse on deep ones (-1: automatic, 8 when the scene's far/near "
                                          "depth ratio is at most 3 and 18 or more photos train; 0: none)")
    appearance: EnumProperty(name="Varying Exposure", default="AUTO", items=APPEARANCE_CHOICES,
                             description="Learn a colour correction per photo, for captures whose exposure or white "
                                         "balance changes between shots")
    refine_poses: EnumProperty(name="Refine Poses", default="AUTO", items=POSE_CHOICES,
                               description="Learn a small correction of each photo's camera pose, for captures whose "
                                           "reconstruction is off by a tenth of a degree or more")
    back_surface: EnumProperty(name="Back Surface", default="AUTO", items=BACK_SURFACE_CHOICES,
                               description="Let each ray see a surface behind its first and blend the two: "
                                           "sharper on deep scenes and on subjects well in front of their "
                                           "background; about 1.4 times the training time a step and 1.5 times "
                                           "the render time")
    stop_early: BoolProperty(name="Stop Early", default=True,
                             description="With at most 13 photos, end training once it has passed over their "
                                         "pixels 100 times, even before the time is up: more only memorises so few "
                                         "photos and blurs the views between them. Off: train for the whole time")
    two_starts: BoolProperty(name="Two Starts", default=True,
                             description="With at most 13 photos, when the time pays for it, train a second random "
                                         "start to 42 % of the training and keep the one that fits the photos "
                                         "better: one run in three otherwise can settle on a worse shape. Not while "
                                         "the poses are being refined (it gains nothing there). Off: one start")
    members: IntProperty(name="Members", default=0, min=0, max=8,
                         description="Light fields trained apart, each with an equal share of the time, rendered "
                                     "as the mean of their colours: better and steadier where one has stopped "
                                     "gaining from more training; renders take this many times longer. 0: "
                                     "automatic (2 when the time passes over the photos' pixels 12 times or more on a CPU, 60 on a GPU, "
                                     "else 1). A model being continued keeps its own count")
    train_scale: FloatProperty(name="Image Scale", default=0.0, min=0.0, max=1.0,
                               description="Train on images resized by this factor. 0: automatic (the largest 1/k at "
                                           "which a photo has at most 200,000 pixels: 1/2 for 960x540 photos, 1/8 for "
                                           "12-megapixel ones). A model being continued keeps its own scale")
    spiral_frames: IntProperty(name="Frames", default=60, min=3, max=2000, description="Frames of the spiral path")
    pixel_samples: EnumProperty(
        name="Pixel Samples", default="AUTO",
        items=(("AUTO", "Auto", "4 points, and 1 where the camera renders 1.5 times the resolution the model trained at "
                                "or finer (the points then gain 0.014 dB or less, at 2-5 times the time)"),
               ("1", "1", "One ray through each pixel's centre: fastest"),
               ("4", "4", "The mean of 2 x 2 points in the pixels whose colour has contrast with a neighbour's: "
                          "+0.05 to +0.28 dB on held-out views, 2-5 times one point's time"),
               ("9", "9", "The mean of 3 x 3 points in each pixel"),
               ("16", "16", "The mean of 4 x 4 points in each pixel")),
        description="Points per pixel whose colours are averaged in renders (anti-aliasing), in the pixels "
                    "whose colour differs from a neighbour's by more than 5 of 255 levels")
    chunk: IntProperty(name="Chunk", default=0, min=0, max=1 << 22,
                       description="Rays per network call. 0: the device's own (32,768 on a CPU, 1,048,576 on a GPU, "
                                   "where large chunks halved the frame time). A chunk the device has no memory for "
                                   "is retried in halves; a smaller one lowers the peak")

    last_status: StringProperty(description="Last training result")
    last_psnr: FloatProperty(description="Validation PSNR of the last training run (dB)")


def settings(context_or_scene):
    scene = getattr(context_or_scene, "scene", context_or_scene)
    return scene.neulf


def pixel_samples_request(props) -> int | None:
    """The Pixel Samples setting as the core takes it: a count, or None (Auto: the model's
    default for the camera, render.LightField.default_pixel_samples)."""
    return None if props.pixel_samples == "AUTO" else int(props.pixel_samples)


CLASSES = (NeulfSceneSettings,)


def register():
    bpy.types.Scene.neulf = bpy.props.PointerProperty(type=NeulfSceneSettings)


def unregister():
    del bpy.types.Scene.neulf

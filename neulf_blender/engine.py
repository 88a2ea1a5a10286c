"""The NeuLF render engine: F12 renders the active camera through the light field,
Ctrl+F12 the frame range (Blender writes the video).  The camera's depth of field (focus
distance or focus object, f-stop) is rendered by synthetic-aperture refocus in neulf_core."""

import bpy

from . import capture, convert
from ..neulf_core.errors import NeulfError


class NeulfRenderEngine(bpy.types.RenderEngine):
    bl_idname = "NEULF"
    bl_label = "NeuLF"
    bl_use_preview = False
    bl_use_postprocess = True

    def render(self, depsgraph):
        from .operators import model_dir
        from .preferences import get_core

        scene = depsgraph.scene_eval
        camera = scene.camera
        original = bpy.data.scenes.get(scene.name) or scene
        try:
            root = bpy.data.objects.get(scene.neulf.root_name) if scene.neulf.root_name else None
            root_matrix = root.evaluated_get(depsgraph).matrix_world if root is not None else None
            request = capture.camera_request(scene, camera.evaluated_get(depsgraph) if camera else None,
                                             root_matrix=root_matrix)
            scale = request.pop("scale")
            request.update(capture.lens_request(camera.evaluated_get(depsgraph), scale))
            self.update_stats("", "NeuLF: rendering")
            result = get_core().call("render", model_dir=model_dir(original), depth=False, chunk=scene.neulf.chunk,
                                     pixel_samples=int(scene.neulf.pixel_samples),
                                     on_progress=self.update_progress, should_stop=self.test_break, **request)
        except InterruptedError:
            return
        except NeulfError as exc:
            self.report({"ERROR"}, str(exc))
            return
        width, height = request["width"], request["height"]
        rgb = convert.srgb_to_linear(result["rgb"])  # the Combined pass is scene-linear
        render_result = self.begin_result(0, 0, width, height)
        render_result.layers[0].passes["Combined"].rect.foreach_set(convert.image_rows_for_blender(rgb))
        self.end_result(render_result)
        for note in result.get("warnings", []):
            self.report({"WARNING"}, note)


COMPAT_PANELS = ("RENDER_PT_format", "RENDER_PT_frame_range", "RENDER_PT_output", "RENDER_PT_encoding",
                 "RENDER_PT_encoding_video", "RENDER_PT_color_management", "RENDER_PT_output_color_management",
                 "RENDER_PT_format_presets", "RENDER_PT_stamp", "RENDER_PT_time_stretching", "DATA_PT_lens",
                 "DATA_PT_camera", "DATA_PT_camera_dof", "DATA_PT_camera_dof_aperture", "DATA_PT_context_camera",
                 "DATA_PT_camera_display", "DATA_PT_camera_safe_areas", "DATA_PT_custom_props_camera",
                 "OUTPUT_PT_format", "OUTPUT_PT_frame_range", "OUTPUT_PT_output", "OUTPUT_PT_encoding",
                 "OUTPUT_PT_encoding_video", "OUTPUT_PT_time_stretching", "OUTPUT_PT_stamp",
                 "RENDER_PT_color_management_curves", "RENDER_PT_color_management_display_settings")


def _panels():
    for name in COMPAT_PANELS:
        panel = getattr(bpy.types, name, None)
        if panel is not None and hasattr(panel, "COMPAT_ENGINES"):
            yield panel


def register():
    for panel in _panels():
        panel.COMPAT_ENGINES.add(NeulfRenderEngine.bl_idname)


def unregister():
    for panel in _panels():
        panel.COMPAT_ENGINES.discard(NeulfRenderEngine.bl_idname)


CLASSES = (NeulfRenderEngine,)

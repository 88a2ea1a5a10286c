"""The NeuLF render engine: F12 renders the active camera through the light field,
Ctrl+F12 the frame range (Blender writes the video).  The camera's depth of field (focus
distance or focus object, f-stop) is rendered by synthetic-aperture refocus in neulf_core.
The viewport's Rendered shading shows the light field from the viewport's camera
(viewport.py renders it in a thread; this draws it)."""

import traceback
import weakref

import bpy
from mathutils import Matrix

from . import capture, compositing, convert, viewport
from .properties import pixel_samples_request
from .model_folder import model_dir
from .wording import panel_words
from ..neulf_core.errors import OUT_OF_MEMORY, NeulfError, is_out_of_memory

_RENDERERS = weakref.WeakSet()  # the viewports' PreviewRenderers, for the redraw timer
REDRAW_INTERVAL = 0.1


class NeulfRenderEngine(bpy.types.RenderEngine):
    bl_idname = "NEULF"
    bl_label = "NeuLF"
    bl_use_preview = False
    bl_use_postprocess = True

    def update_render_passes(self, scene=None, renderlayer=None):
        """The passes F12 fills: Combined, and Depth where the view layer asks for its Z pass
        (Properties > View Layer > NeuLF Passes), for the compositor and multilayer EXR."""
        self.register_pass(scene, renderlayer, "Combined", 4, "RGBA", "COLOR")
        if renderlayer.use_pass_z:
            self.register_pass(scene, renderlayer, "Depth", 1, "Z", "VALUE")

    def render(self, depsgraph):
        scene = depsgraph.scene_eval
        original = scene.original  # (by name, a linked scene would find a local one of its name)
        for view in _views(scene.render):  # (each eye of a stereo render, or the one view)
            try:
                if not self._render_view(depsgraph, original, view):
                    return
            # Any other error ends the render with an ERROR report, which stops an animation (it had
            # left a black frame in the video and reported success); the traceback goes to the
            # console for a bug report, the status bar gets one line.
            except Exception as exc:  # noqa: BLE001
                if is_out_of_memory(exc):
                    self.report({"ERROR"}, OUT_OF_MEMORY)
                    return
                traceback.print_exc()
                self.report({"ERROR"}, f"NeuLF render failed ({type(exc).__name__}: {exc}); the console has the details.")
                return
        mismatch = compositing.out_of_step(original)
        if mismatch:
            self.report({"WARNING"}, mismatch)
        for note in capture.settings_not_followed(scene, scene.camera):
            self.report({"WARNING"}, note)

    def _render_view(self, depsgraph, original, view: str) -> bool:
        """Render one view (a stereo eye by name, or "" without multiview) of this call's view
        layer into its result; False where it stopped (cancelled, or an error reported)."""
        from .preferences import get_core

        scene = depsgraph.scene_eval
        camera = scene.camera.evaluated_get(depsgraph) if scene.camera else None
        want_depth = bool(depsgraph.view_layer_eval.use_pass_z)
        try:
            eye = {}
            if view and camera is not None:  # Blender's own eye placement (interocular, convergence mode)
                self.active_view_set(view)
                eye = dict(matrix_world=self.camera_model_matrix(camera), shift_x=self.camera_shift_x(camera))
            _collection, root = capture.find_capture(original)
            root_matrix = root.evaluated_get(depsgraph).matrix_world if root is not None else None
            request = capture.camera_request(scene, camera, root_matrix=root_matrix, **eye)
            scale = request.pop("scale")
            request.update(capture.lens_request(camera, scale))
            request = _region_only(request, scene.render)
            self.update_stats("", f"NeuLF: rendering {view}".rstrip())
            result = get_core().call("render", model_dir=model_dir(original), depth=want_depth, chunk=scene.neulf.chunk,
                                     pixel_samples=pixel_samples_request(scene.neulf),
                                     on_progress=self.update_progress, should_stop=self.test_break, **request)
        except InterruptedError:
            return False
        except NeulfError as exc:
            self.report({"ERROR"}, panel_words(str(exc)))
            return False
        width, height = request["width"], request["height"]
        rgb = convert.srgb_to_linear(result["rgb"])  # the Combined pass is scene-linear
        alpha = 1.0
        if scene.render.film_transparent and result.get("valid") is not None:
            # Film > Transparent: no alpha where a ray misses the light slab (and no colour: premultiplied)
            alpha = result["valid"].astype("float32")
            rgb = rgb * alpha[..., None]
        # Blender calls render once for each view layer: this call's result is its own layer's.
        render_result = self.begin_result(0, 0, width, height, layer=depsgraph.view_layer.name, view=view)
        passes = render_result.layers[0].passes
        passes["Combined"].rect.foreach_set(convert.image_rows_for_blender(rgb, alpha))
        if want_depth and result.get("depth") is not None and "Depth" in passes:
            passes["Depth"].rect.foreach_set(convert.depth_rows_for_blender(result["depth"] * scale))
        self.end_result(render_result)
        for note in result.get("warnings", []):
            self.report({"WARNING"}, note)
        return True

    # ------------------------------------------------------------------ the viewport

    def view_update(self, context, depsgraph):
        pass  # (view_draw reads the view, the root and the model each time: nothing to prepare)

    def view_draw(self, context, depsgraph):
        scene = depsgraph.scene_eval
        original = scene.original  # (by name, a linked scene would find a local one of its name)
        try:
            request, key = _viewport_view(original, depsgraph, context.region, context.region_data)
        except NeulfError as exc:
            self.update_stats("", f"NeuLF: {panel_words(str(exc))}")
            return
        renderer = self._preview_renderer()
        renderer.want(key, request)
        shown = renderer.image()
        if shown is not None:
            self._draw_preview(scene, shown, context.region.width, context.region.height)
        self.update_stats("", viewport.status_line(renderer, key))
        if renderer.busy and not bpy.app.timers.is_registered(_redraw_while_rendering):
            bpy.app.timers.register(_redraw_while_rendering, first_interval=REDRAW_INTERVAL)

    def _preview_renderer(self) -> viewport.PreviewRenderer:
        """This viewport's renderer, made again when the preferences chose another core."""
        from .preferences import get_core

        core = get_core()  # (read here, on Blender's thread: the preferences are bpy data)
        wanted = (core.python, core.extra_paths, core.device, core.mode)
        renderer = getattr(self, "_neulf_preview", None)
        if renderer is None or getattr(self, "_neulf_core", None) != wanted:
            if renderer is not None:
                renderer.close()
            renderer = viewport.PreviewRenderer(viewport.render_function(core))
            self._neulf_preview, self._neulf_core = renderer, wanted
            _RENDERERS.add(renderer)
        return renderer

    def _draw_preview(self, scene, shown: viewport.PreviewImage, width: int, height: int) -> None:
        import gpu
        from gpu_extras.presets import draw_texture_2d

        cached = getattr(self, "_neulf_texture", None)
        if cached is None or cached[0] is not shown:  # a new image: upload it once
            rgba = convert.image_rows_for_blender(convert.srgb_to_linear(shown.rgb))  # scene-linear, bottom row first
            rows, columns = shown.rgb.shape[:2]
            texture = gpu.types.GPUTexture((columns, rows), format="RGBA16F",
                                           data=gpu.types.Buffer("FLOAT", rgba.size, rgba))
            self._neulf_texture = cached = (shown, texture)
        gpu.state.blend_set("ALPHA_PREMULT")
        # (Blender's viewport applies the scene's view transform to what an engine draws, so the
        # texture holds scene-linear values, as F12's Combined pass; this binds the image shader)
        self.bind_display_space_shader(scene)
        draw_texture_2d(cached[1], (0, 0), width, height)  # (a coarse image is stretched over the region)
        self.unbind_display_space_shader()
        gpu.state.blend_set("NONE")

    def __del__(self):  # (Blender frees the viewport's engine when the shading leaves Rendered)
        try:
            renderer = getattr(self, "_neulf_preview", None)
        except ReferenceError:  # (the Blender side already gone; the thread ends when idle)
            renderer = None
        if renderer is not None:
            renderer.close()
        parent = getattr(super(), "__del__", None)  # (none in bpy 4.2-5.0; Blender's docs call it)
        if parent is not None:
            parent()


def _views(render) -> list[str]:
    """The views Blender renders: with Stereoscopy on, its left and right eyes (Stereo 3D) or
    every view in use (Multi-View); else one, unnamed."""
    if not render.use_multiview:
        return [""]
    if render.views_format == "STEREO_3D":
        return [view.name for view in render.views if view.use and view.name in ("left", "right")]
    return [view.name for view in render.views if view.use]


def _region_only(request: dict, render) -> dict:
    """With a render region on, the request for its pixels only: Blender's render result then
    holds just the region (cropped or not; Blender places it in the frame)."""
    if not render.use_border:
        return request
    region = convert.border_region(request["width"], request["height"], (render.border_min_x, render.border_max_x),
                                   (render.border_min_y, render.border_max_y))
    if region[2] < 1 or region[3] < 1:
        raise NeulfError("the render region is less than a pixel: draw a larger one (Ctrl+B in the camera view) "
                         "or turn Render Region off.")
    return convert.crop_request(request, *region)


def _viewport_view(scene, depsgraph, region, view) -> tuple[dict, tuple]:
    """The render request of the viewport's pinhole (in the model's frame; looking through the
    scene camera, with the camera's depth of field) and the key of its preview image."""
    model = model_dir(scene)  # (raises with what to do when there is none)
    _collection, root = capture.find_capture(scene)
    root_matrix = root.evaluated_get(depsgraph).matrix_world if root is not None else Matrix.Identity(4)
    if (view.view_perspective == "CAMERA" and scene.camera is not None and scene.camera.type == "CAMERA"
            and scene.camera.data.type != "PERSP"):  # (the view's own message would say to look through a camera)
        raise NeulfError(f"camera {scene.camera.name} is {scene.camera.data.type.lower()}; NeuLF renders perspective "
                         "cameras only.")
    request = viewport.view_request(view.view_matrix, view.window_matrix, region.width, region.height, root_matrix)
    scale = request.pop("scale")
    if view.view_perspective == "CAMERA" and scene.camera is not None and scene.camera.type == "CAMERA":
        # Through the camera: its depth of field too, so a picked focus shows as it renders.
        request.update(capture.lens_request(scene.camera.evaluated_get(depsgraph), scale))
    from ..neulf_core.worker import model_stamp  # (numpy only at import: safe in Blender's Python)

    stamp = model_stamp(model)  # (every member's files: a second member trained on refreshes it too)
    key = viewport.view_key(request, model, stamp)
    return {**request, "model_dir": model}, key


def _redraw_while_rendering():
    """A timer on Blender's thread: redraws the 3D viewports while a preview renders (the
    render thread must not touch Blender), and once more when it has finished."""
    for window in bpy.context.window_manager.windows:
        for area in window.screen.areas:
            if area.type == "VIEW_3D":
                area.tag_redraw()
    return REDRAW_INTERVAL if any(renderer.busy for renderer in list(_RENDERERS)) else None


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

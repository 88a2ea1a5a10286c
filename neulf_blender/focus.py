"""Focus from the light field: `neulf.focus_at` (an image point) and `neulf.pick_focus`
(a click in a viewport that looks through the camera).

The eyedropper's work is plain functions so it runs without a mouse (scripts, headless
tests): `pick_event` decides what one event does, `click_pixel` maps a click to the active
camera's image, `focus_at` asks the model for the depth there and sets the camera's DOF.
The operators only forward Blender's events and report.
"""

from __future__ import annotations

import bpy
from bpy.props import FloatProperty

from . import capture, convert
from .model_folder import model_dir
from .operators import _Reporting
from .preferences import get_core
from .wording import panel_words
from ..neulf_core.errors import NeulfError

HINT = "Click on what should be sharp (camera view); Esc / right click cancels"


def focus_at(context, x: float, y: float) -> tuple[str, str]:
    """Set the active camera's focus distance to the light field's depth at image point (x, y)
    (pixels from the image's top-left corner); returns the report (level, line): focus_report's."""
    scene = context.scene
    camera = scene.camera
    request = capture.camera_request(scene, camera)
    width, height = request["width"], request["height"]
    if not (0 <= x <= width and 0 <= y <= height):
        raise NeulfError(f"point ({x:.0f}, {y:.0f}) is outside the {width}x{height} camera image.")
    result = get_core(context).call("depth_at", model_dir=model_dir(scene), K=request["K"], R=request["R"],
                                    t=request["t"], x=float(x), y=float(y))
    # The model's depth runs along the camera's axis, as Blender's focus distance does.
    distance = result["depth"] * request["scale"]
    dof = camera.data.dof
    dof.use_dof = True
    dof.focus_object = None  # it would override the distance
    dof.focus_distance = distance
    return focus_report(camera.data, request["K"][0][0], distance)


def focus_report(camera_data, focal_px: float, distance: float) -> tuple[str, str]:
    """The focus distance set, and how much the camera's f-stop blurs a surface twice as far
    (the circle's diameter in render pixels, thin lens: 2 A f |1/D - 1/2D| = A f / D).  A
    reconstruction's units are its own, not metres: CanClip's subject stands 33 units away,
    where its 48 mm lens at f/2.8 blurs 0.34 px at 960x540 and f/0.5 rendered within 52 dB of
    the pinhole; scaling the root to the scene's real size makes the lens behave as a real one
    (an audit, 2026-12-02)."""
    fstop = camera_data.dof.aperture_fstop
    if fstop <= 0:
        return "INFO", f"focus distance {distance:.4g}"
    blur = capture.aperture_radius(camera_data) * focal_px / distance
    said = f"focus distance {distance:.4g}; at f/{fstop:.3g} a surface twice as far blurs {blur:.2g} px"
    if blur >= 1.0:
        return "INFO", said
    return "WARNING", (f"{said}: hardly any depth of field, as the capture's units are its reconstruction's, not "
                       f"metres. Scale the NeuLF Root by (the subject's real distance in metres) / {distance:.4g}, "
                       "or lower the F-Stop")


def viewport_under(screen, mouse_x: int, mouse_y: int):
    """(area, region) of the 3D viewport's main region under a window point, or (None, None).

    Started from the N-panel the operator's own region is the sidebar, so every VIEW_3D area
    of the screen is searched; a point on a header, toolbar or sidebar drawn over the
    viewport does not count as a click in it."""
    def inside(region):
        return region.x <= mouse_x < region.x + region.width and region.y <= mouse_y < region.y + region.height

    for area in screen.areas:
        if area.type != "VIEW_3D":
            continue
        window = next((r for r in area.regions if r.type == "WINDOW" and inside(r)), None)
        covered = any(r.type != "WINDOW" and r.width > 1 and r.height > 1 and inside(r) for r in area.regions)
        if window is not None and not covered:
            return area, window
    return None, None


def click_pixel(scene, space, region, x: float, y: float) -> tuple[float, float]:
    """The active camera's image point (pixels from the top-left) under region point (x, y)
    (pixels from the region's bottom-left) of a viewport looking through that camera."""
    camera = scene.camera
    if camera is None or camera.type != "CAMERA":
        raise NeulfError("the scene has no active camera.")
    rv3d = getattr(region, "data", None) or space.region_3d  # quad view: each region has its own
    if rv3d.view_perspective != "CAMERA":
        raise NeulfError("look through the camera first (Numpad 0), then pick the focus.")
    if space.use_local_camera and space.camera is not None and space.camera != camera:
        raise NeulfError(f"this viewport looks through {space.camera.name}, not the scene camera {camera.name}.")
    render, cam = scene.render, camera.data
    border = convert.camera_view_border(
        region.width, region.height, view_camera_zoom=rv3d.view_camera_zoom,
        view_camera_offset=tuple(rv3d.view_camera_offset), sensor_fit=cam.sensor_fit, shift_x=cam.shift_x,
        shift_y=cam.shift_y, resolution_x=render.resolution_x, resolution_y=render.resolution_y,
        pixel_aspect_x=render.pixel_aspect_x, pixel_aspect_y=render.pixel_aspect_y)
    width, height = convert.render_size(render.resolution_x, render.resolution_y, render.resolution_percentage)
    point = convert.border_to_pixel(border, x, y, width, height)
    if point is None:
        raise NeulfError("click inside the camera frame.")
    return point


def focus_from_click(context, mouse_x: int, mouse_y: int) -> tuple[str, str]:
    """Focus the active camera on what is under a window point (an event's mouse_x, mouse_y)."""
    area, region = viewport_under(context.screen, mouse_x, mouse_y)
    if region is None:
        raise NeulfError("click inside a 3D viewport that looks through the camera.")
    x, y = click_pixel(context.scene, area.spaces.active, region, mouse_x - region.x, mouse_y - region.y)
    return focus_at(context, x, y)


def pick_event(context, event_type: str, event_value: str, mouse_x: int, mouse_y: int):
    """What one event does to the eyedropper: (status, report), status one of 'RUNNING_MODAL',
    'CANCELLED', 'FINISHED'; report None or (level, one line)."""
    if event_type in {"ESC", "RIGHTMOUSE"}:
        return "CANCELLED", None
    if event_type != "LEFTMOUSE" or event_value != "PRESS":
        return "RUNNING_MODAL", None
    try:
        report = focus_from_click(context, mouse_x, mouse_y)
    except NeulfError as exc:
        return "CANCELLED", ("ERROR", panel_words(str(exc)))
    return "FINISHED", report


class NEULF_OT_focus_at(_Reporting, bpy.types.Operator):
    """Focus the active camera on the light field's depth at an image point (pixels, top-left origin)"""

    bl_idname = "neulf.focus_at"
    bl_label = "Focus At Point"
    bl_options = {"REGISTER", "UNDO"}

    x: FloatProperty(name="X", description="Pixels from the left edge (pixel i's centre is i + 0.5)")
    y: FloatProperty(name="Y", description="Pixels from the top edge (pixel j's centre is j + 0.5)")

    def run(self, context):
        level, line = focus_at(context, self.x, self.y)
        self.report({level}, line)
        return {"FINISHED"}


class NEULF_OT_pick_focus(bpy.types.Operator):
    """Click on what should be sharp in the camera view; its light-field depth becomes the focus distance"""

    bl_idname = "neulf.pick_focus"
    bl_label = "Pick Focus"
    bl_options = {"REGISTER", "UNDO"}

    def invoke(self, context, event):
        try:  # say what is missing now, not after the click
            capture.camera_request(context.scene, context.scene.camera)
            model_dir(context.scene)
        except NeulfError as exc:
            self.report({"ERROR"}, panel_words(str(exc)))
            return {"CANCELLED"}
        context.window.cursor_modal_set("EYEDROPPER")
        context.window_manager.modal_handler_add(self)
        context.workspace.status_text_set(HINT)
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        status, report = pick_event(context, event.type, event.value, event.mouse_x, event.mouse_y)
        if status != "RUNNING_MODAL":
            context.window.cursor_modal_restore()
            context.workspace.status_text_set(None)
        if report is not None:
            self.report({report[0]}, report[1])
        return {status}


CLASSES = (NEULF_OT_focus_at, NEULF_OT_pick_focus)

"""The N-panel (3D viewport > sidebar > NeuLF): capture, training, rendering."""

import textwrap
from pathlib import Path

import bpy

from . import compositing, tasks
from .model_folder import TRAINED_ELSEWHERE, is_model_of

CHARS_PER_PIXEL = 1 / 7.0  # the UI font's average advance at 1x scale, for wrapping labels


def wrapped_lines(text: str, width_px: float, ui_scale: float = 1.0) -> list[str]:
    """`text` cut into lines that fit a panel `width_px` wide (a label does not wrap by itself,
    and the status lines -- pose corrections, another process training the folder -- are long)."""
    chars = max(20, int((width_px - 30) * CHARS_PER_PIXEL / max(ui_scale, 0.1)))
    return textwrap.wrap(text, chars) or [""]


def _wrapped_label(layout, context, text: str, icon: str = "NONE"):
    region = context.region
    width = region.width if region is not None else 300
    column = layout.column(align=True)
    for number, line in enumerate(wrapped_lines(text, width, context.preferences.system.ui_scale)):
        column.label(text=line, icon=icon if number == 0 else "BLANK1")


def _job_box(layout, job, label: str, cancel_op: str | None = None):
    state = job.state
    box = layout.box()
    elapsed = state.get("elapsed") or state.get("elapsed_wall", 0.0)
    text = f"{label}: {state.get('message', '')}"[:60]
    box.progress(factor=float(state.get("fraction", 0.0)), type="BAR", text=text)
    row = box.row()
    minutes, seconds = divmod(int(elapsed), 60)
    row.label(text=f"{minutes}:{seconds:02d}", icon="TIME")
    if state.get("val_psnr") is not None:
        row.label(text=f"val {state['val_psnr']:.2f} dB")
    if cancel_op:
        box.operator(cancel_op, icon="CANCEL", text="Cancel")


class NEULF_PT_main(bpy.types.Panel):
    bl_label = "NeuLF"
    bl_idname = "NEULF_PT_main"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "NeuLF"

    def draw(self, context):
        layout = self.layout
        props = context.scene.neulf

        col = layout.column(align=True)
        col.label(text="Capture", icon="OUTLINER_OB_CAMERA")
        col.operator("neulf.import_colmap", text="Import COLMAP / LLFF", icon="IMPORT")
        col.operator("neulf.reconstruct", text="Reconstruct Photos", icon="IMAGE_DATA")
        col.operator("neulf.reconstruct_video", text="Reconstruct Video", icon="FILE_MOVIE")
        recon = tasks.get("reconstruct")  # (a video's frame picking, then its reconstruction)
        what = "Picking frames" if recon is not None and recon.kind == "frame picking" else "Reconstructing"
        if recon is not None and recon.running:
            _job_box(layout, recon, what)
        elif recon is not None and recon.state["status"] == "failed":
            _wrapped_label(layout, context, f"{what} failed: {recon.state['error']}", icon="ERROR")
        if props.scene_dir:
            layout.label(text=bpy.path.basename(props.scene_dir.rstrip("/\\")) or props.scene_dir, icon="FILE_FOLDER")
        layout.operator("neulf.use_capture_camera", icon="VIEW_CAMERA")

        layout.separator()
        col = layout.column(align=True)
        col.label(text="Training", icon="SHADERFX")
        row = col.row(align=True)
        row.prop(props, "train_minutes")
        row.prop(props, "train_steps")
        row = col.row(align=True)
        row.prop(props, "preset", text="")
        row.prop(props, "train_scale")
        col.prop(props, "sweep_teacher")
        fast_only = col.column(align=True)  # (the fast field's options: greyed out for the other presets, not passed)
        fast_only.enabled = props.preset == "fast"
        fast_only.prop(props, "depth_layers")
        fast_only.prop(props, "back_surface")
        col.prop(props, "appearance")
        col.prop(props, "refine_poses")
        row = col.row(align=True)
        row.prop(props, "stop_early")
        row.prop(props, "two_starts")
        col.prop(props, "members")
        train = tasks.get("train")
        if train is not None and train.running:
            ours = is_model_of(context.scene, train.model_dir)
            label = "Training" if ours else f"Training {Path(train.model_dir).name}"  # (another file's model)
            _job_box(layout, train, label, "neulf.cancel_train")
        else:
            label = "Continue Training" if props.model_dir else "Train NeuLF"
            layout.operator("neulf.train", text=label, icon="PLAY")
            if train is not None and train.state["status"] == "failed":
                _wrapped_label(layout, context, f"Failed: {train.state['error']}", icon="ERROR")
        if props.last_status:
            psnr = f", val {props.last_psnr:.2f} dB" if props.last_psnr else ""
            elsewhere = props.last_status.startswith(TRAINED_ELSEWHERE)
            _wrapped_label(layout, context, f"{'' if elsewhere else 'Last: '}{props.last_status}{psnr}",
                           icon="TIME" if elsewhere else "NONE")

        layout.separator()
        col = layout.column(align=True)
        col.label(text="Model", icon="FILE_3D")
        col.prop(props, "model_dir", text="")
        col.operator("neulf.load_model", text="Load Model", icon="FILEBROWSER")

        layout.separator()
        col = layout.column(align=True)
        col.label(text="Render", icon="RENDER_STILL")
        col.operator("neulf.render_camera", text="Render Camera", icon="RENDER_STILL")
        row = col.row(align=True)
        row.prop(props, "pixel_samples")
        row.prop(props, "chunk")
        col.operator("neulf.viewport_preview", icon="SHADING_RENDERED")
        col.operator("neulf.pick_focus", icon="EYEDROPPER")
        row = col.row(align=True)
        row.prop(props, "spiral_frames")
        row.operator("neulf.spiral_path", text="Spiral Camera Path", icon="CURVE_BEZCIRCLE")
        col.operator("neulf.render_video", text="Render Video", icon="RENDER_ANIMATION")
        col.operator("neulf.composite_cg", icon="NODE_COMPOSITING")
        mismatch = compositing.out_of_step(context.scene)
        if mismatch:
            _wrapped_label(layout, context, mismatch, icon="ERROR")


class NEULF_PT_view_layer_passes(bpy.types.Panel):
    """Properties > View Layer, with the NeuLF engine: the passes F12 writes besides the image
    (Blender's own Passes panels list only their engines' passes)."""

    bl_label = "NeuLF Passes"
    bl_idname = "NEULF_PT_view_layer_passes"
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "view_layer"

    @classmethod
    def poll(cls, context):
        return context.engine == "NEULF"

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        layout.prop(context.view_layer, "use_pass_z", text="Z")
        layout.label(text="Depth along the view axis, in scene units")
        hint = multilayer_exr_hint(context.scene)
        if hint:
            _wrapped_label(layout, context, hint, icon="ERROR")


def multilayer_exr_hint(scene) -> str | None:
    """Blender 5.0.1 fails to save a multilayer EXR whose pixels are not square once it holds
    more than the Combined pass ("Error writing render result"; Cycles' renders too), and a
    capture whose fx and fy differ gets such pixels.  Said for 5.0, where it was seen (4.2 saves
    them); later versions are unchecked."""
    render = scene.render
    if bpy.app.version[:2] != (5, 0) or render.pixel_aspect_x == render.pixel_aspect_y:
        return None
    if not any(layer.use_pass_z for layer in scene.view_layers):
        return None
    return ("Blender 5.0 cannot save a multilayer EXR with a Z pass and non-square pixels (Output > Format > "
            "Aspect, set from this capture's camera): save the Z pass as its own EXR with a compositor File "
            "Output node.")


CLASSES = (NEULF_PT_main, NEULF_PT_view_layer_passes)

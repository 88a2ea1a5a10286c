"""Operators: thin Blender <-> neulf_core translation.  User errors are one-line reports.
The model folder's handling is model_folder.py's; Render Video's settings, video_settings.py's."""

from __future__ import annotations

import tempfile
from pathlib import Path

import bpy
import numpy as np
from bpy.props import FloatProperty, IntProperty, StringProperty

from . import capture, compositing, jobs, tasks
from .jobs import job_status_text
from .model_folder import (attach_model, chosen_path, default_model_dir, model_dir, model_not_found,
                           saved_progress_text,
                           readable_model, refuse_linked, restore_metadata, scenes_of_model,
                           store_path)
from .preferences import get_core, get_prefs, worker_python
from .properties import CHOICE_OPTION, pixel_samples_request
from .video_settings import (configure_video, refuse_odd_video_size, refuse_unwritable_video, restore_after_render,
                             restore_render_settings, saved_render_settings, video_path)
from .wording import panel_words
from ..neulf_core.errors import NeulfError
from ..neulf_core.lock import being_trained_message, training_holder
from ..neulf_core.members import budget_done
from ..neulf_core.model_files import METADATA_NAME, can_resume, read_metadata
from ..neulf_core.presets import get_preset

RENDER_IMAGE = "NeuLF Render"
DEPTH_IMAGE = "NeuLF Depth"


class _Reporting:
    """`run()` does the work; NeulfError becomes one ERROR line, never a traceback."""

    def execute(self, context):
        try:
            return self.run(context)
        except NeulfError as exc:
            self.report({"ERROR"}, panel_words(str(exc)))
            return {"CANCELLED"}
        except OSError as exc:  # (a file or folder the operator met that cannot be read or written: one line)
            where = f" {exc.filename}" if exc.filename else ""
            self.report({"ERROR"}, f"cannot read or write{where}: {exc.strerror or exc}. Check the path, its "
                                   "permissions and the free disk space.")
            return {"CANCELLED"}


# ----------------------------------------------------------------------------- import


def import_scene(context, scene_dir: str, images_dir: str = "", import_points: bool = True,
                 model_path: str = "") -> dict:
    """`model_path`: the model the capture is for, where it is not (yet) the scene's."""
    props = context.scene.neulf
    existing_model = model_path or chosen_path(props.model_dir)
    description = get_core(context).call("describe_scene", scene_dir=scene_dir, images_dir=images_dir or None,
                                         model_dir=existing_model or None)
    capture.build_capture(context, description, import_points=import_points)
    props.scene_dir = store_path(scene_dir)
    images_dir = images_dir or description.get("images_dir_from_model") or ""  # (the photos the model trained on)
    props.images_dir = store_path(images_dir) if images_dir else ""
    return description


class NEULF_OT_import_colmap(_Reporting, bpy.types.Operator):
    """Import a COLMAP scene (sparse/0 + images/) or an LLFF folder: cameras, light slab, points"""

    bl_idname = "neulf.import_colmap"
    bl_label = "Import NeuLF Capture (COLMAP/LLFF)"
    bl_options = {"REGISTER", "UNDO"}

    directory: StringProperty(subtype="DIR_PATH")
    images_dir: StringProperty(name="Images", subtype="DIR_PATH", description="Images folder if not SCENE/images")
    import_points: bpy.props.BoolProperty(name="Sparse Points", default=True)
    filter_folder: bpy.props.BoolProperty(default=True, options={"HIDDEN"})

    def invoke(self, context, event):
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def run(self, context):
        if not self.directory.strip():
            raise NeulfError("choose the scene folder (the one holding sparse/0 and images/, or poses_bounds.npy).")
        description = import_scene(context, chosen_path(self.directory), chosen_path(self.images_dir),
                                   self.import_points)
        notes = "; ".join(description.get("notes", []))
        self.report({"INFO"}, f"imported {len(description['views'])} cameras" + (f" ({notes})" if notes else ""))
        return {"FINISHED"}


class _CaptureJob(_Reporting):
    """Reconstruct Photos and Reconstruct Video: a file browser first; one capture job at a time."""

    @classmethod
    def poll(cls, context):
        return not tasks.running("reconstruct")

    def invoke(self, context, event):
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}


class NEULF_OT_reconstruct(_CaptureJob, bpy.types.Operator):
    """Reconstruct a folder of photos with pycolmap in the background, then import it"""

    bl_idname = "neulf.reconstruct"
    bl_label = "Reconstruct Photos (pycolmap)"

    directory: StringProperty(subtype="DIR_PATH", description="Folder of photos")
    scene_dir: StringProperty(name="Scene Folder", subtype="DIR_PATH",
                              description="Where to write the COLMAP scene (default: next to the photos)")
    filter_folder: bpy.props.BoolProperty(default=True, options={"HIDDEN"})

    def run(self, context):
        photos = chosen_path(self.directory)
        if not photos or not Path(photos).is_dir():
            raise NeulfError("choose the folder that holds the photos.")
        out = chosen_path(self.scene_dir) or str(Path(photos).parent / f"{Path(photos).name}_neulf")
        start_reconstruction(context, photos, out)
        if not bpy.app.background:
            self.report({"INFO"}, f"reconstructing {photos} into {out} in the background")
        return {"FINISHED"}


def start_reconstruction(context, photos: str, out: str) -> None:
    """Reconstruct `photos` into the scene folder `out` in the background, then import it into
    the scene it was started from (where that file is still open)."""
    python, extra = worker_python(get_prefs(context))
    job = jobs.ReconstructJob(python, photos, out, env=jobs.core_environment(extra))
    scene_name, opened = context.scene.name, tasks.opened_files

    def done(job):
        scene = bpy.data.scenes.get(scene_name) if tasks.same_file_since(opened) else None
        if job.state["status"] != "finished" or scene is None:
            found = job.state["status"] == "finished"  # (another .blend was opened meanwhile)
            print(f"NeuLF: reconstruction {job.state['status']}: "
                  + (f"the scene is in {out}: import it with Import COLMAP / LLFF" if found
                     else str(job.state.get("error"))))
            return
        with bpy.context.temp_override(scene=scene):
            bpy.ops.neulf.import_colmap(directory=out)

    tasks.start("reconstruct", job, done)
    _wait_in_background(job, "reconstruction")


def _wait_in_background(job, what: str) -> None:
    """In background mode (scripts, tests) run the job to its end (its `done` included) and raise
    its failure; in the UI the timer drains it and the panel shows it."""
    if bpy.app.background:
        job.wait()
        tasks.poll_all()
        if job.state["status"] != "finished":
            raise NeulfError(f"{what} failed: {job.state['error']}")


class NEULF_OT_reconstruct_video(_CaptureJob, bpy.types.Operator):
    """Pick the sharpest frames of a capture's video as photos, reconstruct them with pycolmap in the background, then import it"""

    bl_idname = "neulf.reconstruct_video"
    bl_label = "Reconstruct Video (pycolmap)"

    filepath: StringProperty(subtype="FILE_PATH", description="The capture's video")
    filter_glob: StringProperty(default="*.mp4;*.mov;*.m4v;*.mkv;*.avi;*.webm;*.mts", options={"HIDDEN"})
    count: IntProperty(name="Photos", default=60, min=3, max=1000,
                       description="Photos to pick: the sharpest frame of each of that many equal stretches of the video")
    scene_dir: StringProperty(name="Scene Folder", subtype="DIR_PATH",
                              description="Where to write the COLMAP scene (default: next to the video)")

    def run(self, context):
        video = chosen_path(self.filepath)
        if not video or not Path(video).is_file():
            raise NeulfError("choose the video file of the capture.")
        stem = Path(video).stem
        out = chosen_path(self.scene_dir) or str(Path(video).parent / f"{stem}_neulf")
        photos = str(Path(out).parent / f"{Path(out).name}_frames")  # (beside the scene: reconstruct links them)
        python, extra = worker_python(get_prefs(context))
        job = jobs.FramesJob(python, video, photos, self.count, env=jobs.core_environment(extra))
        scene_name, opened = context.scene.name, tasks.opened_files

        def done(job):
            scene = bpy.data.scenes.get(scene_name) if tasks.same_file_since(opened) else None
            if job.state["status"] != "finished" or scene is None:
                print(f"NeuLF: frame picking {job.state['status']}: {job.state.get('error') or photos}")
                return
            with bpy.context.temp_override(scene=scene):
                start_reconstruction(bpy.context, photos, out)

        tasks.start("reconstruct", job, done)  # (one capture job at a time: the panel shows either)
        _wait_in_background(job, "frame picking")  # (in background mode, the reconstruction too)
        if not bpy.app.background:
            self.report({"INFO"}, f"picking frames of {video} into {photos}, then reconstructing into {out}")
        return {"FINISHED"}


# ----------------------------------------------------------------------------- model


class NEULF_OT_load_model(_Reporting, bpy.types.Operator):
    """Attach a trained NeuLF model folder to this scene"""

    bl_idname = "neulf.load_model"
    bl_label = "Load NeuLF Model"
    bl_options = {"REGISTER", "UNDO"}

    directory: StringProperty(subtype="DIR_PATH")
    filter_folder: bpy.props.BoolProperty(default=True, options={"HIDDEN"})

    def invoke(self, context, event):
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def run(self, context):
        path = chosen_path(self.directory)
        refuse_linked(context.scene, "load its model")
        restored = restore_metadata(context, path)
        if restored:
            self.report({"WARNING"}, restored)
        scene_meta = readable_model(context, path).get("scene", {})
        loaded = f"model loaded: {path}"
        fingerprint = scene_meta.get("fingerprint")
        if context.scene.neulf.fingerprint and fingerprint not in (None, context.scene.neulf.fingerprint):
            self.report({"WARNING"}, "the model was trained on another reconstruction than the imported cameras; "
                                     "its renders will not line up with them.")
        elif not context.scene.neulf.scene_dir and scene_meta.get("root") and Path(scene_meta["root"]).is_dir():
            try:  # (first, through the model's photos; a capture that fails to import leaves nothing half-built)
                imported = import_scene(context, scene_meta["root"], model_path=path)
                loaded += f"; its capture imported: {len(imported['views'])} cameras from {scene_meta['root']}"
            except NeulfError as exc:  # (rendering needs only the model: photos moved or not copied along)
                why = panel_words(str(exc))
                self.report({"WARNING"}, f"the capture it trained on could not be imported ({why}); the model renders "
                                         "without it (Import COLMAP / LLFF takes an Images folder)")
        attach_model(context, path)
        self.report({"INFO"}, loaded)
        return {"FINISHED"}


# ----------------------------------------------------------------------------- training


def refuse_unwritable_model_folder(out: str, chosen: bool) -> None:
    """Said before the training process starts, naming the panel's field: the default folder
    sits inside the capture's, which may be read-only (a downloaded dataset, a share)."""
    try:
        Path(out).mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=out):
            pass
    except OSError as exc:
        where = "" if chosen else " (the Model field is empty, so the model goes into the capture folder)"
        raise NeulfError(f"cannot write the model folder {out}{where}: {exc.strerror}; choose a folder you can write "
                         "in the panel's Model field.") from None


def start_training(context, *, minutes=None, steps=None):
    """Start (or continue) training the scene's model in a separate process."""
    refuse_linked(context.scene, "train its model")
    props = context.scene.neulf
    scene_dir = chosen_path(props.scene_dir)
    if not scene_dir:
        raise NeulfError("import a capture first (NeuLF > Import), then train.")
    out = chosen_path(props.model_dir) or default_model_dir(context.scene)  # (scene_dir: checked above)
    if not Path(out).is_dir() and props.last_status.startswith(model_not_found(out)):
        # (a .blend opened away from its model: start over only where the user names a new folder)
        raise NeulfError(f"the model folder {out} does not exist: move the .blend together with its model folder or "
                         "point Load Model at the model; to start a new model there, create the folder first (or "
                         "choose another).")
    refuse_unwritable_model_folder(out, chosen=bool(props.model_dir))
    owner = training_holder(out)
    if owner is not None:  # its checkpoints would overwrite ours, and the step to continue from is not known yet
        raise NeulfError(being_trained_message(out, owner, "it was started before, perhaps by a Blender that closed: "
                                                             "wait until the panel says it stopped, then press Train "
                                                             "to continue it"))
    resume = can_resume(out)
    resumed_from = None
    if resume:  # budgets count from the start of training: add to what is done (as the budget counts it)
        restored = restore_metadata(context, out)
        if restored:
            print(f"NeuLF: {restored}")
        done_steps, done_seconds = budget_done(out)
        resumed_from = done_steps
        if steps:
            steps = done_steps + int(steps)
        else:
            minutes = done_seconds / 60.0 + float(minutes)
    prefs = get_prefs(context)
    python, extra = worker_python(prefs)
    device = None if prefs is None or prefs.device == "AUTO" else prefs.device.lower()
    fast_field = get_preset(props.preset).field == "disparity"  # (its options mean nothing to the other fields)
    job = jobs.TrainJob(python, scene_dir, out, minutes=minutes, steps=steps, resume=resume, preset=props.preset,
                        scale=props.train_scale or None, images_dir=chosen_path(props.images_dir) or None, device=device,
                        env=jobs.core_environment(extra), sweep_teacher=CHOICE_OPTION[props.sweep_teacher],
                        depth_layers=props.depth_layers if fast_field else -1, appearance=CHOICE_OPTION[props.appearance],
                        refine_poses=CHOICE_OPTION[props.refine_poses],
                        back_surface=CHOICE_OPTION[props.back_surface] if fast_field else None,
                        stop_early=props.stop_early, two_starts=props.two_starts, members=props.members)
    job.state["resumed_from"] = resumed_from
    props.model_dir = store_path(out)
    props.last_status = (f"training from step {resumed_from}" if resume else "training")

    def done(job):
        for scene in scenes_of_model(out):  # (by folder: the user may have opened another .blend since)
            _show_training_result(scene, job.state, out)

    tasks.start("train", job, done)
    return job, resume


def _show_training_result(scene, state: dict, out: str) -> None:
    """A finished (cancelled, failed) training's status and model, in a scene of that model."""
    status = job_status_text(state) if state["status"] != "failed" else f"failed: {state['error']}"
    if state["status"] == "failed" and can_resume(out):
        # (where the last checkpoint left it: what Train continues from, e.g. after the process was killed)
        status = f"{status.rstrip('.')}; the model as last saved: {saved_progress_text(out, read_metadata(out))}"
    scene.neulf.last_status = status
    if state.get("val_psnr") is not None:
        scene.neulf.last_psnr = float(state["val_psnr"])
    if (Path(out) / METADATA_NAME).is_file():
        with bpy.context.temp_override(scene=scene):
            try:
                attach_model(bpy.context, out)
            except NeulfError:
                pass
            scene.neulf.last_status = status


# The panel's settings a continued model keeps as it was trained (TrainJob passes none of them on
# resume), by property, the model's train_config field and the panel's name.
KEPT_ON_CONTINUE = (("preset", "preset", "Preset"), ("train_scale", "scale", "Image Scale"),
                    ("sweep_teacher", "teacher", "Depth from Photos"), ("appearance", "appearance", "Varying Exposure"),
                    ("refine_poses", "refine_poses", "Refine Poses"), ("back_surface", "back_surface", "Back Surface"),
                    ("two_starts", "two_starts", "Two Starts"))


def _asked(props, name: str):
    """A panel setting as the trainer takes it; None where it is left to the rules (Auto, 0, on)."""
    value = getattr(props, name)
    if name == "train_scale":
        return value or None
    if name == "two_starts":
        return None if value else False
    return CHOICE_OPTION[value] if value in CHOICE_OPTION else value


def settings_kept_on_continue(props, saved: dict) -> list[str]:
    """The panel's settings asked for (not left to the rules) that differ from those the continued
    model was trained with, said as the panel names them (the preset alone had been said; Image
    Scale, Back Surface and the others were dropped without a word)."""
    kept = []
    for name, field, label in KEPT_ON_CONTINUE:
        asked, own = _asked(props, name), saved.get(field)
        if asked is None or own is None or asked == own:
            continue
        shown = ("On" if own else "Off") if isinstance(own, bool) else (f"'{own}'" if isinstance(own, str) else f"{own:g}")
        kept.append(f"{label} (the model's: {shown})")
    return kept


class NEULF_OT_train(_Reporting, bpy.types.Operator):
    """Train (or continue training) the light field in a separate process; Blender stays usable"""

    bl_idname = "neulf.train"
    bl_label = "Train NeuLF"

    minutes: FloatProperty(name="Minutes", default=0.0, min=0.0, description="0: the panel's setting")
    steps: IntProperty(name="Steps", default=0, min=0, description="0: the panel's setting")

    @classmethod
    def poll(cls, context):
        return not tasks.running("train")

    def run(self, context):
        props = context.scene.neulf
        steps = self.steps or (props.train_steps if not self.minutes else 0)
        minutes = self.minutes or props.train_minutes
        job, resume = start_training(context, minutes=None if steps else minutes, steps=steps or None)
        kept = settings_kept_on_continue(props, read_metadata(job.model_dir).get("train_config", {})) if resume else []
        if kept:  # (a model's network and what defines it cannot change; the panel's settings apply to a new one)
            self.report({"WARNING"}, f"the model keeps what it was trained with: {', '.join(kept)}; the panel's "
                                     "settings apply to a new model (choose another Model folder)")
        if not bpy.app.background:
            self.report({"INFO"}, (f"continuing from step {job.state['resumed_from']}" if resume else "training")
                        + " in the background")
            return {"FINISHED"}
        state = job.wait()
        tasks.poll_all()
        if state["status"] == "failed":
            raise NeulfError(f"training failed: {state['error']}")
        psnr = f", validation {state['val_psnr']:.2f} dB" if state.get("val_psnr") is not None else ""
        self.report({"INFO"}, f"training {job_status_text(state)}{psnr}")
        return {"FINISHED"}


class NEULF_OT_cancel_train(bpy.types.Operator):
    """Stop training; the model is saved where it is and can be continued later"""

    bl_idname = "neulf.cancel_train"
    bl_label = "Cancel Training"

    @classmethod
    def poll(cls, context):
        return tasks.running("train")

    def execute(self, context):
        tasks.get("train").cancel()
        self.report({"INFO"}, "stopping training: the model is saved where it is; Train continues it")
        return {"FINISHED"}


# ----------------------------------------------------------------------------- rendering


def active_camera_render(context, *, depth=True):
    """The active camera's render, read from Blender on its own thread: `(render, request)`,
    where `render(on_progress=None, should_stop=None)` touches no Blender data, so it may run
    on another thread, and returns the result with its depth in Blender units."""
    scene = context.scene
    request = capture.camera_request(scene, scene.camera)
    scale = request.pop("scale")
    core = get_core(context)
    args = dict(model_dir=model_dir(scene), depth=depth, chunk=scene.neulf.chunk,
                pixel_samples=pixel_samples_request(scene.neulf), **request, **capture.lens_request(scene.camera, scale))

    def render(on_progress=None, should_stop=None) -> dict:
        result = core.call("render", on_progress=on_progress, should_stop=should_stop, **args)
        if result.get("depth") is not None:
            result["depth"] = result["depth"] * scale  # model units -> Blender units
        return result

    return render, request


def render_active_camera(context, *, depth=True):
    render, request = active_camera_render(context, depth=depth)
    return render(), request


def show_render(result: dict, request: dict) -> list[tuple[str, str]]:
    """A finished render into the images 'NeuLF Render' and 'NeuLF Depth'; the reports to make."""
    capture.show_image(RENDER_IMAGE, result["rgb"])  # byte image: sRGB, stored as computed
    depth = np.nan_to_num(result["depth"], nan=0.0)
    capture.show_image(DEPTH_IMAGE, np.repeat(depth[..., None], 3, axis=2), float_buffer=True, non_color=True)
    notes = [("WARNING", note) for note in result.get("warnings", [])]
    return [*notes, ("INFO", f"rendered {request['width']}x{request['height']} into '{RENDER_IMAGE}'")]


def threaded_render_tick(call: jobs.ThreadCall, request: dict):
    """What the UI's threaded Render Camera does at a timer tick: `(status, status_text, reports)`,
    status 'RUNNING' while the thread works, else the operator's ending ('FINISHED' with the
    images shown, or 'CANCELLED'); status_text the status bar's line (None: Blender's own).
    A plain function, so scripts and headless tests run what the modal operator runs."""
    if call.running:
        return ("RUNNING", f"NeuLF: rendering {request['width']}x{request['height']}, {call.fraction:.0%} "
                           "(Esc cancels)", [])
    if call.cancelled:
        return "CANCELLED", None, [("INFO", "Render Camera cancelled")]
    if call.error is not None:
        return "CANCELLED", None, [("ERROR", panel_words(call.error))]
    return "FINISHED", None, show_render(call.result, request)


class NEULF_OT_render_camera(_Reporting, bpy.types.Operator):
    """Render the active camera through the light field into the images 'NeuLF Render' and 'NeuLF Depth'"""

    bl_idname = "neulf.render_camera"
    bl_label = "Render Camera (NeuLF)"

    def run(self, context):  # (blocking: scripts and background mode)
        result, request = render_active_camera(context)
        return self._report(show_render(result, request), "FINISHED")

    def invoke(self, context, event):
        """In the UI: rendered on a thread, with progress in the status bar and Esc to cancel (a
        large image takes minutes, which blocking would freeze Blender for)."""
        if bpy.app.background:
            return self.execute(context)
        try:
            render, self._request = active_camera_render(context)
        except NeulfError as exc:
            self.report({"ERROR"}, panel_words(str(exc)))
            return {"CANCELLED"}
        self._call = jobs.ThreadCall(render)
        self._timer = context.window_manager.event_timer_add(0.2, window=context.window)
        context.window_manager.modal_handler_add(self)
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        if event.type == "ESC" and event.value == "PRESS":
            self._call.cancel()
            return {"RUNNING_MODAL"}
        if event.type != "TIMER":
            return {"PASS_THROUGH"}
        status, text, reports = threaded_render_tick(self._call, self._request)
        context.workspace.status_text_set(text)
        if status == "RUNNING":
            return {"PASS_THROUGH"}
        context.window_manager.event_timer_remove(self._timer)
        return self._report(reports, status)

    def _report(self, reports, status: str):
        for level, line in reports:
            self.report({level}, line)
        return {status}


# ----------------------------------------------------------------------------- camera paths and video


SPIRAL_CAMERA = "NeuLF Spiral"
TRANSFORM_PATHS = ("location", "rotation_euler", "rotation_quaternion", "rotation_axis_angle")


def spiral_camera(scene, camera):
    """The camera to keyframe: the active one, unless it is one of the capture's (its pose is its
    photo's), then a camera of the spiral's own with that camera's lens, parented to the root
    like the capture's, made the scene camera."""
    if not capture.is_capture_camera(camera):
        return camera
    spiral = next((obj for obj in scene.objects if obj.get(capture.ROLE) == "spiral"), None)
    if spiral is None:
        spiral = bpy.data.objects.new(SPIRAL_CAMERA, camera.data.copy())
        spiral.data.name = SPIRAL_CAMERA
        spiral[capture.ROLE] = "spiral"
        scene.collection.objects.link(spiral)
        spiral.parent, spiral.matrix_parent_inverse = camera.parent, camera.matrix_parent_inverse.copy()
    scene.camera = spiral
    return spiral


def path_camera(scene, camera) -> dict | None:
    """The pinhole a camera path will be flown with -- the camera's lens (a capture camera's is
    the spiral's own camera's: a copy) at the scene's render size -- for the core to say which
    frames see past the capture and the lens that keeps them inside; None for a camera NeuLF
    does not render (said when it is rendered)."""
    if camera.type != "CAMERA" or camera.data.type != "PERSP":
        return None
    request = capture.camera_request(scene, camera)
    return {"K": request["K"], "width": request["width"], "height": request["height"], "lens_mm": camera.data.lens}


def clear_transform_keys(obj) -> None:
    """Remove the object's location and rotation keyframes, keeping the rest of its animation
    (a lens, a custom property, visibility)."""
    animation = obj.animation_data
    if animation is None or animation.action is None:
        return
    if animation.action.users > 1:  # (shared with another object: its keys stay its own)
        animation.action = animation.action.copy()
    fcurves = animation.action.fcurves if hasattr(animation.action, "fcurves") else None
    if getattr(animation, "action_slot", None) is not None:  # 4.4+: an action's curves are per slot
        from bpy_extras import anim_utils

        channelbag = anim_utils.action_get_channelbag_for_slot(animation.action, animation.action_slot)
        fcurves = channelbag.fcurves if channelbag is not None else None
    for fcurve in [fcurve for fcurve in (fcurves or []) if fcurve.data_path in TRANSFORM_PATHS]:
        fcurves.remove(fcurve)


class NEULF_OT_spiral_path(_Reporting, bpy.types.Operator):
    """Keyframe a smooth spiral through the capture on the active camera, or on a camera of its
    own where the active one is a capture camera (frame range set to it)"""

    bl_idname = "neulf.spiral_path"
    bl_label = "Spiral Camera Path"
    bl_options = {"REGISTER", "UNDO"}

    frames: IntProperty(name="Frames", default=0, min=0, description="0: the panel's setting")

    def run(self, context):
        scene = context.scene
        camera = scene.camera
        if camera is None:
            raise NeulfError("the scene has no active camera to animate.")
        refuse_linked(scene, "keyframe its camera")
        frames = self.frames or scene.neulf.spiral_frames
        path = get_core(context).call("spiral", model_dir=model_dir(scene), frames=frames,
                                      camera=path_camera(scene, camera))
        _collection, root = capture.find_capture(scene)
        root_matrix = root.matrix_world.copy() if root is not None else capture.Matrix.Identity(4)
        camera = spiral_camera(scene, camera)
        clear_transform_keys(camera)
        parent_inverse = (camera.parent.matrix_world.inverted() if camera.parent is not None
                          else capture.Matrix.Identity(4))
        start = scene.frame_start
        if camera.rotation_mode == "AXIS_ANGLE":
            camera.rotation_mode = "XYZ"
        previous = None
        for i, (R, t) in enumerate(zip(path["R"], path["t"])):
            world = capture.matrix_for_pose(root_matrix, R, t)
            location, rotation, _scale = (camera.matrix_parent_inverse.inverted() @ parent_inverse @ world).decompose()
            camera.location = location
            if camera.rotation_mode == "QUATERNION":
                if previous is not None:
                    rotation.make_compatible(previous)
                camera.rotation_quaternion = previous = rotation
                camera.keyframe_insert("rotation_quaternion", frame=start + i)
            else:  # continuous Euler angles: no 360-degree jumps between keys
                euler = rotation.to_euler(camera.rotation_mode, previous) if previous else rotation.to_euler(
                    camera.rotation_mode)
                camera.rotation_euler = previous = euler
                camera.keyframe_insert("rotation_euler", frame=start + i)
            camera.keyframe_insert("location", frame=start + i)
        scene.frame_end = start + len(path["R"]) - 1
        done = f"keyframed {len(path['R'])} frames on {camera.name}"
        warnings = path.get("warnings", [])
        self.report({"WARNING"} if warnings else {"INFO"}, "; ".join([done, *warnings]))
        return {"FINISHED"}


class NEULF_OT_render_video(_Reporting, bpy.types.Operator):
    """Render the frame range through the light field into a video (MP4, H.264)"""

    bl_idname = "neulf.render_video"
    bl_label = "Render Video (NeuLF)"

    filepath: StringProperty(subtype="FILE_PATH", default="//neulf.mp4")
    filter_glob: StringProperty(default="*.mp4", options={"HIDDEN"})

    def invoke(self, context, event):
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def run(self, context):
        scene = context.scene
        model_dir(scene)  # a clear error before the render starts
        if scene.camera is None:
            raise NeulfError("the scene has no active camera.")
        capture.camera_request(scene, scene.camera)  # (an orthographic or panoramic camera: said before the render)
        refuse_odd_video_size(scene.render)
        path = video_path(self.filepath)
        refuse_unwritable_video(path)
        saved = saved_render_settings(scene)
        scene.render.engine = "NEULF"
        configure_video(scene, path)
        written = Path(scene.render.frame_path(frame=scene.frame_start))  # (the name Blender gives the video)
        if not bpy.app.background:
            forget = restore_after_render(scene, saved, written)
            try:
                started = bpy.ops.render.render("INVOKE_DEFAULT", animation=True, scene=scene.name)
            except RuntimeError as exc:  # (the render refused to start: its handlers must not wait for it)
                forget()
                raise NeulfError(str(exc).removeprefix("Error: ").strip()) from None
            if "CANCELLED" in started:
                forget()
                raise NeulfError("Blender is rendering already: wait for that render to end, then Render Video again.")
            return {"FINISHED"}
        try:
            try:
                bpy.ops.render.render(animation=True, scene=scene.name)
            except RuntimeError as exc:  # (the engine's error for a frame, say a camera switched to by a marker)
                written.unlink(missing_ok=True)  # (a video cut short)
                raise NeulfError(str(exc).removeprefix("Error: ").strip()) from None
        finally:
            restore_render_settings(scene, saved)
        if not written.is_file():
            raise NeulfError(f"Blender wrote no video at {written}: see the console for why.")
        self.report({"INFO"}, f"wrote {written}")
        return {"FINISHED"}


class NEULF_OT_use_capture_camera(_Reporting, bpy.types.Operator):
    """Make the selected capture camera active and set the render size to its photo"""

    bl_idname = "neulf.use_capture_camera"
    bl_label = "Use Capture Camera"
    bl_options = {"REGISTER", "UNDO"}

    def run(self, context):
        obj = context.active_object
        if obj is None or obj.type != "CAMERA":
            raise NeulfError("select a camera first.")
        context.scene.camera = obj
        if not capture.apply_capture_camera(context.scene, obj):
            self.report({"INFO"}, f"{obj.name} is not a capture camera; the render size is unchanged")
        return {"FINISHED"}


class NEULF_OT_viewport_preview(_Reporting, bpy.types.Operator):
    """Fly through the light field: this 3D viewport's Rendered shading with the NeuLF engine (again: back to Solid)"""

    bl_idname = "neulf.viewport_preview"
    bl_label = "Preview in Viewport"

    def run(self, context):
        from .engine import NeulfRenderEngine

        space = context.space_data
        if space is None or space.type != "VIEW_3D":
            raise NeulfError("run Preview in Viewport from a 3D viewport's NeuLF panel.")
        if space.shading.type == "RENDERED" and context.scene.render.engine == NeulfRenderEngine.bl_idname:
            space.shading.type = "SOLID"
            return {"FINISHED"}
        model_dir(context.scene)  # (says what to do when there is no model to look through)
        context.scene.render.engine = NeulfRenderEngine.bl_idname
        space.shading.type = "RENDERED"
        return {"FINISHED"}


class NEULF_OT_composite_cg(_Reporting, bpy.types.Operator):
    """Put CG objects into the light field: the objects of the collection '<scene> CG Objects' render with Cycles through the scene camera in a second scene, and this scene's compositor shows them in front of or behind the light field by depth (Z Combine)"""

    bl_idname = "neulf.composite_cg"
    bl_label = "Composite CG Objects"
    bl_options = {"REGISTER", "UNDO"}

    def run(self, context):
        from .engine import NeulfRenderEngine

        scene = context.scene
        refuse_linked(scene, "set up its CG compositing")
        cg = compositing.set_up(scene, context.view_layer)
        scene.render.engine = NeulfRenderEngine.bl_idname  # the plate: F12 renders the light field here
        self.report({"INFO"}, f"objects in the collection '{scene.neulf.cg_collection.name}' render in the scene "
                              f"'{cg.name}' (Cycles) and are composited by depth at F12")
        return {"FINISHED"}


def menu_import(self, context):
    self.layout.operator(NEULF_OT_import_colmap.bl_idname, text="NeuLF Capture (COLMAP/LLFF)")


CLASSES = (NEULF_OT_import_colmap, NEULF_OT_reconstruct, NEULF_OT_reconstruct_video, NEULF_OT_load_model, NEULF_OT_train, NEULF_OT_cancel_train,
           NEULF_OT_render_camera, NEULF_OT_spiral_path,
           NEULF_OT_render_video, NEULF_OT_use_capture_camera, NEULF_OT_viewport_preview, NEULF_OT_composite_cg)

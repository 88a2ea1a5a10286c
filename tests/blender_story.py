"""The artist's story, told inside a bpy process: `python blender_story.py SETUP.json`.

Run by tests/test_blender_extension.py (not collected by pytest itself).  Needs only bpy and
numpy in the Blender process, as a stock Blender has: the capture, the reference values from
pycolmap and neulf_core, and the folder of photos are written beforehand by the pytest side
into SETUP.json.  With "worker_python" set (the bpy 4.2 run), neulf_core runs in that
interpreter, as it does for a user whose Blender has no torch.

Each step's outcome goes to the results file, checked by its own test.
"""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import sys
import time
import traceback
from pathlib import Path

import numpy as np

PACKAGE = "bl_ext.user_default.neulf"

# ----------------------------------------------------------------------------- the synthetic capture (numpy only)

WIDTH, HEIGHT = 64, 48
FX, FY, CX, CY = 58.0, 61.0, 33.3, 22.6          # non-square pixels, off-centre principal point
PLANE_POINT = np.array([0.0, 0.0, 4.0])
PLANE_NORMAL = np.array([0.25, -0.15, -1.0]) / np.linalg.norm([0.25, -0.15, -1.0])
GRID = [(x, y) for y in (-0.3, 0.0, 0.3) for x in (-0.3, 0.0, 0.3)]

STEPS = ["install", "import", "cameras_match_pycolmap", "slab_planes", "reimport_no_duplicates", "train_blocking",
         "train_options", "train_timer_resume", "panel_draws", "train_cancel", "train_cancel_resume", "train_killed", "members", "render_camera", "render_camera_thread", "render_only_model", "pixel_samples",
         "render_worker_process", "focus_at", "pick_focus_frame", "pick_focus_click", "root_scale", "engine_f12", "composite_cg", "viewport_preview", "spiral_video", "video_cut_short", "artist_settings", "capture_identity", "save_reload",
         "blend_moved", "linked_scene", "quit_while_training", "open_other_while_training", "reconstruct_photos", "user_errors", "real_captures", "dependencies_status",
         "install_dependencies"]


def _look_rotation(centre, target):
    z = target - centre
    z = z / np.linalg.norm(z)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z])


def scene_views():
    views = []
    for i, (x, y) in enumerate(GRID):
        centre = np.array([x, y, 0.1 * (i % 2)])
        R = _look_rotation(centre, np.array([0.05 * x, 0.05 * y, 4.0]))
        views.append({"name": f"view_{i:02d}.png", "R": R, "t": -R @ centre})
    return views


def K_matrix():
    return np.array([[FX, 0, CX], [0, FY, CY], [0, 0, 1.0]])


def trace(R, t, K=None, width=WIDTH, height=HEIGHT):
    """Colour (H, W, 3) and depth along the optical axis (H, W) of the textured tilted plane."""
    K = K_matrix() if K is None else K
    xs, ys = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    bearings = np.stack([(xs - K[0, 2]) / K[0, 0], (ys - K[1, 2]) / K[1, 1], np.ones_like(xs)], -1)
    directions = bearings @ R
    origin = -R.T @ t
    s = ((PLANE_POINT - origin) @ PLANE_NORMAL) / (directions @ PLANE_NORMAL)
    hit = origin + directions * s[..., None]
    e1 = np.cross(PLANE_NORMAL, [0, 1, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(PLANE_NORMAL, e1)
    a, b = hit @ e1, hit @ e2
    rgb = np.stack([0.5 + 0.35 * np.sin(2.1 * a + 0.5) * np.cos(1.3 * b),
                    0.5 + 0.35 * np.cos(1.7 * b - 0.3),
                    0.5 + 0.3 * np.sin(1.1 * (a + b))], -1)
    return np.clip(rgb, 0, 1), s * bearings[..., 2]  # bearing z = 1: s is the axis depth


def photo_bytes(rgb):
    """The 8-bit values make_scene writes to the PNG files."""
    return (rgb * 255 + 0.5).astype(np.uint8)


# ----------------------------------------------------------------------------- the story


class Story:
    def __init__(self, results: Path):
        self.results_path = results
        self.results: dict = {}

    def step(self, name, *needs):
        def wrap(fn):
            missing = [n for n in needs if not self.results.get(n, {}).get("ok")]
            started = time.monotonic()
            if missing:
                self.results[name] = {"ok": False, "detail": f"skipped: needs {', '.join(missing)}", "seconds": 0}
            else:
                try:
                    detail = fn()
                    self.results[name] = {"ok": True, "detail": detail or "", "seconds": time.monotonic() - started}
                except BaseException:  # noqa: BLE001 - every failure is reported, the story goes on
                    self.results[name] = {"ok": False, "detail": traceback.format_exc(), "seconds": time.monotonic() - started}
            print(f"[{name}] {'ok' if self.results[name]['ok'] else 'FAILED'} {self.results[name]['seconds']:.1f}s "
                  f"{str(self.results[name]['detail'])[-2000:]}", flush=True)
            self.results_path.write_text(json.dumps(self.results, indent=1, default=str))
            return fn
        return wrap


def reports_of(call) -> str:
    """What an operator reports (background Blender prints its reports on stdout: "Info: ...")."""
    import tempfile

    sys.stdout.flush()
    saved = os.dup(1)
    with tempfile.TemporaryFile("w+") as captured:
        os.dup2(captured.fileno(), 1)
        try:
            call()
        finally:
            sys.stdout.flush()
            os.dup2(saved, 1)
            os.close(saved)
        captured.seek(0)
        text = captured.read()
    print(text, end="")
    return text


def error_of(call) -> str:
    """The message of an operator's ERROR report (background mode raises it as RuntimeError)."""
    try:
        call()
    except RuntimeError as exc:
        return str(exc)
    raise AssertionError("expected an error report")


def run_story(setup: dict) -> None:  # noqa: C901 - one story, told in order
    import bpy
    from mathutils import Matrix

    zip_path, work = Path(setup["zip"]), Path(setup["work"])
    scene_dir, reference = Path(setup["scene_dir"]), setup["reference"]
    worker_python = setup.get("worker_python")
    story = Story(Path(setup["results"]))
    ctx = {}
    flip = np.diag([1.0, -1.0, -1.0, 1.0])

    def mod(name):
        return sys.modules[f"{PACKAGE}.neulf_blender.{name}"]

    def prefs():
        return bpy.context.preferences.addons[PACKAGE].preferences

    def cameras():
        coll = bpy.context.scene.neulf.capture_collection
        return sorted((o for o in coll.objects if o.type == "CAMERA"), key=lambda o: o["neulf_view"])

    def root():
        return bpy.context.scene.neulf.root

    def remove_scene_and_capture(scene):
        """A scene made by a step, with the capture imported into it (its objects and collection)."""
        collection = scene.neulf.capture_collection
        for obj in list(collection.objects if collection is not None else []):
            bpy.data.objects.remove(obj)
        if collection is not None:
            bpy.data.collections.remove(collection)
        bpy.data.scenes.remove(scene)

    def image_array(name):
        image = bpy.data.images[name]
        width, height = image.size
        pixels = np.empty(width * height * 4, np.float32)
        image.pixels.foreach_get(pixels)
        return pixels.reshape(height, width, 4)[::-1, :, :3]

    def _laplacian_variance(image: np.ndarray) -> float:
        """Sharpness: variance of the Laplacian of the grey image (blur lowers it)."""
        grey = np.asarray(image, dtype=np.float64)[..., :3].mean(axis=2)
        return float((-4 * grey[1:-1, 1:-1] + grey[:-2, 1:-1] + grey[2:, 1:-1] + grey[1:-1, :-2] + grey[1:-1, 2:]).var())

    def load_png(path):
        """A PNG's 8-bit values / 255 (a byte image's pixels are the file's values)."""
        image = bpy.data.images.load(str(path), check_existing=False)
        try:
            image.name = "_story_png"
            return image_array(image.name).copy()
        finally:
            bpy.data.images.remove(image)

    def psnr(a, b):
        return -10 * math.log10(max(float(np.mean((a - b) ** 2)), 1e-12))

    @story.step("install")
    def _():
        bpy.ops.extensions.package_install_files(filepath=str(zip_path), repo="user_default", enable_on_install=True)
        assert PACKAGE in bpy.context.preferences.addons, list(bpy.context.preferences.addons.keys())
        assert hasattr(bpy.types.Scene, "neulf") and hasattr(bpy.ops.neulf, "import_colmap")
        assert hasattr(bpy.ops.neulf, "pick_focus") and hasattr(bpy.types, "NEULF_PT_main")
        installed = Path(sys.modules[PACKAGE].__file__).parent
        assert (installed / "neulf_core" / "worker.py").is_file()
        ext_user = bpy.utils.extension_path_user(PACKAGE, create=True)
        assert str(work) in ext_user, ext_user
        if worker_python:  # as a user of a Blender without torch does, in the preferences
            prefs().python_path = worker_python
            assert not mod("preferences").get_core().in_process
        return f"Blender {bpy.app.version_string}, installed in {installed}" + (
            f", worker {worker_python}" if worker_python else "")

    @story.step("import", "install")
    def _():
        bpy.ops.wm.read_homefile(use_empty=True)
        result = bpy.ops.neulf.import_colmap(directory=str(scene_dir))
        assert result == {"FINISHED"}, result
        cams = cameras()
        assert [c["neulf_view"] for c in cams] == [v["name"] for v in scene_views()]
        assert [c.name for c in cams] == [Path(v["name"]).stem for v in scene_views()]
        scene = bpy.context.scene
        assert (scene.render.resolution_x, scene.render.resolution_y) == (WIDTH, HEIGHT)
        assert scene.camera in cams
        assert any(o.get("neulf_role") == "points" and len(o.data.vertices) == 270 for o in bpy.data.objects)

    @story.step("cameras_match_pycolmap", "import")
    def _():
        scene = bpy.context.scene
        points = np.array(reference["points"])
        root_inv = np.array(root().matrix_world.inverted())
        worst_px = worst_pose = 0.0
        for cam_obj, view, colmap_px in zip(cameras(), scene_views(), reference["colmap_px"]):
            bpy.context.view_layer.update()
            mod("capture").apply_capture_camera(scene, cam_obj)
            depsgraph = bpy.context.evaluated_depsgraph_get()
            r = scene.render
            P = np.array(cam_obj.calc_matrix_camera(depsgraph, x=r.resolution_x, y=r.resolution_y,
                                                    scale_x=r.pixel_aspect_x, scale_y=r.pixel_aspect_y))
            K_blender = np.array([[P[0, 0] * WIDTH / 2, 0, WIDTH / 2 * (1 - P[0, 2])],
                                  [0, P[1, 1] * HEIGHT / 2, HEIGHT / 2 * (1 + P[1, 2])], [0, 0, 1]])
            assert np.allclose(K_blender, K_matrix(), atol=1e-3), K_blender
            C = root_inv @ np.array(cam_obj.matrix_world) @ flip
            expected = np.eye(4)
            expected[:3, :3], expected[:3, 3] = view["R"].T, -view["R"].T @ view["t"]
            worst_pose = max(worst_pose, float(np.abs(C - expected).max()))
            # Project the sparse points with Blender's matrices (through the root, in world space)
            # and compare with pycolmap's projection (computed beforehand by the pytest side).
            world = (np.array(root().matrix_world) @ np.c_[points, np.ones(len(points))].T)
            clip = P @ np.array(cam_obj.matrix_world.inverted()) @ world
            ndc = clip[:2] / clip[3]
            blender_px = np.stack([(ndc[0] + 1) / 2 * WIDTH, (1 - ndc[1]) / 2 * HEIGHT], 1)
            worst_px = max(worst_px, float(np.abs(blender_px - np.array(colmap_px)).max()))
        assert worst_pose < 1e-5, worst_pose
        assert worst_px < 1e-3, worst_px
        return f"max projection error {worst_px:.2e} px, pose error {worst_pose:.1e}"

    @story.step("slab_planes", "import")
    def _():
        worst = 0.0
        root_inv = root().matrix_world.inverted()
        for plane in ("uv", "st"):
            obj = next(o for o in bpy.data.objects if o.get("neulf_role") == f"{plane}_plane")
            corners = np.array([list(root_inv @ obj.matrix_world @ v.co) for v in obj.data.vertices])
            worst = max(worst, float(np.abs(corners - np.array(reference["slab_corners"][plane])).max()))
        assert worst < 1e-5, worst
        return f"max corner error {worst:.1e}"

    @story.step("reimport_no_duplicates", "import")
    def _():
        before = len(bpy.data.objects), len(bpy.data.collections), len(bpy.data.cameras)
        root().matrix_world = Matrix.Rotation(0.3, 4, "Z") @ root().matrix_world  # the user's orientation ...
        kept = root().matrix_world.copy()
        assert bpy.ops.neulf.import_colmap(directory=str(scene_dir)) == {"FINISHED"}
        after = len(bpy.data.objects), len(bpy.data.collections), len(bpy.data.cameras)
        assert before == after, (before, after)
        assert np.allclose(np.array(root().matrix_world), np.array(kept))  # ... survives a re-import

    model = work / "model"

    @story.step("train_blocking", "import")
    def _():
        props = bpy.context.scene.neulf
        props.model_dir = str(model)
        started = time.monotonic()
        assert bpy.ops.neulf.train(steps=40) == {"FINISHED"}
        assert (model / "checkpoint.pt").is_file()
        meta = json.loads((model / "model.json").read_text())
        assert meta["progress"]["step"] == 40 and props.last_status.startswith("finished"), props.last_status
        return f"40 steps in {time.monotonic() - started:.1f} s, val {props.last_psnr:.2f} dB"

    @story.step("train_options", "import")
    def _():
        # The panel's "Varying Exposure", "Refine Poses" and "Stop Early" (off) reach training,
        # and the pose corrections come back on the status line.
        props = bpy.context.scene.neulf
        saved = props.model_dir
        options_model = work / "model_options"
        props.model_dir, props.appearance, props.refine_poses = str(options_model), "ON", "ON"
        props.stop_early = False
        try:
            assert bpy.ops.neulf.train(steps=10) == {"FINISHED"}
            meta = json.loads((options_model / "model.json").read_text())
            assert meta["train_config"]["appearance"] and meta["train_config"]["refine_poses"], meta["train_config"]
            assert meta["train_config"]["max_passes"] == 0, meta["train_config"]
            assert "poses corrected by" in props.last_status, props.last_status
            # the status line says when the default trained with the multi-view losses
            assert ("multi-view losses" in props.last_status) == meta["multiview_losses"], props.last_status
            status = props.last_status
            # Continued: the model keeps its network and what it was trained with, and says so in the
            # panel's words; a setting left to the rules (Auto) is not said.
            props.preset, props.appearance, props.train_scale, props.back_surface = "authors", "OFF", 0.25, "AUTO"
            report = reports_of(lambda: bpy.ops.neulf.train(steps=12))
            assert "Preset (the model's: 'fast'), Image Scale (the model's: " in report, report
            assert "Varying Exposure (the model's: On)" in report and "Back Surface" not in report, report
            assert json.loads((options_model / "model.json").read_text())["train_config"]["preset"] == "fast"
            # A new Authors model: "Depth from Photos" on Auto is the preset's choice (off: the authors'
            # recipe; it had always been sent on), and the fast field's options are not passed.
            props.model_dir, props.back_surface, props.depth_layers = str(work / "model_authors"), "ON", 8
            job, _ = mod("operators").start_training(bpy.context, steps=5)
            job.cancel()
            while mod("tasks").poll_all():
                time.sleep(0.05)
            passed = [a for a in job.argv if a.startswith("--")]
            assert "--preset" in passed and not {"--sweep-teacher", "--no-sweep-teacher", "--back-surface",
                                                 "--depth-layers"} & set(passed), passed
            return status

        finally:
            props.model_dir, props.appearance, props.refine_poses = saved, "AUTO", "AUTO"
            props.stop_early, props.preset, props.back_surface, props.depth_layers = True, "fast", "AUTO", -1
            props.train_scale = 0.0

    @story.step("train_timer_resume", "train_blocking")
    def _():
        # The UI path: start returns at once; the timer's poll (called here) drains the job.
        job, resumed = mod("operators").start_training(bpy.context, steps=20)
        assert resumed and mod("tasks").running("train")
        fractions = []
        while mod("tasks").poll_all():
            fractions.append(job.state["fraction"])
            time.sleep(0.1)
        assert job.state["status"] == "finished", job.state
        meta = json.loads((model / "model.json").read_text())
        assert meta["progress"]["step"] == 60, meta["progress"]
        assert bpy.context.scene.neulf.last_status.startswith("finished")
        return f"polled {len(fractions)} times, val {job.state['val_psnr']}"

    @story.step("panel_draws", "train_timer_resume")
    def _():
        """The N-panel drawn headless into a layout that records what it draws: every property it
        shows exists (Blender would draw a missing one as an error in the panel) and every button's
        operator is registered -- with a model, with each preset (the fast field's options greyed
        out for the others), and with a failed frame picking in the capture's job slot."""
        from types import SimpleNamespace

        drawn = []

        class RecordingLayout:
            def __init__(self):
                self.enabled, self.alert, self.active = True, False, True

            def column(self, **_options):
                return RecordingLayout()

            row = box = column

            def label(self, text="", **_options):
                drawn.append(("label", text, self.enabled))

            def separator(self, **_options):
                pass

            def progress(self, text="", **_options):
                drawn.append(("progress", text, self.enabled))

            def prop(self, data, name, **_options):
                assert name in data.bl_rna.properties, f"the panel draws {type(data).__name__}.{name}, which is not one"
                drawn.append(("prop", name, self.enabled))

            def operator(self, idname, **_options):
                group, name = idname.split(".")
                getattr(getattr(bpy.ops, group), name).get_rna_type()  # (KeyError where it is not registered)
                drawn.append(("operator", idname, self.enabled))

        props, tasks = bpy.context.scene.neulf, mod("tasks")
        panel = bpy.types.NEULF_PT_main
        for preset in ("authors", "fast"):
            props.preset = preset
            drawn.clear()
            panel.draw(SimpleNamespace(layout=RecordingLayout()), bpy.context)
            greyed = {name for kind, name, enabled in drawn if kind == "prop" and not enabled}
            assert greyed == ({"depth_layers", "back_surface"} if preset == "authors" else set()), (preset, greyed)
        buttons = sorted({name for kind, name, _ in drawn if kind == "operator"})
        shown = {name for kind, name, _ in drawn if kind == "prop"}
        assert {"pixel_samples", "chunk", "model_dir", "train_scale", "members"} <= shown, shown  # (the README's)
        kept = tasks.ACTIVE.get("reconstruct")
        picking = mod("jobs").FramesJob(worker_python or sys.executable, str(work / "no_such_clip.mp4"),
                                        str(work / "no_frames"), 10, env=mod("jobs").core_environment())
        tasks.ACTIVE["reconstruct"] = (picking, None)
        try:
            picking.wait(timeout=60)
            drawn.clear()
            panel.draw(SimpleNamespace(layout=RecordingLayout()), bpy.context)
        finally:
            if kept is None:
                tasks.ACTIVE.pop("reconstruct", None)
            else:
                tasks.ACTIVE["reconstruct"] = kept
        labels = " ".join(text for kind, text, _ in drawn if kind == "label")
        failed = labels[labels.index("Picking frames failed:"):] if "Picking frames failed:" in labels else ""
        assert failed and "does not exist" in failed, labels
        bpy.types.NEULF_PT_view_layer_passes.draw(SimpleNamespace(layout=RecordingLayout()), bpy.context)
        return f"{len(buttons)} buttons ({', '.join(buttons)}); the fast field's options greyed for authors; {failed[:90]}"

    @story.step("train_cancel", "train_timer_resume")
    def _():
        cancel_model = work / "model_cancel"
        props = bpy.context.scene.neulf
        saved = props.model_dir
        props.model_dir = str(cancel_model)
        # One run: this step is about Cancel and Train again; five minutes pass over the tiny
        # scene's pixels far more than 60 times, which would train two members (the members step).
        props.members = 1
        try:
            job, _ = mod("operators").start_training(bpy.context, minutes=5)
            deadline = time.monotonic() + 120
            while job.state.get("step", 0) < 5 and time.monotonic() < deadline:
                mod("tasks").poll_all()
                time.sleep(0.1)
            assert bpy.ops.neulf.cancel_train() == {"FINISHED"}
            job.wait(timeout=60)
            mod("tasks").poll_all()
            assert job.state["status"] == "cancelled", job.state
            assert (cancel_model / "checkpoint.pt").is_file()
            ctx["cancelled_step"] = job.state["step"]
        finally:
            props.model_dir, props.members = saved, 0
        return f"cancelled at step {job.state['step']}"

    @story.step("train_cancel_resume", "train_cancel")
    def _():
        # Cancel, then press Train again: training goes on from the cancelled model.
        cancel_model = work / "model_cancel"
        props = bpy.context.scene.neulf
        saved = props.model_dir
        before = json.loads((cancel_model / "model.json").read_text())["progress"]
        stopped = before["step"]
        assert before["status"] == "cancelled" and stopped == ctx["cancelled_step"], (before, ctx["cancelled_step"])
        shown = props.last_status  # what the panel shows after Cancel
        assert shown.startswith(f"cancelled at step {stopped}; Train continues it"), shown  # (+ the pose check's verdict)
        props.model_dir = str(cancel_model)
        try:
            report = reports_of(lambda: bpy.ops.neulf.train(steps=10))
            job = mod("tasks").get("train")
            assert "--resume" in job.argv and job.argv[job.argv.index("--steps") + 1] == str(stopped + 10), job.argv
            after = json.loads((cancel_model / "model.json").read_text())["progress"]
            assert after["status"] == "finished" and after["step"] == stopped + 10, after
            assert after["history"][:len(before["history"])] == before["history"]  # nothing of it lost
            assert f"finished at step {stopped + 10} (continued from step {stopped})" in report, report
            assert props.last_status.startswith(f"finished at step {stopped + 10} (continued from step {stopped})"), \
                props.last_status
        finally:
            props.model_dir = saved
        return f"Cancel: panel '{shown}'; Train again: {report.strip().splitlines()[-1]}"

    @story.step("train_killed", "train_cancel_resume")
    def _():
        """A training the system kills (SIGKILL, as its out-of-memory killer does): the panel says
        it was killed and where Train continues from, not 'ended without a message'."""
        import signal

        killed_model = work / "model_killed"
        shutil.copytree(work / "model_cancel", killed_model)
        saved_step = json.loads((killed_model / "model.json").read_text())["progress"]["step"]
        props = bpy.context.scene.neulf
        saved = props.model_dir
        props.model_dir = str(killed_model)
        try:
            job, resumed = mod("operators").start_training(bpy.context, minutes=5)
            assert resumed
            deadline = time.monotonic() + 120
            while job.state.get("step", 0) <= saved_step and time.monotonic() < deadline:  # (training, not starting)
                mod("tasks").poll_all()
                time.sleep(0.05)
            job.process.send_signal(signal.SIGKILL)
            while mod("tasks").poll_all():
                time.sleep(0.05)
            status = props.last_status
        finally:
            props.model_dir = saved
        assert job.state["status"] == "failed", job.state
        assert status == ("failed: the process was killed (SIGKILL, as the system does when memory runs out); the model "
                          f"as last saved: finished at step {saved_step}"), status
        return status

    @story.step("render_camera", "train_blocking")
    def _():
        scene = bpy.context.scene
        cam = cameras()[1]                       # a training view (view 0 is held out)
        scene.camera = cam
        mod("capture").apply_capture_camera(scene, cam)
        assert bpy.ops.neulf.render_camera() == {"FINISHED"}
        rendered = image_array("NeuLF Render")
        assert rendered.shape == (HEIGHT, WIDTH, 3)
        rgb, true_depth = trace(scene_views()[1]["R"], scene_views()[1]["t"])
        photo = photo_bytes(rgb).astype(np.float32) / 255
        model_psnr = psnr(rendered, photo)
        mean_psnr = psnr(photo.mean((0, 1), keepdims=True) + 0 * photo, photo)
        assert model_psnr > mean_psnr + 3, (model_psnr, mean_psnr)
        depth = image_array("NeuLF Depth")[..., 0]
        ctx["render"], ctx["depth"] = rendered, depth
        return f"PSNR {model_psnr:.2f} dB vs mean colour {mean_psnr:.2f} dB; depth median {np.median(depth):.3f} " \
               f"(true {np.median(true_depth):.3f})"

    @story.step("render_camera_thread", "render_camera")
    def _():
        """Render Camera as the UI runs it: on a thread, a timer tick at a time (the modal operator,
        which needs a window, only forwards Esc and timer events to threaded_render_tick)."""
        import threading

        operators, jobs = mod("operators"), mod("jobs")
        NeulfError = sys.modules[f"{PACKAGE}.neulf_core.errors"].NeulfError
        bpy.data.images.remove(bpy.data.images["NeuLF Render"])
        render, request = operators.active_camera_render(bpy.context)
        call, lines = jobs.ThreadCall(render), []
        while (tick := operators.threaded_render_tick(call, request))[0] == "RUNNING":
            lines.append(tick[1])
            time.sleep(0.02)
        status, text, reports = tick
        assert (status, text) == ("FINISHED", None) and reports[-1] == (
            "INFO", f"rendered {WIDTH}x{HEIGHT} into 'NeuLF Render'"), tick
        assert all(re.fullmatch(rf"NeuLF: rendering {WIDTH}x{HEIGHT}, \d+% \(Esc cancels\)", line) for line in lines), lines
        np.testing.assert_array_equal(image_array("NeuLF Render"), ctx["render"])  # the blocking render's image

        # Esc: the thread stops at its next band of rows (here before its first), nothing is shown.
        gate = threading.Event()

        def after_esc(on_progress, should_stop):
            gate.wait(60)
            return render(on_progress=on_progress, should_stop=should_stop)

        bpy.data.images.remove(bpy.data.images["NeuLF Render"])
        call = jobs.ThreadCall(after_esc)
        call.cancel()
        gate.set()
        call.wait(120)
        cancelled = operators.threaded_render_tick(call, request)
        assert cancelled == ("CANCELLED", None, [("INFO", "Render Camera cancelled")]), cancelled
        assert "NeuLF Render" not in bpy.data.images

        # The core's error on the thread: one line, in the panel's words.
        def failing(on_progress, should_stop):
            raise NeulfError("no photos found: pass --images DIR.")

        call = jobs.ThreadCall(failing)
        call.wait(60)
        failed = operators.threaded_render_tick(call, request)
        assert failed[:2] == ("CANCELLED", None) and failed[2][0][0] == "ERROR", failed
        assert "--images" not in failed[2][0][1], failed
        return f"{len(lines)} progress ticks, then the blocking render's image; Esc: {cancelled[2][0][1]}; " \
               f"an error: {failed[2][0][1]}"

    @story.step("members", "train_blocking")
    def _():
        # "Members" 2: two light fields, each with all the steps and half the rays a step (the
        # default's split on a CPU, members.default_split); the panel's render is their mean.
        props = bpy.context.scene.neulf
        saved = props.model_dir
        members_model = work / "model_members"
        assert props.members == 0, props.members  # the default: the trainer's rule
        props.model_dir, props.members = str(members_model), 2
        try:
            assert bpy.ops.neulf.train(steps=20) == {"FINISHED"}
            state = json.loads((members_model / "members.json").read_text())
            assert state["count"] == 2 and state["finished"] == [2], state
            steps = [json.loads((folder / "model.json").read_text())["progress"]["step"]
                     for folder in (members_model, members_model / "members" / "2")]
            assert steps == [20, 20] and state["split"] == "batch", (steps, state)
            assert props.last_status.startswith("finished at step 20"), props.last_status
            assert bpy.ops.neulf.render_camera() == {"FINISHED"}
            image = image_array("NeuLF Render")
            assert np.isfinite(image).all() and image.std() > 0.01
            # Stopped in the second member (as a process the system killed there leaves it): the status
            # is the second member's, not the first's "finished", which had read as nothing left to train.
            state_file, second = members_model / "members.json", members_model / "members" / "2" / "model.json"
            kept_state, kept_second = state_file.read_text(), second.read_text()
            state_file.write_text(json.dumps({**state, "finished": []}))
            stopped = json.loads(kept_second)
            stopped["progress"].update(status="training", step=12)
            second.write_text(json.dumps(stopped))
            try:
                interrupted = mod("model_folder").refresh_model_status(bpy.context.scene)
            finally:
                state_file.write_text(kept_state)
                second.write_text(kept_second)
            assert interrupted.startswith("member 2 of 2 interrupted at step 12 (last checkpoint); Train continues it"), \
                interrupted
        finally:
            props.model_dir, props.members = saved, 0
        return f"two members of 20 steps of half the batch; {props.last_status.split(';')[0]}"

    @story.step("render_only_model", "render_camera")
    def _():
        """A model folder shipped to render (model.pt, its checkpoint.pt left out, as the README
        describes): Load Model, Render Camera and a reopened file's status take it as the core
        does (Blender had refused it, and said Train would start it)."""
        folder = mod("model_folder")
        props = bpy.context.scene.neulf
        shipped = work / "model_shipped"
        shutil.copytree(model, shipped)
        (shipped / "checkpoint.pt").unlink()
        saved, status = props.model_dir, props.last_status
        try:
            assert bpy.ops.neulf.load_model(directory=str(shipped)) == {"FINISHED"}
            assert props.last_status == folder.RENDER_ONLY, props.last_status
            props.last_status = ""
            assert folder.refresh_model_status(bpy.context.scene) == folder.RENDER_ONLY
            assert bpy.ops.neulf.render_camera() == {"FINISHED"}
            shipped_psnr = psnr(image_array("NeuLF Render"), ctx["render"])
        finally:
            props.model_dir, props.last_status = saved, status
        assert shipped_psnr > 35, shipped_psnr  # (model.pt stores 8-bit grids and float16 weights)
        return f"model.pt alone renders {shipped_psnr:.1f} dB from the checkpoint's render"

    @story.step("pixel_samples", "render_camera")
    def _():
        props = bpy.context.scene.neulf
        # The default, Auto: the mean of 2 x 2 points a pixel at the trained resolution (this camera's),
        # the centre ray alone 1.5 times finer.
        assert props.pixel_samples == "AUTO", props.pixel_samples
        renders = {}
        try:
            for count in ("1", "4"):
                props.pixel_samples = count
                assert bpy.ops.neulf.render_camera() == {"FINISHED"}
                renders[count] = image_array("NeuLF Render")
        finally:
            props.pixel_samples = "AUTO"
        ctx["render_one_point"] = centres = renders["1"]
        assert np.array_equal(renders["4"], ctx["render"])  # (Auto took 4 here)
        change = np.abs(centres - ctx["render"])
        assert change.max() > 1 / 255 and change.mean() < 0.02, (change.max(), change.mean())
        assert bpy.ops.neulf.render_camera() == {"FINISHED"}
        assert np.array_equal(image_array("NeuLF Render"), ctx["render"])
        return f"1 point a pixel differs from 4 by {change.mean() * 255:.2f}/255 on average (at most {change.max() * 255:.0f}/255)"

    @story.step("render_worker_process", "render_camera")
    def _():
        prefs().render_mode = "WORKER"
        try:
            core = mod("preferences").get_core()
            assert not core.in_process
            assert bpy.ops.neulf.render_camera() == {"FINISHED"}
            worker_image = image_array("NeuLF Render")
            assert np.abs(worker_image - ctx["render"]).max() <= 1 / 255 + 1e-6
            assert mod("core")._worker is not None and mod("core")._worker.alive
        finally:
            prefs().render_mode = "AUTO"
            mod("core").shutdown()
        return "the worker process's render matches the first render"

    @story.step("focus_at", "render_camera")
    def _():
        scene = bpy.context.scene
        result, _request = mod("operators").render_active_camera(bpy.context)
        i, j = 40, 20
        dof = scene.camera.data.dof

        def focus_on_it():
            finished = []
            said = reports_of(lambda: finished.append(bpy.ops.neulf.focus_at(x=i + 0.5, y=j + 0.5)))
            assert finished == [{"FINISHED"}], finished
            return said

        said = focus_on_it()
        expected = float(result["depth"][j, i])
        assert dof.use_dof and dof.focus_object is None
        assert abs(dof.focus_distance - expected) < 1e-4 * expected, (dof.focus_distance, expected)
        # The report says how much the f-stop blurs a surface twice as far (thin lens: A f / D, in
        # render pixels): at this capture's size f/2.8 hardly blurs, which is said with what to do.
        blur = scene.camera.data.lens * 1e-3 / (2 * dof.aperture_fstop) * _request["K"][0][0] / dof.focus_distance
        assert blur < 1 and f"blurs {blur:.2g} px: hardly any depth of field" in said, (blur, said)
        assert "Scale the NeuLF Root by (the subject's real distance in metres) / " in said, said
        saved_fstop, dof.aperture_fstop = dof.aperture_fstop, dof.aperture_fstop * blur / 3  # three pixels
        try:
            shallow = focus_on_it()
        finally:
            dof.aperture_fstop = saved_fstop
        assert "blurs 3 px" in shallow and "hardly" not in shallow and "Warning" not in shallow, shallow
        ctx["focus"] = dof.focus_distance
        return (f"focus {dof.focus_distance:.4f} = model depth {expected:.4f}; said: "
                f"{said.strip().splitlines()[-1]}")

    # The eyedropper.  Headless Blender sends no mouse events and never draws, so the
    # viewport's matrices are never computed; but view3d.render_border maps a region box to
    # the camera frame with Blender's own ED_view3d_calc_camera_border, which is the oracle
    # for the add-on's frame maths here.
    def viewport():
        window = bpy.context.window
        area = next(a for a in window.screen.areas if a.type == "VIEW_3D")
        region = next(r for r in area.regions if r.type == "WINDOW")
        return window, area, region, area.spaces.active

    def blender_frame_point(x, y):
        """(u, v) of region point (x, y) in the camera frame (0..1 from the bottom-left), by Blender."""
        window, area, region, _space = viewport()
        with bpy.context.temp_override(window=window, area=area, region=region):
            bpy.ops.view3d.render_border(xmin=x, xmax=x + 1, ymin=y, ymax=y + 1, wait_for_input=False)
        render = bpy.context.scene.render
        return render.border_min_x, render.border_min_y

    def set_view(perspective, zoom=0.0, offset=(0.0, 0.0)):
        rv3d = viewport()[3].region_3d
        rv3d.view_perspective, rv3d.view_camera_zoom, rv3d.view_camera_offset = perspective, zoom, offset

    @story.step("pick_focus_frame", "import")
    def _():
        _window, _area, region, space = viewport()
        scene = bpy.context.scene
        capture_camera = scene.camera
        other = bpy.data.objects.new("Probe Camera", bpy.data.cameras.new("Probe Camera"))
        scene.collection.objects.link(other)
        other.data.sensor_fit, other.data.shift_x, other.data.shift_y, other.data.lens = "AUTO", 0.2, -0.1, 35.0
        cases = [("capture camera", capture_camera, None, 0.0, (0.0, 0.0)),
                 ("capture camera, zoomed and panned", capture_camera, None, 17.5, (0.13, -0.07)),
                 ("portrait, AUTO fit, shift, wide pixels", other, (48, 64, 1.2, 1.0), -8.0, (-0.2, 0.15))]
        worst, inside_points = 0.0, 0
        try:
            for _label, camera, size, zoom, offset in cases:
                scene.camera = camera
                if size is not None:
                    r = scene.render
                    r.resolution_x, r.resolution_y, r.pixel_aspect_x, r.pixel_aspect_y = size
                width, height = scene.render.resolution_x, scene.render.resolution_y
                set_view("CAMERA", zoom, offset)
                for x in np.linspace(0.08, 0.92, 9) * region.width:
                    for y in np.linspace(0.05, 0.85, 7) * region.height:
                        x, y = int(x), int(y)
                        u, v = blender_frame_point(x, y)
                        inside = 0.0 < u < 1.0 and 0.0 < v < 1.0
                        try:
                            px, py = mod("focus").click_pixel(scene, space, region, x, y)
                        except Exception as exc:  # noqa: BLE001 - outside the frame: a clear refusal
                            assert not inside and "inside the camera frame" in str(exc), (x, y, u, v, exc)
                            continue
                        assert inside, (x, y, u, v, px, py)
                        worst = max(worst, abs(px - u * width), abs(py - (1 - v) * height))
                        inside_points += 1
        finally:
            scene.camera = capture_camera
            mod("capture").apply_capture_camera(scene, capture_camera)
            bpy.data.objects.remove(other)
            scene.render.use_border = False
            set_view("PERSP")
        assert inside_points >= 30, inside_points
        assert worst < 2e-3, worst
        return f"{inside_points} clicks in 3 views agree with Blender's camera border within {worst:.1e} px"

    @story.step("pick_focus_click", "focus_at", "pick_focus_frame")
    def _():
        focus = mod("focus")
        window, _area, region, _space = viewport()
        scene = bpy.context.scene
        dof = scene.camera.data.dof
        width, height = scene.render.resolution_x, scene.render.resolution_y
        try:
            set_view("CAMERA", 17.5, (0.13, -0.07))
            # Aim at image point (40.5, 20.5) with Blender's own frame mapping (linear in x and y).
            (u0, v0), (u1, v1) = blender_frame_point(700, 400), blender_frame_point(800, 500)
            mx = round(700 + (40.5 / width - u0) * 100 / (u1 - u0))
            my = round(400 + (1 - 20.5 / height - v0) * 100 / (v1 - v0))
            u, v = blender_frame_point(mx, my)
            target = (u * width, (1 - v) * height)
            assert abs(target[0] - 40.5) < 0.1 and abs(target[1] - 20.5) < 0.1, target
            wx, wy = region.x + mx, region.y + my  # an event's mouse_x, mouse_y are window coordinates

            dof.use_dof, dof.focus_distance = False, 123.0
            for event in (("MOUSEMOVE", "NOTHING"), ("LEFTMOUSE", "RELEASE")):
                assert focus.pick_event(bpy.context, *event, wx, wy) == ("RUNNING_MODAL", None), event
            for event in (("ESC", "PRESS"), ("RIGHTMOUSE", "PRESS")):
                assert focus.pick_event(bpy.context, *event, wx, wy) == ("CANCELLED", None), event
            assert not dof.use_dof and dof.focus_distance == 123.0

            status, report = focus.pick_event(bpy.context, "LEFTMOUSE", "PRESS", wx, wy)
            assert status == "FINISHED" and report[1].startswith("focus distance "), (status, report)
            picked = dof.focus_distance
            assert dof.use_dof and dof.focus_object is None
            assert bpy.ops.neulf.focus_at(x=target[0], y=target[1]) == {"FINISHED"}
            assert abs(picked - dof.focus_distance) < 1e-4 * dof.focus_distance, (picked, dof.focus_distance)
            before_misses = dof.focus_distance  # focus_at's, equal to the click's within the tolerance above

            # Clicks that cannot focus: a one-line error, the focus left as it was.
            properties = next(a for a in window.screen.areas if a.type == "PROPERTIES")
            panel = next(r for r in properties.regions if r.type == "WINDOW")
            misses = {"another editor": (panel.x + panel.width // 2, panel.y + panel.height // 2)}
            set_view("CAMERA", -30.0)  # a small frame in the middle: the region's bottom edge is outside it
            misses["outside the frame"] = (region.x + region.width // 2, region.y + 20)
            messages = {}
            for label, (x, y) in misses.items():
                status, report = focus.pick_event(bpy.context, "LEFTMOUSE", "PRESS", x, y)
                assert status == "CANCELLED" and report[0] == "ERROR", (label, status, report)
                messages[label] = report[1]
            set_view("PERSP")
            status, report = focus.pick_event(bpy.context, "LEFTMOUSE", "PRESS", wx, wy)
            assert status == "CANCELLED" and report[0] == "ERROR", (status, report)
            messages["not through the camera"] = report[1]
            assert "3D viewport" in messages["another editor"], messages
            assert "camera frame" in messages["outside the frame"], messages
            assert "Numpad 0" in messages["not through the camera"], messages
            assert all("\n" not in m for m in messages.values())
            assert dof.focus_distance == before_misses
        finally:
            set_view("PERSP")
            scene.render.use_border = False
        return f"click at region ({mx}, {my}) -> pixel ({target[0]:.2f}, {target[1]:.2f}) -> focus {picked:.4f}; " + \
            " | ".join(messages.values())

    def _f12_renamed_root(scene):
        """F12 through the moved, renamed root: render_camera's image (the engine finds the root
        by the same pointer; by name it lost it and rendered 76 % of the pixels off the slab)."""
        render, engine, path = scene.render, scene.render.engine, scene.render.filepath
        settings = render.image_settings
        if hasattr(settings, "media_type"):
            settings.media_type = "IMAGE"
        settings.file_format, dither = "PNG", render.dither_intensity
        render.engine, render.dither_intensity, render.filepath = "NEULF", 0.0, str(work / "f12_renamed_root.png")
        try:
            bpy.ops.render.render(write_still=True)
        finally:
            render.engine, render.dither_intensity, render.filepath = engine, dither, path
        diff = np.abs(load_png(work / "f12_renamed_root.png") - ctx["render"]).max()
        assert diff <= 2 / 255 + 1e-6, diff

    def _full_copy_finds_its_own_root(scene):
        """Scene > New > Full Copy: the copy's capture is its own copied root and collection
        (found by name, the copy had turned the original's)."""
        find_capture = mod("capture").find_capture
        collection, r = find_capture(scene)
        with bpy.context.temp_override(scene=scene):
            assert bpy.ops.scene.new(type="FULL_COPY") == {"FINISHED"}
        copy = next(other for other in bpy.data.scenes if other not in (scene, scene.neulf.cg_scene)
                    and other.neulf.root is not None and other.neulf.root is not r)
        try:
            copied_collection, copied_root = find_capture(copy)
            assert copied_root.name in copy.objects and copied_root.name not in scene.objects, copied_root.name
            assert copied_collection is not collection and copied_collection in copy.collection.children_recursive
            copied_name = copied_root.name
        finally:
            objects = [obj for obj in copy.objects if obj.name not in scene.objects]
            collections = [c for c in copy.collection.children_recursive if c not in scene.collection.children_recursive]
            if bpy.context.window is not None:
                bpy.context.window.scene = scene
            bpy.data.scenes.remove(copy)
            for obj in objects:
                bpy.data.objects.remove(obj)
            for c in collections:
                bpy.data.collections.remove(c)
        assert bpy.context.scene is scene
        return f"a full copy of the scene finds its own root ({copied_name})"

    def _root_found_after_renames(scene, r):
        """The moved root is still the capture's after the user renames it and its collection
        (pointers), and in a .blend saved before the pointers (names, read only)."""
        props, collection = scene.neulf, scene.neulf.capture_collection
        names = r.name, collection.name
        try:
            r.name, collection.name = "Renamed root", "Renamed capture"
            assert bpy.ops.neulf.render_camera() == {"FINISHED"}
            assert np.abs(image_array("NeuLF Render") - ctx["render"]).max() <= 1 / 255 + 1e-6
            _f12_renamed_root(scene)
            copied = _full_copy_finds_its_own_root(scene)
            props.root, props.capture_collection = None, None  # an older .blend's names
            props.root_name, props.collection_name = r.name, collection.name
            assert mod("capture").find_capture(scene) == (collection, r)
        finally:
            props.root, props.capture_collection = r, collection
            props.root_name = props.collection_name = ""
            r.name, collection.name = names
        return f"renamed root and collection still found (pointers); {copied}; an older .blend's names read"

    @story.step("root_scale", "focus_at")
    def _():
        scene = bpy.context.scene
        r = root()
        original = r.matrix_world.copy()
        try:
            r.matrix_world = Matrix.Translation((1.0, -2.0, 0.5)) @ original @ Matrix.Scale(2.5, 4)
            bpy.context.view_layer.update()
            assert bpy.ops.neulf.focus_at(x=40.5, y=20.5) == {"FINISHED"}
            assert abs(scene.camera.data.dof.focus_distance - 2.5 * ctx["focus"]) < 1e-3 * ctx["focus"]
            assert bpy.ops.neulf.render_camera() == {"FINISHED"}  # the same view, the scene only moved
            assert np.abs(image_array("NeuLF Render") - ctx["render"]).max() <= 1 / 255 + 1e-6
            found_by = _root_found_after_renames(scene, r)
        finally:
            r.matrix_world = original
            bpy.context.view_layer.update()
        return found_by

    def _f12_depth_pass(scene):
        """F12 with a view layer's Z pass on, saved as a multilayer EXR (what a compositor
        reads): its Depth is render_camera's depth in scene units, its Combined render_camera's
        image; each view layer gets its own passes (a second layer asks for Z, the first does
        not), and a root scaled 2.5 times scales the depth so.  With square pixels: Blender
        5.0.1 cannot write a multilayer EXR with a Z pass whose pixel aspect is not 1 (Cycles
        neither; the panel says so), and this capture's pixels are not."""
        from exr_file import read_exr

        render, settings, first = scene.render, scene.render.image_settings, scene.view_layers[0]
        aspect, depth = (render.pixel_aspect_x, render.pixel_aspect_y), settings.color_depth
        assert aspect[0] != aspect[1], aspect  # the capture's fx != fy
        panel = bpy.types.NEULF_PT_view_layer_passes
        assert panel.poll(bpy.context)  # the pass's checkbox is shown with the NeuLF engine
        first.use_pass_z = True
        hint = mod("panel").multilayer_exr_hint(scene)
        assert (hint is not None) == (bpy.app.version[:2] == (5, 0)), hint
        first.use_pass_z = False
        second = scene.view_layers.new("Second")
        second.use_pass_z = True
        r, original = root(), root().matrix_world.copy()

        def f12(name):
            render.filepath = str(work / name)
            bpy.ops.render.render(write_still=True)
            return read_exr(work / name)

        try:
            render.pixel_aspect_x = render.pixel_aspect_y = 1.0
            assert mod("panel").multilayer_exr_hint(scene) is None
            assert bpy.ops.neulf.render_camera() == {"FINISHED"}
            reference, reference_depth = image_array("NeuLF Render"), image_array("NeuLF Depth")[..., 0]
            if hasattr(settings, "media_type"):
                settings.media_type = "MULTI_LAYER_IMAGE"  # (5.0; 4.2 has no media_type)
            settings.file_format = "OPEN_EXR_MULTILAYER"
            settings.color_depth, settings.exr_codec = "32", "NONE"
            channels = f12("f12_passes.exr")
            r.matrix_world = original @ Matrix.Scale(2.5, 4)  # the camera, a child of the root, with it
            bpy.context.view_layer.update()
            scaled = f12("f12_passes_scaled.exr")
        finally:
            r.matrix_world = original
            scene.view_layers.remove(second)
            bpy.context.view_layer.update()
            render.pixel_aspect_x, render.pixel_aspect_y = aspect
            if hasattr(settings, "media_type"):
                settings.media_type = "IMAGE"
            settings.file_format, settings.color_depth = "PNG", depth
        layers = sorted({name.split(".")[0] for name in channels})
        assert layers == sorted([first.name, "Second"]), layers
        assert f"{first.name}.Depth.Z" not in channels  # no Z asked for there
        z = channels["Second.Depth.Z"]
        for layer in layers:  # each layer its own image (before, the second overwrote the first's)
            linear = np.stack([channels[f"{layer}.Combined.{c}"] for c in "RGB"], axis=2)
            srgb = np.where(linear <= 0.0031308, 12.92 * linear,
                            1.055 * np.clip(linear, 0, None) ** (1 / 2.4) - 0.055)
            colour = np.abs(srgb - reference).max()
            assert colour <= 1 / 255 + 1e-6, (layer, colour)
        seen = reference_depth > 0  # render_camera's depth image holds 0 where the field has none
        assert seen.mean() > 0.9, seen.mean()
        error = np.abs(z[seen] - reference_depth[seen]).max() / reference_depth[seen].max()
        assert error < 1e-4, error
        assert np.all(z[~seen] == np.float32(1e10)), np.unique(z[~seen])
        ratio = np.median(scaled["Second.Depth.Z"][seen] / z[seen])
        assert abs(ratio - 2.5) < 1e-3, ratio
        return (f"its Z pass in a multilayer EXR is render_camera's depth (median {np.median(z[seen]):.3f}, "
                f"largest difference {error:.1e} of the farthest; {np.count_nonzero(~seen)} pixels empty), "
                f"{ratio:.4f} times it with the root scaled 2.5 times, each of 2 view layers its own passes, and its "
                f"Combined render_camera's image within {colour * 255:.2f}/255"
                + (f"; non-square pixels: '{hint}'" if hint else ""))

    def _f12_transparent_film(scene):
        """Film > Transparent: alpha 0 (and no colour) where a pixel's ray misses the light slab,
        1 elsewhere.  The camera turned 70 degrees sideways, so part of its view leaves the slab."""
        camera, settings = scene.camera, scene.render.image_settings
        original = camera.matrix_world.copy()
        scene.render.film_transparent = True
        settings.color_mode = "RGBA"
        try:
            camera.matrix_world = original @ Matrix.Rotation(math.radians(70), 4, "Y")
            bpy.context.view_layer.update()
            scene.render.filepath = str(work / "f12_transparent.png")
            bpy.ops.render.render(write_still=True)
            image = bpy.data.images.load(str(work / "f12_transparent.png"), check_existing=False)
            width, height = image.size
            rgba = np.empty(width * height * 4, np.float32)
            image.pixels.foreach_get(rgba)
            bpy.data.images.remove(image)
        finally:
            camera.matrix_world = original
            bpy.context.view_layer.update()
            scene.render.film_transparent = False
            settings.color_mode = "RGB"
        rgba = rgba.reshape(height, width, 4)
        alpha = rgba[..., 3]
        off = alpha == 0
        assert set(np.unique(alpha).tolist()) <= {0.0, 1.0}, np.unique(alpha)
        assert 0.1 < off.mean() < 0.9, off.mean()  # part of the view on the slab, part off it
        assert np.all(rgba[off][:, :3] == 0), rgba[off][:, :3].max()
        return f"with a transparent film {off.mean():.0%} of a camera turned 70 degrees is off the slab: alpha 0, no colour"

    def _f12_render_region(scene, still):
        """F12 with a render region (Output > Format > Render Region), cropped to it and not:
        the region's pixels are the full frame's, the rest of an uncropped frame empty."""
        render = scene.render
        render.use_border = True
        render.border_min_x, render.border_max_x, render.border_min_y, render.border_max_y = 0.25, 0.75, 0.5, 1.0
        left, top, width, height = mod("convert").border_region(WIDTH, HEIGHT, (0.25, 0.75), (0.5, 1.0))
        region = still[top:top + height, left:left + width]
        try:
            for crop in (True, False):
                render.use_crop_to_border = crop
                bpy.ops.render.render(write_still=True)
                image = load_png(work / "f12.png")
                if crop:
                    assert image.shape[:2] == (height, width), image.shape
                    diff = np.abs(image - region).max()
                else:
                    assert image.shape[:2] == (HEIGHT, WIDTH), image.shape
                    diff = np.abs(image[top:top + height, left:left + width] - region).max()
                    outside = np.ones((HEIGHT, WIDTH), bool)
                    outside[top:top + height, left:left + width] = False
                    assert image[outside][:, :3].max() == 0.0, image[outside][:, :3].max()
                assert diff <= 2 / 255 + 1e-6, (crop, diff)
        finally:
            render.use_border = render.use_crop_to_border = False
        return f"a render region ({width} x {height}) cropped and not: its pixels the full frame's"

    def _f12_stereo(scene):
        """F12 with Stereoscopy (Stereo 3D, parallel eyes 0.2 apart about the camera): each eye is
        Render Camera's image of the camera moved half that to its side."""
        render, camera = scene.render, scene.camera
        stereo, settings = camera.data.stereo, render.image_settings
        saved = stereo.convergence_mode, stereo.interocular_distance, stereo.pivot, settings.views_format
        render.use_multiview, render.views_format = True, "STEREO_3D"
        stereo.convergence_mode, stereo.interocular_distance, stereo.pivot = "PARALLEL", 0.2, "CENTER"
        settings.views_format = "INDIVIDUAL"
        render.filepath = str(work / "f12_stereo")
        try:
            bpy.ops.render.render(write_still=True)
            eyes = {side: load_png(next(work.glob(f"f12_stereo_{side}*.png"))) for side in "LR"}
        finally:
            render.use_multiview = False
            stereo.convergence_mode, stereo.interocular_distance, stereo.pivot, settings.views_format = saved
            render.filepath = str(work / "f12.png")
        differences = []
        for side, sign in (("L", -1.0), ("R", 1.0)):
            eye = camera.copy()
            scene.collection.objects.link(eye)
            eye.matrix_world = camera.matrix_world.copy()
            eye.matrix_world.translation = camera.matrix_world.translation + camera.matrix_world.to_3x3().normalized().col[0] * (0.1 * sign)
            scene.camera = eye
            try:
                assert bpy.ops.neulf.render_camera() == {"FINISHED"}
            finally:
                scene.camera = camera
                bpy.data.objects.remove(eye)
            differences.append(np.abs(eyes[side] - image_array("NeuLF Render")).max())
        apart = np.abs(eyes["L"] - eyes["R"]).mean()
        assert max(differences) <= 2 / 255 + 1e-6 and apart > 0.01, (differences, apart)
        return (f"stereo: each eye Render Camera's image of the camera moved 0.1 to its side within "
                f"{max(differences) * 255:.1f}/255 (the eyes differ by {apart * 255:.1f}/255 on average)")

    @story.step("engine_f12", "render_camera")
    def _():
        scene = bpy.context.scene
        scene.camera.data.dof.use_dof = False  # first the pinhole, as render_camera rendered it
        scene.render.engine = "NEULF"
        scene.render.dither_intensity = 0.0  # Blender's noise when it writes 8 bits (4.2: up to 1/255 more)
        settings = scene.render.image_settings
        if hasattr(settings, "media_type"):
            settings.media_type = "IMAGE"
        settings.file_format = "PNG"
        out = work / "f12.png"
        scene.render.filepath = str(out)
        bpy.ops.render.render(write_still=True)
        still = load_png(out)
        diff = np.abs(still - ctx["render"]).max()
        assert diff <= 2 / 255 + 1e-6, diff
        region = _f12_render_region(scene, still)
        region += "; " + _f12_stereo(scene)
        if "render_one_point" in ctx:  # F12 follows the panel's Pixel Samples too
            scene.neulf.pixel_samples = "1"
            try:
                bpy.ops.render.render(write_still=True)
            finally:
                scene.neulf.pixel_samples = "AUTO"
            one = load_png(out)
            to_one, to_four = (np.abs(one - ctx[k]).mean() for k in ("render_one_point", "render"))
            assert to_one < to_four, (to_one, to_four)
            bpy.ops.render.render(write_still=True)  # the 4-point still again, for what follows
        passes = _f12_depth_pass(scene)
        assert "NEULF" in bpy.types.DATA_PT_camera_dof.COMPAT_ENGINES
        # Depth of field: a wide aperture focused far behind the scene blurs the image
        # (synthetic aperture through the model) without changing its overall colour.
        dof = scene.camera.data.dof
        dof.use_dof, dof.focus_object, dof.focus_distance, dof.aperture_fstop = True, None, 1000.0, 0.05
        out_dof = work / "f12_dof.png"
        scene.render.filepath = str(out_dof)
        bpy.ops.render.render(write_still=True)
        dof.use_dof = False
        blurred = load_png(out_dof)
        change = np.abs(blurred - still).mean()
        sharpness = _laplacian_variance(blurred) / _laplacian_variance(still)
        assert sharpness < 0.5 and abs(blurred.mean() - still.mean()) < 0.03, (sharpness, blurred.mean(), still.mean())
        transparent = _f12_transparent_film(scene)
        return (f"F12 matches render_camera within {diff * 255:.1f}/255; {region}; {passes}; DOF keeps {sharpness:.0%} of the "
                f"sharpness (variance of the Laplacian) and changes pixels by {change * 255:.1f}/255 on average; "
                f"{transparent}")

    def _cube_depth(cg, camera, scene):
        """Depth along the camera's axis of the CG scene's first surface through each pixel
        centre (Blender's own ray casts), inf where none."""
        from mathutils import Vector

        K = mod("capture").camera_request(scene, camera)["K"]
        frame = camera.matrix_world.to_3x3().normalized()
        origin, forward = camera.matrix_world.translation.copy(), -frame.col[2]
        depsgraph = cg.view_layers[0].depsgraph
        depsgraph.update()  # (4.2 evaluates a scene that is not the window's only when asked)
        depth = np.full((HEIGHT, WIDTH), np.inf)
        for row in range(HEIGHT):
            for col in range(WIDTH):
                local = Vector(((col + 0.5 - K[0][2]) / K[0][0], -(row + 0.5 - K[1][2]) / K[1][1], -1.0))
                hit, location, *_ = cg.ray_cast(depsgraph, origin, (frame @ local).normalized())
                if hit:
                    depth[row, col] = (location - origin).dot(forward)
        return depth

    def _users_compositor_tree(scene):
        """5.0: the tree Blender's New button makes in the compositor (Render Layers, Reroute,
        Viewer, Group Output), assigned to the scene; 4.2 (a tree of the scene's own): None."""
        if not hasattr(scene, "compositing_node_group"):
            return None
        tree = bpy.data.node_groups.new("Users Compositing", "CompositorNodeTree")
        for kind in ("CompositorNodeRLayers", "NodeReroute", "CompositorNodeViewer", "NodeGroupOutput"):
            tree.nodes.new(kind)
        scene.compositing_node_group = tree
        return tree

    def _composite_stereo(scene, camera):
        """Stereoscopy on (parallel eyes 0.4 apart about the camera): said as drift until pressed
        again, then each eye's composite shows the cube, shifted between the eyes (the CG scene
        had rendered no eye at all)."""
        compositing = mod("compositing")
        render, stereo, settings = scene.render, camera.data.stereo, scene.render.image_settings
        saved = stereo.convergence_mode, stereo.interocular_distance, stereo.pivot, settings.views_format
        render.use_multiview, render.views_format = True, "STEREO_3D"
        stereo.convergence_mode, stereo.interocular_distance, stereo.pivot = "PARALLEL", 0.4, "CENTER"
        settings.views_format = "INDIVIDUAL"
        try:
            assert "use_multiview" in (compositing.out_of_step(scene) or "")
            assert bpy.ops.neulf.composite_cg() == {"FINISHED"} and compositing.out_of_step(scene) is None
            render.filepath = str(work / "composite_stereo")
            bpy.ops.render.render(write_still=True)
            eyes = [load_png(next(work.glob(f"composite_stereo_{side}*.png"))) for side in "LR"]
        finally:
            render.use_multiview = False
            stereo.convergence_mode, stereo.interocular_distance, stereo.pivot, settings.views_format = saved
            render.filepath = str(work / "composite.png")
            assert bpy.ops.neulf.composite_cg() == {"FINISHED"}
        red = [np.abs(eye - np.array([1.0, 0.0, 0.0])).max(axis=2) < 0.06 for eye in eyes]
        centres = [np.nonzero(mask)[1].mean() if mask.any() else float("nan") for mask in red]
        assert min(mask.sum() for mask in red) > 50 and abs(centres[0] - centres[1]) > 0.5, \
            ([mask.sum() for mask in red], centres)
        return (f"stereo: the cube in both eyes ({red[0].sum()} and {red[1].sum()} pixels, its centre "
                f"{centres[0] - centres[1]:.1f} pixels apart)")

    def _composite_camera_switch(scene, camera, cg, cube_depth):
        """A camera-switching marker at frame 2 to a second camera, 0.8 units to the first one's
        right: the CG scene gets the switch, so frame 2's composite shows the cube where the
        second camera sees it, not where the first does."""
        compositing = mod("compositing")
        second = camera.copy()
        second.name = "story_cg_second_camera"
        scene.collection.objects.link(second)
        second.matrix_world.translation = camera.matrix_world.translation + camera.matrix_world.to_3x3().col[0] * 0.8
        switch = scene.timeline_markers.new("story_switch", frame=2)
        switch.camera = second
        first = scene.timeline_markers.new("story_first", frame=scene.frame_start)
        first.camera = camera
        try:
            mismatch = compositing.out_of_step(scene)
            assert "camera markers" in (mismatch or ""), mismatch
            assert bpy.ops.neulf.composite_cg() == {"FINISHED"}
            assert [(m.frame, m.camera) for m in cg.timeline_markers if m.camera] == [(1, camera), (2, second)]
            scene.frame_set(2)
            assert scene.camera is second and compositing.out_of_step(scene) is None  # no drift said mid-switch
            bpy.ops.render.render(write_still=True)
            composite = load_png(work / "composite.png")
            second_depth = _cube_depth(cg, second, scene)
            switch.frame = 3  # moved later: said until pressed again
            assert "camera markers" in (compositing.out_of_step(scene) or "")
        finally:
            scene.frame_set(scene.frame_start)
            for marker in (switch, first):
                scene.timeline_markers.remove(marker)
            scene.camera = camera
            bpy.data.objects.remove(second)
        red = np.abs(composite - np.array([1.0, 0.0, 0.0])).max(axis=2) < 0.06
        seen_first, seen_second = np.isfinite(cube_depth), np.isfinite(second_depth)
        only_first = seen_first & ~seen_second
        assert only_first.sum() > 50 and red.sum() > 50, (only_first.sum(), red.sum())
        assert (red & only_first).sum() == 0 and (red & ~seen_second).sum() <= 0.02 * red.sum(), \
            ((red & only_first).sum(), (red & ~seen_second).sum())
        return (f"frame 2's switch to a second camera copied: {red.sum()} cube pixels, none of them where only the "
                f"first camera sees the cube ({only_first.sum()} pixels)")

    @story.step("composite_cg", "engine_f12")
    def _():
        # A CG cube set astride the light field's surface: Composite CG Objects renders it with
        # Cycles through the scene camera, and F12's compositor shows it where it is nearer than
        # the light field's depth (Z Combine).  Checked against the cube's own depth, by Blender's
        # ray casts through each pixel centre, and render_camera's image and depth.
        from mathutils import Euler

        scene, camera = bpy.context.scene, bpy.context.scene.camera
        compositing = mod("compositing")
        plate, plate_depth = ctx["render"], ctx["depth"]
        frame = camera.matrix_world.to_3x3().normalized()
        origin, forward = camera.matrix_world.translation.copy(), -frame.col[2]
        centre = origin + forward * (float(np.median(plate_depth[plate_depth > 0])) + 0.45)  # its front astride
        half = 0.7
        corners = [(x, y, z) for x in (-half, half) for y in (-half, half) for z in (-half, half)]
        faces = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
        mesh = bpy.data.meshes.new("story_cg_cube")
        mesh.from_pydata(corners, [], faces)
        material = bpy.data.materials.new("story_cg_red")
        material.use_nodes = True
        nodes = material.node_tree.nodes
        nodes.clear()
        emission, output = nodes.new("ShaderNodeEmission"), nodes.new("ShaderNodeOutputMaterial")
        emission.inputs["Color"].default_value = (1.0, 0.0, 0.0, 1.0)
        material.node_tree.links.new(emission.outputs[0], output.inputs["Surface"])
        mesh.materials.append(material)
        cube = bpy.data.objects.new("story_cg_cube", mesh)
        cube.location = centre
        cube.rotation_euler = Euler((0.5, 0.7, 0.3))  # faces slanted across the light field's surface

        scenes_before = len(bpy.data.scenes)
        scene.camera = None
        refused = error_of(lambda: bpy.ops.neulf.composite_cg())  # no camera: said, nothing made
        scene.camera = camera
        assert "set a scene camera first" in refused and len(bpy.data.scenes) == scenes_before
        users_tree = _users_compositor_tree(scene)
        refused_tree = "the user's compositor group kept, with a fake user"
        try:
            if users_tree is None:  # 4.2: the scene's own tree with a node of the user's is refused, untouched
                scene.use_nodes = True
                users_own = scene.node_tree.nodes.new("CompositorNodeBlur")
                scene.use_nodes = False
                refused_tree = error_of(lambda: bpy.ops.neulf.composite_cg())
                assert "compositor node tree of its own" in refused_tree and not scene.use_nodes, refused_tree
                scene.node_tree.nodes.remove(users_own)
            assert bpy.ops.neulf.composite_cg() == {"FINISHED"}
            cg, objects = scene.neulf.cg_scene, scene.neulf.cg_collection
            assert cg.neulf.is_cg_scene and cg.cycles.samples == compositing.CG_SAMPLES
            if users_tree is not None:  # 5.0: a group of its own; the user's stays in the file
                assert scene.compositing_node_group is not users_tree and users_tree.use_fake_user
            with bpy.context.temp_override(scene=cg):  # run in the CG scene: said, nothing made
                in_cg = error_of(lambda: bpy.ops.neulf.composite_cg())
            assert "run Composite CG Objects in the light field's scene" in in_cg, in_cg
            objects.objects.link(cube)
            cg.cycles.samples = 16
            name = scene.name
            scene.name, objects.name = "Renamed", "Renamed objects"  # the links are pointers, not names
            assert bpy.ops.neulf.composite_cg() == {"FINISHED"}  # again: brought up to date, not doubled
            scene.name = name
            assert scene.neulf.cg_scene is cg and scene.neulf.cg_collection is objects
            assert len(bpy.data.scenes) == scenes_before + 1
            assert len(cg.collection.children) == 1 and len(cg.collection.objects) == 1
            settings = scene.render.image_settings
            if hasattr(settings, "media_type"):
                settings.media_type = "IMAGE"
            settings.file_format, settings.color_mode = "PNG", "RGB"
            scene.render.filepath = str(work / "composite.png")
            bpy.ops.render.render(write_still=True)
            composite = load_png(work / "composite.png")
            cube_depth = _cube_depth(cg, camera, scene)
            assert compositing.out_of_step(scene) is None
            switched = _composite_camera_switch(scene, camera, cg, cube_depth)
            switched += "; " + _composite_stereo(scene, camera)
            scene.render.resolution_percentage = 50
            mismatch = compositing.out_of_step(scene)  # F12 and the panel say it
            assert "resolution_percentage" in mismatch and "press Composite CG Objects again" in mismatch, mismatch
            assert bpy.ops.neulf.composite_cg() == {"FINISHED"} and compositing.out_of_step(scene) is None
            scene.render.resolution_percentage = 100
        finally:  # the later steps render the light field alone
            if hasattr(scene, "compositing_node_group"):
                ours = scene.compositing_node_group
                scene.compositing_node_group = None
                for tree in (ours, users_tree):
                    if tree is not None:
                        bpy.data.node_groups.remove(tree)
            else:
                scene.use_nodes = False
            if scene.neulf.cg_scene is not None:
                bpy.data.scenes.remove(scene.neulf.cg_scene)
            if scene.neulf.cg_collection is not None:
                bpy.data.collections.remove(scene.neulf.cg_collection)
            scene.view_layers[0].use_pass_z = False

        red = np.array([1.0, 0.0, 0.0])
        inside = np.isfinite(cube_depth)
        edge = np.zeros_like(inside)  # the cube's outline: antialiased, a blend of both
        edge[1:-1, 1:-1] = (inside[1:-1, 1:-1] != inside[:-2, 1:-1]) | (inside[1:-1, 1:-1] != inside[2:, 1:-1]) | \
                           (inside[1:-1, 1:-1] != inside[1:-1, :-2]) | (inside[1:-1, 1:-1] != inside[1:-1, 2:])
        nearer = inside & (cube_depth < plate_depth - 0.05)
        behind = inside & (cube_depth > plate_depth + 0.05)
        clear = ~inside & ~edge
        assert nearer.sum() > 50 and behind.sum() > 50, (nearer.sum(), behind.sum())  # astride the surface
        shows_cube = np.abs(composite - red).max(axis=2) < 0.06
        shows_plate = np.abs(composite - plate).max(axis=2) < 4 / 255
        interior = ~edge
        agree_near = (shows_cube & nearer & interior).sum() / (nearer & interior).sum()
        agree_behind = (shows_plate & behind & interior).sum() / (behind & interior).sum()
        agree_clear = (shows_plate & clear).sum() / clear.sum()
        assert agree_near > 0.97 and agree_behind > 0.97 and agree_clear > 0.99, (agree_near, agree_behind, agree_clear)
        return (f"{refused_tree}; {switched}; {(nearer & interior).sum()} pixels where the cube is nearer than the light field show the cube "
                f"({agree_near:.1%}), {(behind & interior).sum()} where it is behind show the light field "
                f"({agree_behind:.1%}), the rest the light field ({agree_clear:.1%})")

    @story.step("viewport_preview", "render_camera")
    def _():
        # Headless Blender never draws, so the engine's view_draw (gpu) cannot run here; what it
        # stands on can.  A viewport looking through a camera uses the camera's own projection
        # (calc_matrix_camera): from it and the view matrix the preview must ask for the pinhole
        # render_camera renders, with the root moved and scaled too; the preview renderer then
        # renders that view coarse and at full size, in Blender's Python and in a worker.
        viewport, engine = mod("viewport"), mod("engine")
        scene, r = bpy.context.scene, root()
        camera = scene.camera
        original = r.matrix_world.copy()
        render = scene.render
        width, height = render.resolution_x * render.resolution_percentage // 100, \
            render.resolution_y * render.resolution_percentage // 100
        worst = {"K": 0.0, "R": 0.0, "t": 0.0}
        try:
            for moved in (False, True):
                if moved:
                    r.matrix_world = Matrix.Translation((1.0, -2.0, 0.5)) @ original @ Matrix.Scale(2.5, 4)
                    bpy.context.view_layer.update()
                depsgraph = bpy.context.evaluated_depsgraph_get()
                window = camera.calc_matrix_camera(depsgraph, x=width, y=height, scale_x=render.pixel_aspect_x,
                                                   scale_y=render.pixel_aspect_y)
                got = viewport.view_request(camera.matrix_world.inverted(), window, width, height, r.matrix_world)
                expected = mod("capture").camera_request(scene, camera)
                for name in worst:
                    worst[name] = max(worst[name], float(np.abs(np.subtract(got[name], expected[name])).max()))
                assert abs(got["scale"] - expected["scale"]) < 1e-6 * expected["scale"], (got["scale"], expected["scale"])
        finally:
            r.matrix_world = original
            bpy.context.view_layer.update()
        assert worst["K"] < 2e-3 and worst["R"] < 1e-5 and worst["t"] < 1e-5, worst

        depsgraph = bpy.context.evaluated_depsgraph_get()
        big = 6  # the view at six times the render's pixels: more than a coarse pass holds
        window = camera.calc_matrix_camera(depsgraph, x=width, y=height, scale_x=render.pixel_aspect_x,
                                           scale_y=render.pixel_aspect_y)
        request = viewport.view_request(camera.matrix_world.inverted(), window, big * width, big * height,
                                        r.matrix_world)
        request.pop("scale")
        request["model_dir"] = mod("model_folder").model_dir(scene)
        key = viewport.view_key(request, request["model_dir"], 0.0)
        lines = []
        for mode in ("AUTO", "WORKER"):
            prefs().render_mode = mode
            try:
                core = mod("preferences").get_core()
                if mode == "AUTO" and not core.in_process:
                    continue  # (Blender 4.2's Python has no torch: its core is the worker, run next)
                assert core.in_process == (mode == "AUTO"), mode
                sizes = []
                renderer = viewport.PreviewRenderer(viewport.render_function(core),
                                                    on_image=lambda: sizes.append(renderer.image().rgb.shape[:2]))
                renderer.want(key, request)
                if mode == "WORKER":  # Blender's own call while the preview has the worker: they take turns
                    alongside = core.call("render", depth=False, pixel_samples=1, **request)["rgb"]
                assert renderer.wait(300) and renderer.error is None, renderer.error
                direct = core.call("render", depth=False, pixel_samples=1, **request)["rgb"]
                shown = renderer.image()
                assert shown.full_size and np.abs(shown.rgb - direct).max() < 1e-5
                if mode == "WORKER":
                    assert np.abs(alongside - direct).max() < 1e-5
                assert sizes[-1] == (big * height, big * width) and len(sizes) == 2, sizes
                assert sizes[0][0] * sizes[0][1] <= viewport.PREVIEW_PIXELS * 1.02, sizes
                renderer.want(key, dict(request))  # a redraw of the same view renders nothing
                time.sleep(0.2)
                assert renderer.renders == 2 and not renderer.busy
                lines.append(f"{mode.lower()}: {sizes[0][1]}x{sizes[0][0]} then {sizes[1][1]}x{sizes[1][0]} "
                             f"({shown.seconds:.2f} s)")
                renderer.close()
            finally:
                prefs().render_mode = "AUTO"
                mod("core").shutdown()
        # The engine's own reading of a viewport (region and RegionView3D stood in by their
        # attributes): the request above, and a key that a new checkpoint of the model changes.
        from types import SimpleNamespace

        region = SimpleNamespace(width=big * width, height=big * height)
        view = SimpleNamespace(view_matrix=camera.matrix_world.inverted(), window_matrix=window,
                               view_perspective="PERSP")
        seen, key_before = engine._viewport_view(scene, depsgraph, region, view)
        assert seen["model_dir"] == request["model_dir"] and np.allclose(seen["K"], request["K"]) \
            and np.allclose(seen["R"], request["R"]) and np.allclose(seen["t"], request["t"]), (seen, request)
        assert engine._viewport_view(scene, depsgraph, region, view)[1] == key_before
        # Through the camera with its depth of field on: the preview renders it (F12's lens request).
        dof = camera.data.dof
        saved_dof = (dof.use_dof, dof.focus_object, dof.focus_distance, dof.aperture_fstop)
        dof.use_dof, dof.focus_object, dof.focus_distance, dof.aperture_fstop = True, None, 3.0, 0.5
        try:
            through = SimpleNamespace(**{**vars(view), "view_perspective": "CAMERA"})
            lensed, key_lens = engine._viewport_view(scene, bpy.context.evaluated_depsgraph_get(), region, through)
            expected_lens = mod("capture").lens_request(camera, mod("convert").uniform_scale(np.array(r.matrix_world)))
            assert expected_lens and all(abs(lensed[k] - v) < 1e-9 for k, v in expected_lens.items()), \
                (lensed, expected_lens)
            assert key_lens != key_before and "focus_distance" not in seen
        finally:
            dof.use_dof, dof.focus_object, dof.focus_distance, dof.aperture_fstop = saved_dof
        checkpoint = Path(request["model_dir"]) / "checkpoint.pt"
        stamp = checkpoint.stat().st_mtime
        os.utime(checkpoint, (stamp + 5, stamp + 5))  # as a checkpoint of a model in training
        try:
            assert engine._viewport_view(scene, depsgraph, region, view)[1] != key_before
        finally:
            os.utime(checkpoint, (stamp, stamp))
        saved = scene.neulf.model_dir
        scene.neulf.model_dir = ""
        try:
            engine._viewport_view(scene, depsgraph, region, view)
            raise AssertionError("a viewport without a model was rendered")
        except Exception as exc:  # noqa: BLE001 - the NeulfError the viewport's corner shows
            assert "no NeuLF model" in str(exc), exc
        finally:
            scene.neulf.model_dir = saved
        # The panel's button: this viewport in Rendered shading with the NeuLF engine, again: Solid.
        window = bpy.context.window
        area = next(a for a in window.screen.areas if a.type == "VIEW_3D")
        space = area.spaces.active
        saved_engine, saved_shading = scene.render.engine, space.shading.type
        scene.render.engine, space.shading.type = "CYCLES", "SOLID"
        try:
            with bpy.context.temp_override(window=window, area=area, space_data=space):
                assert bpy.ops.neulf.viewport_preview() == {"FINISHED"}
                assert scene.render.engine == "NEULF" and space.shading.type == "RENDERED"
                assert bpy.ops.neulf.viewport_preview() == {"FINISHED"}
                assert space.shading.type == "SOLID"
            properties = next(a for a in window.screen.areas if a.type == "PROPERTIES")
            with bpy.context.temp_override(window=window, area=properties, space_data=properties.spaces.active):
                refused = error_of(lambda: bpy.ops.neulf.viewport_preview()).strip()
            assert "3D viewport" in refused and "\n" not in refused, refused
        finally:
            scene.render.engine, space.shading.type = saved_engine, saved_shading
        ortho = Matrix.Diagonal((0.5, 0.5, -0.02, 1.0))
        try:
            viewport.view_request(camera.matrix_world.inverted(), ortho, width, height, r.matrix_world)
            raise AssertionError("an orthographic view was accepted")
        except Exception as exc:  # noqa: BLE001 - a NeulfError with what to do
            assert "orthographic" in str(exc) and "Numpad 5" in str(exc), exc
        assert callable(engine.NeulfRenderEngine.view_draw) and callable(engine.NeulfRenderEngine.view_update)
        return f"projection -> pinhole within K {worst['K']:.1e} px, R {worst['R']:.1e}, t {worst['t']:.1e}; " \
            + "; ".join(lines)

    def _spiral_keeps_other_keys(scene, spiral):
        """Spiral Camera Path again, on its own camera now active: the same camera (no second),
        its location / rotation keys replaced, a lens key of the user's kept."""
        spiral.data.keyframe_insert("lens", frame=1)
        spiral.keyframe_insert("hide_render", frame=1)
        cameras_before = sum(obj.type == "CAMERA" for obj in bpy.data.objects)
        assert bpy.ops.neulf.spiral_path(frames=3) == {"FINISHED"}
        assert scene.camera is spiral and sum(obj.type == "CAMERA" for obj in bpy.data.objects) == cameras_before
        assert spiral.data.animation_data is not None and spiral.animation_data is not None
        paths = sorted({fcurve.data_path for fcurve in _fcurves_of(spiral)})
        assert paths == ["hide_render", "location", "rotation_euler"], paths
        assert all(len(fcurve.keyframe_points) == (3 if fcurve.data_path != "hide_render" else 1)
                   for fcurve in _fcurves_of(spiral)), [(f.data_path, len(f.keyframe_points)) for f in _fcurves_of(spiral)]
        return "pressed again: the same camera, its transform keys replaced (3 each), a visibility key kept"

    def _fcurves_of(obj):
        animation = obj.animation_data
        if getattr(animation, "action_slot", None) is not None:
            from bpy_extras import anim_utils
            return anim_utils.action_get_channelbag_for_slot(animation.action, animation.action_slot).fcurves
        return animation.action.fcurves

    @story.step("spiral_video", "render_camera")
    def _():
        scene = bpy.context.scene
        scene.frame_start = 1
        capture_camera = scene.camera
        assert capture_camera.get("neulf_role") == "camera"
        photo_pose = capture_camera.matrix_world.copy()
        assert bpy.ops.neulf.spiral_path(frames=3) == {"FINISHED"}
        assert scene.frame_end == 3
        spiral = scene.camera  # a camera of its own: the capture camera keeps its photo's pose
        assert spiral is not capture_camera and spiral.name == "NeuLF Spiral", spiral.name
        assert spiral.data.lens == capture_camera.data.lens and capture_camera.animation_data is None
        kept = _spiral_keeps_other_keys(scene, spiral)
        poses = []
        for frame in (1, 2, 3):
            scene.frame_set(frame)
            poses.append(np.array(scene.camera.matrix_world))
        assert not np.allclose(poses[0], poses[1])
        assert np.allclose(np.array(capture_camera.matrix_world), np.array(photo_pose))
        # A lens a quarter as long sees past the capture: said when keyframing, with the lens that
        # keeps the path inside (it had been said only frame by frame when rendered).
        lens = spiral.data.lens
        spiral.data.lens = lens / 4
        wide = reports_of(lambda: bpy.ops.neulf.spiral_path(frames=3))
        spiral.data.lens = lens
        assert "frames look past the region the photos captured" in wide and "mm or longer" in wide, wide
        longer = int(re.search(r"a lens of (\d+) mm or longer", wide).group(1))
        assert lens / 4 < longer <= math.ceil(lens * 1.01), (wide, lens)
        quiet = reports_of(lambda: bpy.ops.neulf.spiral_path(frames=3))
        assert "look past" not in quiet, quiet
        assert not bpy.data.filepath  # the default '//neulf.mp4' in a file never saved: said, not lost
        unsaved = error_of(lambda: bpy.ops.neulf.render_video())
        assert "not saved yet" in unsaved and unsaved.strip().count("\n") == 0, unsaved
        video = work / "spiral.mp4"
        assert bpy.ops.neulf.render_video(filepath=str(video)) == {"FINISHED"}
        written = video if video.is_file() else next(work.glob("spiral*.mp4"))
        clip = bpy.data.movieclips.load(str(written))  # Blender's own FFmpeg reader
        count = clip.frame_duration
        bpy.data.movieclips.remove(clip)
        assert count == 3, count
        ctx["video"] = str(written)
        return f"{written.name}: {count} frames through '{spiral.name}' (the capture camera untouched); {kept}"

    @story.step("video_cut_short", "spiral_video")
    def _():
        """A frame of Render Video that fails (a marker switches to an orthographic camera at frame
        2): neither the UI's render (which runs on after the operator; handlers clean up after
        it) nor a script's leaves a video that would pass for the whole path, and the artist's
        render settings come back."""
        video = mod("video_settings")
        scene = bpy.context.scene
        scene.frame_set(scene.frame_start)
        spiral = scene.camera
        ortho = bpy.data.objects.new("StoryOrtho", bpy.data.cameras.new("StoryOrtho"))
        ortho.data.type = "ORTHO"
        scene.collection.objects.link(ortho)
        ortho.matrix_world = spiral.matrix_world
        markers = [scene.timeline_markers.new("story_spiral", frame=scene.frame_start),
                   scene.timeline_markers.new("story_ortho", frame=scene.frame_start + 1)]
        markers[0].camera, markers[1].camera = spiral, ortho
        engine, status = scene.render.engine, scene.neulf.last_status
        try:
            # The UI's branch of Render Video, line by line: its render is Blender's job, which
            # the operator has returned before.
            saved = video.saved_render_settings(scene)
            scene.render.engine = "NEULF"
            video.configure_video(scene, str(work / "cut_ui.mp4"))
            written = Path(scene.render.frame_path(frame=scene.frame_start))
            video.restore_after_render(scene, saved, written)
            try:
                bpy.ops.render.render("INVOKE_DEFAULT", animation=True, scene=scene.name)
            except RuntimeError:
                pass
            assert not written.exists() and scene.render.engine == engine, (written, scene.render.engine)
            removed = scene.neulf.last_status
            assert "partial video was removed" in removed, removed
            # A render that did not start (Blender rendering already): forgotten at once, so a later
            # render's cancel cannot remove this path's (complete, earlier) video.
            kept = work / "kept.mp4"
            kept.write_bytes(b"an earlier video")
            saved = video.saved_render_settings(scene)
            scene.render.engine = "NEULF"
            forget = video.restore_after_render(scene, saved, kept)
            forget()
            assert scene.render.engine == engine and not any(
                "cut_short" in getattr(h, "__name__", "") for h in bpy.app.handlers.render_cancel)
            for handler in list(bpy.app.handlers.render_cancel):
                handler(scene)
            assert kept.read_bytes() == b"an earlier video"
            # A script's (blocking) Render Video.
            failed = error_of(lambda: bpy.ops.neulf.render_video(filepath=str(work / "cut_script.mp4")))
            assert "ortho" in failed and not list(work.glob("cut_script*")), failed
            # Not a user's error but a bug in a frame (here: the core raising ZeroDivisionError) ends
            # the render as one line too; it had written a black frame into the video and reported success.
            preferences, get_core = mod("preferences"), mod("preferences").get_core

            class Broken:
                def call(self, *args, **kwargs):
                    return 1 / 0

            markers[1].camera = spiral
            preferences.get_core = lambda context=None: Broken()
            try:
                bug = error_of(lambda: bpy.ops.neulf.render_video(filepath=str(work / "cut_bug.mp4")))
            finally:
                preferences.get_core = get_core
            assert "NeuLF render failed (ZeroDivisionError" in bug and not list(work.glob("cut_bug*")), bug
        finally:
            for marker in markers:
                scene.timeline_markers.remove(marker)
            bpy.data.objects.remove(ortho)
            scene.camera, scene.neulf.last_status = spiral, status
        return f"UI: {removed}; script: {failed.strip()}; a bug: {bug.strip()}"

    @story.step("artist_settings", "spiral_video")
    def _():
        """What an artist sets up stays theirs (from a headless audit): a copy of a capture
        camera, the scene camera, size and colours through a re-import; the render settings
        through Render Video; a focus bone, a focus object behind the camera."""
        from mathutils import Vector

        scene, render = bpy.context.scene, bpy.context.scene.render
        original_camera = bpy.data.objects["view_04"]
        shot = original_camera.copy()  # as Shift+D: the copy carries the capture's properties
        shot.data = original_camera.data.copy()
        shot.name = "MyShot"
        original_camera.users_collection[0].objects.link(shot)
        shot.location.x += 0.5
        bpy.context.view_layer.update()
        moved = shot.matrix_world.copy()
        kept = (scene.camera, render.resolution_x, render.resolution_y)
        scene.camera, render.resolution_x, render.resolution_y = shot, 96, 64
        scene.view_settings.view_transform = "AgX"
        props = scene.neulf
        assert bpy.ops.neulf.import_colmap(directory=bpy.path.abspath(props.scene_dir)) == {"FINISHED"}
        assert np.allclose(np.array(shot.matrix_world), np.array(moved)), "the copy was snapped back onto the photo"
        assert scene.camera == shot and (render.resolution_x, render.resolution_y) == (96, 64)
        assert scene.view_settings.view_transform == "AgX"
        assert not mod("capture").is_capture_camera(shot) and mod("capture").is_capture_camera(original_camera)
        assert bpy.ops.neulf.spiral_path(frames=2) == {"FINISHED"} and scene.camera == shot  # keyframes the copy
        # Render Video puts the artist's engine and output back, and refuses an orthographic camera.
        render.engine, render.filepath = "CYCLES", str(work / "renders" / "sh010_####")
        render.image_settings.file_format = "OPEN_EXR"
        folder = work / "videos"
        folder.mkdir(exist_ok=True)
        assert bpy.ops.neulf.render_video(filepath=str(folder) + "/") == {"FINISHED"}
        assert (folder / "neulf.mp4").is_file() or any(folder.glob("neulf*.mp4")), list(folder.iterdir())
        assert (render.engine, render.image_settings.file_format) == ("CYCLES", "OPEN_EXR"), render.engine
        assert render.filepath == str(work / "renders" / "sh010_####"), render.filepath
        shot.data.type = "ORTHO"
        ortho = error_of(lambda: bpy.ops.neulf.render_video(filepath=str(work / "ortho.mp4")))
        assert "ortho" in ortho and "Traceback" not in ortho and not (work / "ortho.mp4").exists(), ortho
        shot.data.type = "PERSP"
        # The focus: a bone of an armature, and an object behind the camera (Blender's distances).
        lens_request = mod("capture").lens_request
        shot.data.dof.use_dof, shot.data.dof.aperture_fstop = True, 2.8
        armature = bpy.data.objects.new("Rig", bpy.data.armatures.new("Rig"))
        scene.collection.objects.link(armature)
        bpy.context.view_layer.objects.active = armature
        forward = -np.array(shot.matrix_world.to_3x3().col[2])
        bpy.ops.object.mode_set(mode="EDIT")
        bone = armature.data.edit_bones.new("focus")  # its head 3 further along the view than the rig's origin
        bone.head = Vector(forward * 3.0)
        bone.tail = bone.head + Vector((0.0, 0.0, 0.1))
        bpy.ops.object.mode_set(mode="OBJECT")
        armature.location = shot.matrix_world.translation + Vector(forward * 2.0)  # the origin 2 ahead
        bpy.context.view_layer.update()
        shot.data.dof.focus_object = armature
        by_origin = lens_request(shot, 1.0)["focus_distance"]
        if hasattr(shot.data.dof, "focus_subtarget"):
            bone_head = armature.matrix_world @ armature.pose.bones["focus"].head
            shot.data.dof.focus_subtarget = "focus"
            expected = float(np.array(bone_head - shot.matrix_world.translation) @ forward)
            by_bone = lens_request(shot, 1.0)["focus_distance"]
            assert abs(by_bone - abs(expected)) < 1e-4 and abs(by_bone - by_origin) > 0.1, (by_bone, expected, by_origin)
            shot.data.dof.focus_subtarget = ""
        armature.location = shot.matrix_world.translation - Vector(forward * 2.0)  # behind the camera
        bpy.context.view_layer.update()
        behind = lens_request(shot, 1.0)["focus_distance"]
        assert abs(by_origin - 2.0) < 1e-4 and abs(behind - 2.0) < 1e-4, (by_origin, behind)
        bpy.data.objects.remove(armature)
        bpy.data.objects.remove(shot)
        scene.camera, render.resolution_x, render.resolution_y = kept
        scene.view_settings.view_transform = "Standard"
        # The same capture imported into a second scene: a root of its own (turning one turned both).
        variant = bpy.data.scenes.new("Variant")
        with bpy.context.temp_override(scene=variant):
            assert bpy.ops.neulf.import_colmap(directory=bpy.path.abspath(props.scene_dir)) == {"FINISHED"}
        assert variant.neulf.root is not None and variant.neulf.root != props.root, variant.neulf.root
        assert variant.neulf.capture_collection != props.capture_collection
        bpy.data.scenes.remove(variant)
        return (f"re-import kept MyShot, the scene camera, 96x64 and AgX; the video went into videos/ and "
                f"CYCLES/OPEN_EXR came back; ortho: {ortho.strip()}; focus {by_origin:.3f} by the origin, "
                f"{behind:.3f} behind")

    @story.step("capture_identity", "artist_settings")
    def _():
        """The capture's own objects stay its own (a second reader's audit): a renamed capture camera
        is still its photo's (Spiral keyframes a camera of its own; a re-import makes no second
        one), a Shift+D copy of the root does not become the root, a root deleted with X comes back
        without the re-import taking the artist's camera and size, a root scaled unevenly is
        refused, and a capture camera whose photo frames otherwise than the scene is said."""
        scene, render, props = bpy.context.scene, bpy.context.scene.render, bpy.context.scene.neulf
        capture_mod = mod("capture")
        kept = (scene.camera, render.resolution_x, render.resolution_y)
        root = props.root
        photo = bpy.data.objects["view_04"]
        pose = photo.matrix_world.copy()

        def reimport():
            assert bpy.ops.neulf.import_colmap(directory=bpy.path.abspath(props.scene_dir)) == {"FINISHED"}

        def claiming(view):
            return [obj for obj in bpy.data.objects if obj.get("neulf_view") == view and obj.users_scene]

        photo.name = "Hero"  # F2
        assert capture_mod.is_capture_camera(photo)
        reimport()
        assert claiming("view_04.png") == [photo], claiming("view_04.png")
        scene.camera = photo
        assert bpy.ops.neulf.spiral_path(frames=2) == {"FINISHED"}
        assert scene.camera != photo and scene.camera.get(capture_mod.ROLE) == "spiral", scene.camera
        bpy.context.scene.frame_set(scene.frame_start + 1)
        assert np.allclose(np.array(photo.matrix_world), np.array(pose)), "the photo's camera was keyframed"
        photo.name = "view_04"
        # A Shift+D copy of the root, moved away: the re-import keeps the capture on its own root.
        copy = root.copy()
        root.users_collection[0].objects.link(copy)
        copy.location.x += 3.0
        reimport()
        assert props.root == root and photo.parent == root, (props.root, photo.parent)
        assert np.allclose(np.array(photo.matrix_world), np.array(pose))
        bpy.data.objects.remove(copy)
        # The root deleted with X (unlinked; the scene's pointer holds it), the artist's camera set:
        # the re-import links it back and leaves the camera and size as they are.
        artist = bpy.data.objects.new("ArtCam", bpy.data.cameras.new("ArtCam"))
        scene.collection.objects.link(artist)
        scene.camera, render.resolution_x, render.resolution_y = artist, 96, 64
        for collection in list(root.users_collection):
            collection.objects.unlink(root)
        reimport()
        assert props.root == root and root.users_collection and photo.parent == root
        assert scene.camera == artist and (render.resolution_x, render.resolution_y) == (96, 64)
        assert len([obj for obj in bpy.data.objects if obj.get(capture_mod.ROLE) == "root" and obj.users_scene]) == 1
        # A capture camera framing otherwise than the scene: said with F12's other notes.
        scene.camera = photo
        framing = [n for n in capture_mod.settings_not_followed(scene, photo) if "another framing" in n]
        assert framing and "Use Capture Camera" in framing[0], capture_mod.settings_not_followed(scene, photo)
        # A root scaled unevenly cannot be rendered through: refused in one line.
        scale = root.scale.copy()
        root.scale = (scale.x, scale.y, 2.0 * scale.z)
        bpy.context.view_layer.update()
        uneven = error_of(lambda: bpy.ops.neulf.render_camera())
        assert "scaled unevenly" in uneven and "Traceback" not in uneven, uneven
        root.scale = scale
        bpy.context.view_layer.update()
        bpy.data.objects.remove(artist)
        scene.camera, render.resolution_x, render.resolution_y = kept
        return f"renamed camera kept its photo; root copy and deleted root handled; {uneven.strip()}"

    @story.step("save_reload", "render_camera")
    def _():
        blend = work / "scenes" / "capture.blend"
        blend.parent.mkdir(exist_ok=True)
        props = bpy.context.scene.neulf
        assert not bpy.data.filepath and Path(props.model_dir).is_absolute()  # imported and trained before a save
        capture = Path(props.scene_dir).resolve()

        def folders(props):
            return [Path(bpy.path.abspath(path)).resolve() for path in (props.model_dir, props.scene_dir)]

        bpy.ops.wm.save_as_mainfile(filepath=str(blend))  # the first save makes the folders relative to it
        assert props.model_dir.startswith("//") and props.scene_dir.startswith("//"), props.model_dir
        assert folders(props) == [model.resolve(), capture], folders(props)
        failed = error_of(lambda: bpy.ops.wm.save_as_mainfile(filepath=str(work / "no_such" / "folder" / "x.blend")))
        assert failed and not (work / "no_such").exists(), failed
        if hasattr(bpy.app.handlers, "save_post_fail"):  # (4.4+; 4.2 restores them at the next save)
            assert folders(props) == [model.resolve(), capture], (props.model_dir, folders(props))
        elsewhere = work / "save_as" / "deeper" / "capture.blend"
        elsewhere.parent.mkdir(parents=True, exist_ok=True)
        bpy.ops.wm.save_as_mainfile(filepath=str(elsewhere))  # Save As into another folder: the same folders
        assert folders(props) == [model.resolve(), capture], (props.model_dir, folders(props))
        copy = work / "save_copy" / "capture.blend"
        copy.parent.mkdir(exist_ok=True)
        bpy.ops.wm.save_as_mainfile(filepath=str(copy), copy=True)  # Save Copy: the open file's paths unchanged
        assert folders(props) == [model.resolve(), capture], (props.model_dir, folders(props))
        bpy.ops.wm.open_mainfile(filepath=str(copy))
        assert folders(bpy.context.scene.neulf) == [model.resolve(), capture], bpy.context.scene.neulf.model_dir
        bpy.ops.wm.open_mainfile(filepath=str(elsewhere))
        bpy.ops.wm.save_as_mainfile(filepath=str(blend))
        bpy.ops.wm.open_mainfile(filepath=str(blend))
        props = bpy.context.scene.neulf
        assert folders(props) == [model.resolve(), capture], props.model_dir
        assert bpy.ops.neulf.render_camera() == {"FINISHED"}
        return f"{props.model_dir} after a first save, a Save As elsewhere and a Save Copy (each resolving to the model)"

    def child(session: str, **args) -> dict:
        """Run a session of this script in a new bpy process (Blender started again), same user folder."""
        import subprocess

        out = work / f"{session}.result.json"
        out.unlink(missing_ok=True)
        config = dict(args, session=session, out=str(out), worker_python=worker_python)
        (work / f"{session}.json").write_text(json.dumps(config))
        run = subprocess.run([sys.executable, str(Path(__file__).resolve()), str(work / f"{session}.json")],
                             capture_output=True, text=True, timeout=600)
        if not out.is_file():
            raise AssertionError(f"session {session} wrote nothing (exit {run.returncode}):\n"
                                 f"{run.stdout[-3000:]}\n{run.stderr[-3000:]}")
        result = json.loads(out.read_text())
        assert not result.get("error"), f"session {session}: {result['error']}\n{run.stdout[-2000:]}"
        result["exit"] = run.returncode
        return result

    @story.step("blend_moved", "save_reload")
    def _():
        # The .blend and its model folder moved together to another folder, opened by another
        # Blender: the model path is relative to the .blend and resolves there.
        assert bpy.ops.neulf.render_camera() == {"FINISHED"}
        here = image_array("NeuLF Render").copy()
        blend = Path(bpy.data.filepath)
        elsewhere = work / "elsewhere" / "deeper"
        shutil.copytree(blend.parent, elsewhere / blend.parent.name)
        shutil.copytree(model, elsewhere / model.name)
        moved_blend = elsewhere / blend.parent.name / blend.name
        hidden = model.with_name("model_away")  # the old absolute path must not be what works
        model.rename(hidden)
        try:
            result = child("moved", blend=str(moved_blend), render=str(work / "moved_render.npy"))
        finally:
            hidden.rename(model)
        assert result["model_dir"].startswith("//"), result["model_dir"]
        assert Path(result["resolved"]) == (elsewhere / model.name).resolve(), result["resolved"]
        assert result["status"] == "finished at step 60", result["status"]
        moved = np.load(work / "moved_render.npy")
        diff = float(np.abs(moved - here).max())
        assert moved.shape == here.shape and diff <= 1 / 255 + 1e-6, diff
        # ... and moved without its model folder: the panel and the error say what is wrong.
        assert result["missing_status"].startswith("model folder not found:"), result["missing_status"]
        missing = result["missing_error"]
        assert missing.startswith("Error:") and "does not exist" in missing and missing.strip().count("\n") == 0, missing
        refused = result["missing_train"]  # Train does not start a new model where the old one was
        assert "does not exist" in refused and "create the folder first" in refused, refused
        assert not result["missing_made"]
        return (f"reopened from {elsewhere.relative_to(work)}: model {result['model_dir']}, panel "
                f"'{result['status']}', render equal within {diff * 255:.1f}/255; without the model folder: "
                f"{missing.strip()}")

    @story.step("linked_scene", "save_reload")
    def _():
        # A shot file in another folder links the capture's scene (File > Link): the scene's model
        # path is relative to the file the scene lives in, and resolves there; Load Model, which
        # would change linked data for the session only, is refused in one line.
        blend = work / "scenes" / "capture.blend"
        bpy.ops.wm.open_mainfile(filepath=str(blend))
        name = bpy.context.scene.name
        assert bpy.ops.neulf.render_camera() == {"FINISHED"}
        direct = image_array("NeuLF Render").copy()
        bpy.ops.wm.read_homefile(use_empty=True)
        shot = work / "shots" / "deeper" / "shot.blend"
        shot.parent.mkdir(parents=True, exist_ok=True)
        bpy.ops.wm.save_as_mainfile(filepath=str(shot))
        with bpy.data.libraries.load(str(blend), link=True, relative=True) as (_source, linked):
            linked.scenes = [name]
        differences = []
        for reopened in (False, True):
            if reopened:
                bpy.ops.wm.save_mainfile()
                bpy.ops.wm.open_mainfile(filepath=str(shot))
            scene = next(scene for scene in bpy.data.scenes if scene.library is not None)
            with bpy.context.temp_override(scene=scene):
                assert bpy.ops.neulf.render_camera() == {"FINISHED"}
                refused = error_of(lambda: bpy.ops.neulf.load_model(directory=str(model)))
                for call in (lambda: bpy.ops.neulf.spiral_path(frames=3), lambda: bpy.ops.neulf.composite_cg()):
                    also = error_of(call)  # (they would change linked data for this session only)
                    assert "is linked from" in also, also
            differences.append(float(np.abs(image_array("NeuLF Render") - direct).max()))
            assert "is linked from" in refused and refused.strip().count("\n") == 0, refused
        assert max(differences) <= 1 / 255 + 1e-6, differences
        return (f"linked into {shot.relative_to(work)}: Render Camera equals the capture file's within "
                f"{max(differences) * 255:.1f}/255 (and after saving and reopening); {refused.strip()}")

    def reopened_while_trained_elsewhere(blend: Path, folder: Path) -> str:
        # The .blend opened while another process still trains its model folder (as the training
        # a crashed Blender leaves behind does until it has saved; here one started from a
        # terminal, which runs until stopped): the panel says so and follows it, Train is refused
        # in one line instead of a second training overwriting the first's checkpoints, and once
        # that process has stopped the panel says Train continues the model.
        busy = child("reopen_busy", blend=str(blend), scene_dir=str(scene_dir), model=str(folder))
        pid = busy["other_pid"]
        assert busy["status_on_open"].startswith(f"being trained by another process (pid {pid} on "), busy
        assert busy["status_on_open"].endswith("when it stops, Train continues it"), busy["status_on_open"]
        lines = busy["panel_lines"]  # the panel wraps the long line instead of cutting it off
        assert len(lines) > 1 and " ".join(lines) == busy["status_on_open"] and max(map(len, lines)) <= 38, lines
        refused = busy["refused"]
        assert refused.startswith("Error:") and f"is being trained by process {pid}" in refused, refused
        assert "Traceback" not in refused and refused.strip().count("\n") == 0, refused
        assert busy["tick_while_busy"] == mod("handlers").WATCH_INTERVAL and busy["tick_after"] is None, busy
        assert busy["steps_followed"][1] > busy["steps_followed"][0], busy["steps_followed"]  # the panel follows it
        stopped = json.loads((folder / "model.json").read_text())["progress"]
        assert busy["status_after"].startswith(f"stopped at step {stopped['step']} (checkpoint saved)"), busy
        return (f"reopened while process {pid} trained the folder: '{busy['status_on_open']}'; Train: "
                f"{refused.strip()}; once it stopped: '{busy['status_after']}'")

    @story.step("quit_while_training", "install")
    def _():
        # Blender started, a capture imported and saved, Train pressed (the UI's timer path), the
        # .blend saved during training, then Blender gone: quit (Python exits; the add-on is
        # unregistered, which cancels training) or killed (a crash: only the closed pipe tells the
        # training process).  A new Blender opens the .blend; the panel shows the model's progress
        # and Train continues it.
        saved, gone, opened = set(), [], ""
        for how in ("quit", "kill"):
            folder = work / f"quit_{how}"
            folder.mkdir(exist_ok=True)
            blend, quit_model = folder / "session.blend", folder / "model"
            a = child("quit_a", how=how, blend=str(blend), model=str(quit_model), scene_dir=str(scene_dir))
            assert a["saved_status"] == "training", a
            assert (a["exit"] == 0) if how == "quit" else (a["exit"] != 0), (how, a["exit"])
            assert wait_gone(a["worker_pid"], 120), \
                f"the training process {a['worker_pid']} still runs 120 s after Blender went away"
            if how == "kill":
                busy_text = reopened_while_trained_elsewhere(blend, quit_model)
            found = json.loads((quit_model / "model.json").read_text())["progress"]
            assert found["step"] >= a["step"], (found, a["step"])  # no step that Blender saw is lost
            b = child("reopen_b", blend=str(blend), train=how == "kill")
            assert b["model_dir"].startswith("//") and Path(b["resolved"]) == quit_model.resolve(), b
            expected = f"stopped at step {found['step']} (checkpoint saved); Train continues it"
            assert b["status_on_open"].startswith(expected), (b["status_on_open"], expected)
            saved.add(a["saved_status"])
            gone.append(f"{how} at step {a['step']} -> checkpoint at step {found['step']}")
            opened = b["status_on_open"]
        # The last one (killed) continued by Train in the reopened Blender.
        assert "--resume" in b["argv"], b["argv"]
        assert b["argv"][b["argv"].index("--steps") + 1] == str(found["step"] + 10), b["argv"]
        assert b["progress"]["status"] == "finished" and b["progress"]["step"] == found["step"] + 10, b
        assert b["progress"]["history"][:len(found["history"])] == found["history"]
        resumed = f"finished at step {found['step'] + 10} (continued from step {found['step']})"
        # (a short run that ends before the pose check is checked at its end: the status says so)
        assert resumed in b["report"] and b["last_status"].startswith(resumed), (b["report"], b["last_status"])
        return (f"Blender {', '.join(gone)} (the .blend, saved while training, says '{', '.join(saved)}'); reopened, "
                f"the panel reads the model folder: '{opened}'; Train: {resumed}; {busy_text}")

    @story.step("open_other_while_training", "install")
    def _():
        # Train pressed, then another .blend opened while the training runs: the training's end
        # must not write its model or status into that file; the file it belongs to, reopened,
        # finds the model finished.
        tasks, operators = mod("tasks"), mod("operators")
        bpy.ops.wm.read_homefile(use_empty=True)
        other = work / "other_file" / "other.blend"
        other.parent.mkdir(exist_ok=True)
        bpy.ops.wm.save_as_mainfile(filepath=str(other))  # a file of the user's without a model
        bpy.ops.wm.read_homefile(use_empty=True)
        assert bpy.ops.neulf.import_colmap(directory=str(scene_dir)) == {"FINISHED"}
        folder = work / "trained_file"
        folder.mkdir(exist_ok=True)
        props = bpy.context.scene.neulf
        props.model_dir, props.members = str(folder / "model"), 1
        job, _resumed = operators.start_training(bpy.context, steps=30)  # what Train does in the UI
        bpy.ops.wm.save_as_mainfile(filepath=str(folder / "trained.blend"))  # saved while training
        bpy.ops.wm.open_mainfile(filepath=str(other))
        deadline = time.monotonic() + 180
        while tasks.poll_all() and time.monotonic() < deadline:  # the UI timer's ticks, in the other file
            time.sleep(0.05)
        assert job.state["status"] == "finished", job.state
        untouched = bpy.context.scene.neulf
        assert untouched.model_dir == "" and untouched.last_status == "", (untouched.model_dir, untouched.last_status)
        bpy.ops.wm.open_mainfile(filepath=str(folder / "trained.blend"))
        status = bpy.context.scene.neulf.last_status
        assert status.startswith("finished at step 30"), status
        return f"the other file untouched; the training's own file reopened: '{status}'"

    @story.step("reconstruct_photos", "install")
    def _():
        bpy.ops.wm.read_homefile(use_empty=True)
        photos = Path(setup["photos"])
        names = sorted(p.name for p in photos.iterdir())
        out = work / "reconstructed"
        started = time.monotonic()
        assert bpy.ops.neulf.reconstruct(directory=str(photos), scene_dir=str(out)) == {"FINISHED"}
        seconds = time.monotonic() - started
        job = mod("tasks").get("reconstruct")
        assert job.state["status"] == "finished" and job.state["fraction"] == 1.0, job.state
        assert {"cameras.bin", "images.bin", "points3D.bin"} <= {p.name for p in (out / "sparse" / "0").iterdir()}
        # ... and imported, through the same callback the UI's timer runs.
        props = bpy.context.scene.neulf
        assert Path(bpy.path.abspath(props.scene_dir)).resolve() == out.resolve(), props.scene_dir
        cams = cameras()
        assert [c["neulf_view"] for c in cams] == names, [c["neulf_view"] for c in cams]
        focal = cams[0]["neulf_K"][0]
        assert abs(focal - setup["photos_focal"]) < 0.05 * setup["photos_focal"], focal
        assert any(o.get("neulf_role") == "uv_plane" for o in bpy.data.objects)
        # Too few photos: one clear line, no traceback, nothing imported.
        few = work / "two_photos"
        few.mkdir(exist_ok=True)
        for name in names[:2]:
            (few / name).write_bytes((photos / name).read_bytes())
        message = error_of(lambda: bpy.ops.neulf.reconstruct(directory=str(few), scene_dir=str(work / "few_scene")))
        assert "reconstruction failed" in message and "Only 2 photo" in message, message
        assert "Traceback" not in message and message.count("\n") <= 1, message
        assert Path(bpy.path.abspath(bpy.context.scene.neulf.scene_dir)).resolve() == out.resolve()
        # The capture filmed: Reconstruct Video picks a frame of each stretch, then reconstructs and imports them.
        bpy.ops.wm.read_homefile(use_empty=True)
        filmed = work / "filmed"
        assert bpy.ops.neulf.reconstruct_video(filepath=setup["video"], count=setup["video_photos"],
                                               scene_dir=str(filmed)) == {"FINISHED"}
        picked = sorted(p.name for p in (work / "filmed_frames").iterdir())
        assert picked == [f"frame_{i:04d}.png" for i in range(1, setup["video_photos"] + 1)], picked
        assert Path(bpy.path.abspath(bpy.context.scene.neulf.scene_dir)).resolve() == filmed.resolve()
        assert len(cameras()) == setup["video_photos"], len(cameras())
        return (f"{len(cams)} cameras, focal {focal:.1f} px, {seconds:.1f} s; {message.strip()}; a video: "
                f"{len(picked)} frames picked, reconstructed and imported")

    def audited_errors(props) -> list[str]:
        """What the Blender audit (seventy-eighth session) found wrong, each now one line: another
        program's model.json (Load Model had said "model loaded", and Train replaced the file), a
        model.json damaged beside its checkpoint (Train had counted its budget from step 0), a video
        under a file (a traceback), '//' in a .blend never saved (the model went to Blender's
        working folder), a camera under a turned, unevenly scaled parent (rendered 23 px off), a
        render size of 0 pixels, Image Scale 1e-06 (trained on 1x1 photos), and a render before a
        training's first checkpoint ("train it")."""
        found = []
        theirs = work / "tfjs_model"
        theirs.mkdir(exist_ok=True)
        (theirs / "model.json").write_text('{"format": "layers-model", "modelTopology": {}}')
        found.append(error_of(lambda: bpy.ops.neulf.load_model(directory=str(theirs))))
        assert "cannot be read (damaged or not a NeuLF model's)" in found[-1], found[-1]
        props.model_dir = str(theirs)
        found.append(error_of(lambda: bpy.ops.neulf.train(steps=5)))
        assert "no NeuLF training wrote" in found[-1], found[-1]
        assert (theirs / "model.json").read_text() == '{"format": "layers-model", "modelTopology": {}}'
        assert sorted(p.name for p in theirs.iterdir()) == ["model.json"]
        copy = work / "model_json_damaged"
        shutil.rmtree(copy, ignore_errors=True)
        shutil.copytree(model, copy)
        step = json.loads((copy / "model.json").read_text())["progress"]["step"]
        (copy / "model.json").write_text('{"progress": {"st')
        restored = reports_of(lambda: bpy.ops.neulf.load_model(directory=str(copy)))
        assert "written again from checkpoint.pt" in restored, restored
        assert json.loads((copy / "model.json").read_text())["progress"]["step"] == step
        props.model_dir = str(model)
        found.append(error_of(lambda: bpy.ops.neulf.render_video(filepath=str(work / "a_file" / "x.mp4"))))
        assert "cannot write the video" in found[-1] and "a_file" in found[-1], found[-1]
        assert not bpy.data.filepath  # (reconstruct_photos opened a new file, never saved)
        props.model_dir = "//relative_model"
        found.append(error_of(lambda: bpy.ops.neulf.train(steps=5)))
        assert "is not saved yet" in found[-1] and not Path("relative_model").exists(), found[-1]
        props.model_dir = str(model)
        camera = bpy.context.scene.camera
        parent = bpy.data.objects.new("StorySkewedParent", None)
        bpy.context.scene.collection.objects.link(parent)
        parent.rotation_euler, parent.scale = (0.4, 0.2, 0.7), (1.0, 2.5, 0.6)
        bpy.context.view_layer.update()
        kept_matrix, camera.parent = camera.matrix_world.copy(), parent
        camera.matrix_world = kept_matrix
        try:
            found.append(error_of(lambda: bpy.ops.neulf.render_camera()))
            assert "sheared" in found[-1] and "Alt+P" in found[-1], found[-1]
        finally:
            camera.parent = None
            camera.matrix_world = kept_matrix
            bpy.data.objects.remove(parent)
        render = bpy.context.scene.render
        size = (render.resolution_x, render.resolution_y, render.resolution_percentage)
        render.resolution_x, render.resolution_y, render.resolution_percentage = 64, 48, 1
        try:
            found.append(error_of(lambda: bpy.ops.neulf.render_camera()))
        finally:
            render.resolution_x, render.resolution_y, render.resolution_percentage = size
        assert "pixels: raise Output > Format > Resolution %" in found[-1], found[-1]
        scale, props.train_scale, props.model_dir = props.train_scale, 1e-6, str(work / "tiny_scale_model")
        try:
            found.append(error_of(lambda: bpy.ops.neulf.train(steps=5)))
        finally:
            props.train_scale = scale
        assert "too small to learn from" in found[-1] and "a larger Image Scale, or 0" in found[-1], found[-1]
        first = work / "before_first_checkpoint"
        first.mkdir(exist_ok=True)
        props.model_dir = str(first)
        with sys.modules[f"{PACKAGE}.neulf_core.lock"].training_lock(first):
            found.append(error_of(lambda: bpy.ops.neulf.render_camera()))
        assert "has not saved its first checkpoint yet" in found[-1], found[-1]
        return found

    @story.step("user_errors", "install", "train_blocking")
    def _():
        props = bpy.context.scene.neulf
        props.model_dir = str(work / "no_such_model")
        messages = [error_of(call) for call in (
            lambda: bpy.ops.neulf.render_camera(), lambda: bpy.ops.neulf.import_colmap(directory=str(work)),
            lambda: bpy.ops.neulf.focus_at(x=1, y=1))]
        damaged = work / "damaged_model"  # a model.json cut short: said so, not "missing"
        damaged.mkdir(exist_ok=True)
        (damaged / "model.json").write_text('{"preset": "fa')
        messages.append(error_of(lambda: bpy.ops.neulf.load_model(directory=str(damaged))))
        assert "cannot be read" in messages[-1], messages[-1]
        # A model whose capture folder is no capture (moved, emptied): in an empty scene Load Model
        # imports the capture first; its failure is a warning, and the model is attached (it
        # renders without the photos) with no half-built capture.
        elsewhere, not_a_capture = work / "model_of_no_capture", work / "not_a_capture"
        elsewhere.mkdir(exist_ok=True)
        not_a_capture.mkdir(exist_ok=True)
        (elsewhere / "model.json").write_text(json.dumps({"format": "neulf-checkpoint", "scene": {"root": str(not_a_capture)},
                                                          "progress": {"status": "finished", "step": 5}}))
        empty = bpy.data.scenes.new("StoryEmpty")
        try:
            with bpy.context.temp_override(scene=empty):
                loaded = reports_of(lambda: bpy.ops.neulf.load_model(directory=str(elsewhere)))
            assert "could not be imported" in loaded and "Traceback" not in loaded, loaded
            assert empty.neulf.model_dir and not empty.neulf.scene_dir and empty.neulf.root is None, loaded
        finally:
            bpy.data.scenes.remove(empty)
        # Load Model into an empty scene imports the capture it trained on, and says so (it had said
        # only "model loaded" while 9 cameras appeared).
        empty = bpy.data.scenes.new("StoryLoadInto")
        try:
            with bpy.context.temp_override(scene=empty, view_layer=empty.view_layers[0]):
                loaded = reports_of(lambda: bpy.ops.neulf.load_model(directory=str(model)))
            assert f"its capture imported: {len(scene_views())} cameras from " in loaded, loaded
        finally:
            remove_scene_and_capture(empty)
        # The capture imported into a second scene, whose default model folder (inside the capture's)
        # holds a model: Render names it and Load Model (it had said only "train one", while Train
        # there continues that model).
        copied = work / "capture_with_its_model"
        shutil.copytree(scene_dir, copied)
        shutil.copytree(model, copied / "neulf_model")
        second = bpy.data.scenes.new("StorySecondImport")
        try:
            with bpy.context.temp_override(scene=second, view_layer=second.view_layers[0]):
                assert bpy.ops.neulf.import_colmap(directory=str(copied)) == {"FINISHED"}
                second.camera = next(o for o in second.neulf.capture_collection.objects if o.type == "CAMERA")
                messages.append(error_of(lambda: bpy.ops.neulf.render_camera()))
            assert "no NeuLF model in this scene; the capture's folder holds one, " in messages[-1] and \
                str(copied / "neulf_model") in messages[-1] and "Load Model" in messages[-1], messages[-1]
        finally:
            remove_scene_and_capture(second)
        # A model folder that cannot be written (here: inside a file): said before training starts,
        # naming the panel's field; and a video size H.264 cannot take, before its render.
        in_a_file = work / "a_file"
        in_a_file.write_text("")
        props.model_dir = str(in_a_file / "model")
        messages.append(error_of(lambda: bpy.ops.neulf.train(steps=5)))
        assert "cannot write the model folder" in messages[-1] and "Model field" in messages[-1], messages[-1]
        render = bpy.context.scene.render
        size = (render.resolution_x, render.resolution_y, render.resolution_percentage)
        render.resolution_x, render.resolution_y, render.resolution_percentage = 960, 540, 25
        props.model_dir = str(model)
        try:
            messages.append(error_of(lambda: bpy.ops.neulf.render_video(filepath=str(work / "odd.mp4"))))
        finally:
            render.resolution_x, render.resolution_y, render.resolution_percentage = size
        assert "even width and height" in messages[-1] and "240x135" in messages[-1], messages[-1]
        messages.extend(audited_errors(props))
        props.model_dir = str(work / "no_such_model")
        p, chosen = prefs(), prefs().python_path  # a "Python" that is not one: Train must not say it finished
        p.python_path = shutil.which("true") or "/bin/true"
        try:
            messages.append(error_of(lambda: bpy.ops.neulf.train(steps=5)))
        finally:
            p.python_path = chosen
        assert "ended without training" in messages[-1] and "Python with torch" in messages[-1], messages[-1]
        assert all("Traceback" not in m and m.startswith("Error:") for m in messages), messages
        return " | ".join(m.strip() for m in messages)

    def render_like_the_cli(scene, capture_cameras: dict, hci: dict) -> str:
        """A model the CLI trained, loaded into the scene: Render Camera through a capture camera at
        50 % (the trained size) gives the image `render --views` gave for that photo."""
        assert bpy.ops.neulf.load_model(directory=hci["model_dir"]) == {"FINISHED"}
        worst = []
        for view_name, png in hci["renders"].items():
            scene.camera = capture_cameras[view_name]
            mod("capture").apply_capture_camera(scene, scene.camera)
            scene.render.resolution_percentage = 50
            assert bpy.ops.neulf.render_camera() == {"FINISHED"}
            rendered, expected = image_array("NeuLF Render"), load_png(png)
            assert rendered.shape == expected.shape, (view_name, rendered.shape, expected.shape)
            difference = np.abs(rendered - expected) * 255
            assert difference.max() <= 2.01 and difference.mean() < 0.05, (view_name, difference.max(),
                                                                           difference.mean())
            worst.append(f"{difference.max():.0f}/255")
        return f"its Render Camera of {', '.join(hci['renders'])} as the CLI's render (at most {max(worst)} apart)"

    @story.step("real_captures", "install")
    def _():
        """The reference scenes (real captures: COLMAP 4.x with rigs, a portrait capture, fern's
        model of 4032x3024 photos read from images_8/, HCI's shifted-sensor grid), each imported
        into a scene of its own: every Blender camera projects the scene's points where pycolmap's
        pinhole does on the photo files (computed by the pytest side without neulf_core)."""
        lines = []
        for reference in setup["real_captures"]:
            scene = bpy.data.scenes.new(f"NeuLF real {reference['name']}")
            view_layer = scene.view_layers[0]
            try:
                with bpy.context.temp_override(scene=scene, view_layer=view_layer):
                    result = bpy.ops.neulf.import_colmap(directory=reference["scene_dir"],
                                                         images_dir=reference["images_dir"])
                    assert result == {"FINISHED"}, (reference["name"], result)
                    capture_cameras = {obj["neulf_view"]: obj for obj in scene.neulf.capture_collection.objects
                                       if obj.type == "CAMERA"}
                    assert sorted(capture_cameras) == sorted(reference["views"]), reference["name"]
                    view_layer.update()
                    world = np.array(scene.neulf.root.matrix_world) @ np.c_[reference["points"],
                                                                           np.ones(len(reference["points"]))].T
                    worst = 0.0
                    for view_name, obj in capture_cameras.items():
                        expected = reference["views"][view_name]
                        width, height = expected["width"], expected["height"]
                        mod("capture").apply_capture_camera(scene, obj)
                        render = scene.render
                        assert (render.resolution_x, render.resolution_y) == (width, height), view_name
                        view_layer.update()
                        P = np.array(obj.calc_matrix_camera(bpy.context.evaluated_depsgraph_get(), x=width,
                                                            y=height, scale_x=render.pixel_aspect_x,
                                                            scale_y=render.pixel_aspect_y))
                        clip = P @ np.array(obj.matrix_world.inverted()) @ world
                        ndc = clip[:2] / clip[3]
                        px = np.stack([(ndc[0] + 1) / 2 * width, (1 - ndc[1]) / 2 * height], 1)
                        colmap_px = np.array(expected["px"], dtype=float)
                        near_frame = np.all(np.abs(colmap_px - [width / 2, height / 2]) < [width, height], axis=1)
                        assert near_frame.sum() >= 10, (view_name, int(near_frame.sum()))
                        worst = max(worst, float(np.abs(px - colmap_px)[near_frame].max()))
                    assert worst < 0.01, (reference["name"], worst)
                    lines.append(f"{reference['name']} {len(capture_cameras)} cameras at {width}x{height}, "
                                 f"{worst:.1e} px")
                    if reference["name"] == "hci_antinous" and setup.get("hci"):
                        lines.append(render_like_the_cli(scene, capture_cameras, setup["hci"]))
            finally:
                remove_scene_and_capture(scene)
        return "; ".join(lines) or "no reference scenes"

    @story.step("dependencies_status", "install")
    def _():
        p = prefs()
        chosen = p.python_path
        assert bpy.ops.neulf.check_dependencies() == {"FINISHED"}
        assert p.status.startswith("torch ") and "pycolmap " in p.status and "device: cpu" in p.status, p.status
        usable = p.status
        # A Python without torch: the status says so and what to do, in one line.
        bare = work / "bare_python"
        import subprocess

        subprocess.run([worker_python or sys.executable, "-m", "venv", "--without-pip", str(bare)], check=True)
        p.python_path = str(bare / ("Scripts/python.exe" if os.name == "nt" else "bin/python"))
        try:
            assert p.status == mod("preferences").NOT_CHECKED, p.status  # the verdict was the other Python's
            assert bpy.ops.neulf.check_dependencies() == {"FINISHED"}
            assert p.status.startswith("not usable:") and "has no '" in p.status, p.status
            assert "Install dependencies" in p.status, p.status
            missing = p.status
            p.python_path = str(work / "no_such_python")  # one that does not start: said on the status line too
            error_of(lambda: bpy.ops.neulf.check_dependencies())
            assert p.status.startswith("not usable:"), p.status
        finally:
            p.python_path = chosen
        return f"{usable} | {missing}"

    @story.step("install_dependencies", "install")
    def _():
        p = prefs()
        system = bpy.context.preferences.system
        deps = Path(mod("preferences").deps_dir(create=True))
        assert str(work / "blender_user") in str(deps) and deps.is_dir()
        # Online access off (Blender's default without a UI): refused before anything runs.
        system.use_online_access = False
        assert not bpy.app.online_access
        refused = error_of(lambda: bpy.ops.neulf.install_dependencies())
        assert "Online access is disabled" in refused and mod("tasks").get("install") is None, refused
        # Online access on, but pip kept offline (no index, no config, no find-links): the
        # command runs for real and its failure comes back as one line in the status.
        os.environ.update(PIP_CONFIG_FILE=os.devnull, PIP_NO_INDEX="1")
        for name in ("PIP_FIND_LINKS", "PIP_INDEX_URL", "PIP_EXTRA_INDEX_URL"):
            os.environ.pop(name, None)
        system.use_online_access = True
        p.torch_variant = "CPU"
        try:
            assert bpy.app.online_access
            failed = error_of(lambda: bpy.ops.neulf.install_dependencies())
        finally:
            system.use_online_access = False
        job = mod("tasks").get("install")
        assert job.argv[job.argv.index("--target") + 1] == str(deps), job.argv
        assert {"torch", "pycolmap==4.2.1"} <= set(job.argv), job.argv
        assert "https://download.pytorch.org/whl/cpu" in job.argv, job.argv
        assert failed.startswith("Error: install failed:") and "torch" in failed, failed
        assert "Traceback" not in failed and failed.strip().count("\n") == 0, failed
        assert p.status.startswith("install failed:"), p.status
        return f"{refused.strip()} | {failed.strip()}"

    story.results_path.write_text(json.dumps(story.results, indent=1, default=str))


def wait_gone(pid: int, timeout: float) -> bool:
    """Whether process `pid` ended (or is a zombie) within `timeout` seconds."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except FileNotFoundError:
            return True
        except OSError:  # no /proc: ask the process
            try:
                os.kill(pid, 0)
            except ProcessLookupError:
                return True
            state = "R"
        if state in ("Z", "X"):
            return True
        time.sleep(0.1)
    return False


# ----------------------------------------------------------------------------- sessions in a new Blender


def run_session(setup: dict) -> dict:
    """One part of a story that needs Blender started again (a new bpy process); what it found
    goes to setup["out"] and the story's step checks it."""
    import bpy
    import addon_utils  # noqa: I001 - importable once bpy is

    out = Path(setup["out"])
    result: dict = {}
    addon_utils.extensions_refresh(ensure_wheels=True, addon_modules_pending=[PACKAGE])  # installed by the story
    addon_utils.enable(PACKAGE, default_set=True, persistent=True)

    def mod(name):
        return sys.modules[f"{PACKAGE}.neulf_blender.{name}"]

    if setup.get("worker_python"):
        bpy.context.preferences.addons[PACKAGE].preferences.python_path = setup["worker_python"]

    def resolved(props):
        return str(Path(bpy.path.abspath(props.model_dir)).resolve())

    try:
        session = setup["session"]
        if session == "moved":
            bpy.ops.wm.open_mainfile(filepath=setup["blend"])
            props = bpy.context.scene.neulf
            result.update(model_dir=props.model_dir, resolved=resolved(props), status=props.last_status)
            assert bpy.ops.neulf.render_camera() == {"FINISHED"}
            image = bpy.data.images["NeuLF Render"]
            width, height = image.size
            pixels = np.empty(width * height * 4, np.float32)
            image.pixels.foreach_get(pixels)
            np.save(setup["render"], pixels.reshape(height, width, 4)[::-1, :, :3])
            model = Path(result["resolved"])
            model.rename(model.with_name(model.name + "_gone"))
            bpy.ops.wm.open_mainfile(filepath=setup["blend"])
            result["missing_status"] = bpy.context.scene.neulf.last_status
            result["missing_error"] = error_of(lambda: bpy.ops.neulf.render_camera())
            result["missing_train"] = error_of(lambda: bpy.ops.neulf.train(steps=2))  # refused: no new model there
            result["missing_made"] = Path(bpy.path.abspath(bpy.context.scene.neulf.model_dir)).exists()
        elif session == "quit_a":
            bpy.ops.wm.read_homefile(use_empty=True)
            assert bpy.ops.neulf.import_colmap(directory=setup["scene_dir"]) == {"FINISHED"}
            bpy.ops.wm.save_as_mainfile(filepath=setup["blend"])
            props = bpy.context.scene.neulf
            props.model_dir = setup["model"]
            props.members = 1  # one run, as in train_cancel (this is about quitting, not members)
            job, resumed = mod("operators").start_training(bpy.context, minutes=5)  # what Train does in the UI
            assert not resumed
            deadline = time.monotonic() + 180
            while job.state.get("step", 0) < 10 and time.monotonic() < deadline:
                assert mod("tasks").poll_all(), job.state  # the UI timer's tick
                time.sleep(0.05)
            assert job.state["step"] >= 10, job.state
            bpy.ops.wm.save_mainfile()  # Ctrl+S while training
            result.update(worker_pid=job.process.pid, step=job.state["step"], saved_status=props.last_status,
                          model_dir=props.model_dir)
            if setup["how"] == "kill":
                out.write_text(json.dumps(result))
                os.kill(os.getpid(), 9)  # Blender gone at once, as in a crash
            result["quit"] = True  # a normal exit, after the result is written (see __main__)
        elif session == "reopen_b":
            bpy.ops.wm.open_mainfile(filepath=setup["blend"])
            props = bpy.context.scene.neulf
            result.update(model_dir=props.model_dir, resolved=resolved(props), status_on_open=props.last_status)
            if setup["train"]:
                result["report"] = reports_of(lambda: bpy.ops.neulf.train(steps=10))  # Train pressed again
                result.update(argv=mod("tasks").get("train").argv, last_status=props.last_status,
                              progress=json.loads((Path(result["resolved"]) / "model.json").read_text())["progress"])
        elif session == "reopen_busy":
            result.update(reopen_while_trained_elsewhere(setup, mod))
        else:
            raise ValueError(f"unknown session {session}")
    except BaseException:  # noqa: BLE001 - reported to the story's step
        result["error"] = traceback.format_exc()
    out.write_text(json.dumps(result, default=str))
    return result


def reopen_while_trained_elsewhere(setup: dict, mod) -> dict:
    """Session: another process trains the model folder (started here, so that this process can
    stop and reap it) while the .blend is opened and Train pressed; then it is stopped."""
    import re
    import signal
    import subprocess

    import bpy

    log = Path(setup["out"]).with_suffix(".train.log")
    with log.open("w") as out:
        other = subprocess.Popen(
            [setup.get("worker_python") or sys.executable, "-m", "neulf_core", "train", setup["scene_dir"],
             "--out", setup["model"], "--resume", "--steps", "1000000", "--progress", "json", "--checkpoint-seconds", "2"],
            env=mod("jobs").core_environment(), stdout=out, stderr=subprocess.STDOUT)
    try:
        def steps_logged():
            return [int(n) for n in re.findall(r'"step": (\d+)', log.read_text())]

        deadline = time.monotonic() + 180
        while len(steps_logged()) < 2 and other.poll() is None and time.monotonic() < deadline:
            time.sleep(0.1)
        assert len(steps_logged()) >= 2, log.read_text()[-2000:]  # it trains: it holds the lock
        bpy.ops.wm.open_mainfile(filepath=setup["blend"])
        props = bpy.context.scene.neulf
        result = {"other_pid": other.pid, "status_on_open": props.last_status,
                  "panel_lines": mod("panel").wrapped_lines(props.last_status, 300)}  # a narrow N-panel
        result["refused"] = error_of(lambda: bpy.ops.neulf.train(steps=10))
        first = json.loads((Path(setup["model"]) / "model.json").read_text())["progress"]["step"]
        deadline = time.monotonic() + 60  # its next periodic checkpoint (every 2 s here)
        while (json.loads((Path(setup["model"]) / "model.json").read_text())["progress"]["step"] == first
               and time.monotonic() < deadline):
            time.sleep(0.5)
        result["tick_while_busy"] = mod("handlers").other_training_tick()  # what the panel's timer runs
        later = int(re.search(r"at step (\d+)", props.last_status).group(1))
        result["steps_followed"] = [first, later]
    finally:
        other.send_signal(signal.SIGTERM)  # the user stops it (Ctrl-C in its terminal): it saves and exits
        other.wait(120)
    result["tick_after"] = mod("handlers").other_training_tick()
    result["status_after"] = props.last_status
    return result


if __name__ == "__main__":
    # A fresh Python with BLENDER_USER_RESOURCES set (see test_blender_extension.py).
    config = json.loads(Path(sys.argv[1]).read_text())
    if "session" in config:
        if run_session(config).get("quit"):
            sys.exit(0)  # Blender quits: bpy's exit handlers disable the add-ons (unregister)
    else:
        run_story(config)
    os._exit(0)  # skip bpy's slow teardown

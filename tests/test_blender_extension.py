"""The Blender extension end to end, under the real bpy 5.0.1 module (headless).

pytest builds the repository into an extension zip with Blender's own builder, validates
it, and then runs this file as a script in a fresh Python (BLENDER_USER_RESOURCES isolated
to a temp folder before bpy is imported) that installs the zip as a user extension and
walks through the artist's story on a tiny synthetic capture: import, check every camera
against pycolmap, train through the operator (blocking and timer paths, cancel, resume),
render, focus, F12, a spiral video, save and reload.  Each step's outcome is written to a
JSON file and checked by its own test below.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time
import traceback
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
BL_PKG_CLI = "5.0/scripts/addons_core/bl_pkg/cli/blender_ext.py"
PACKAGE = "bl_ext.user_default.neulf"

# ----------------------------------------------------------------------------- the synthetic capture

WIDTH, HEIGHT = 64, 48
FX, FY, CX, CY = 58.0, 61.0, 33.3, 22.6          # non-square pixels, off-centre principal point
PLANE_POINT = np.array([0.0, 0.0, 4.0])
PLANE_NORMAL = np.array([0.25, -0.15, -1.0]) / np.linalg.norm([0.25, -0.15, -1.0])
GRID = [(x, y) for y in (-0.3, 0.0, 0.3) for x in (-0.3, 0.0, 0.3)]


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


def make_scene(out: Path) -> Path:
    """A COLMAP scene folder (images/, sparse/0) of the plane seen by a 3x3 rig."""
    import pycolmap
    from PIL import Image

    (out / "images").mkdir(parents=True, exist_ok=True)
    recon = pycolmap.Reconstruction()
    recon.add_camera_with_trivial_rig(pycolmap.Camera(model="PINHOLE", width=WIDTH, height=HEIGHT,
                                                      params=[FX, FY, CX, CY], camera_id=1))
    rng = np.random.default_rng(0)
    for image_id, view in enumerate(scene_views(), start=1):
        rgb, depth = trace(view["R"], view["t"])
        Image.fromarray((rgb * 255 + 0.5).astype(np.uint8)).save(out / "images" / view["name"])
        recon.add_image_with_trivial_frame(pycolmap.Image(name=view["name"], camera_id=1, image_id=image_id),
                                           pycolmap.Rigid3d(pycolmap.Rotation3d(view["R"]), view["t"]))
        rows, cols = rng.integers(0, HEIGHT, 30), rng.integers(0, WIDTH, 30)
        K = K_matrix()
        cam = np.stack([(cols + 0.5 - K[0, 2]) / K[0, 0], (rows + 0.5 - K[1, 2]) / K[1, 1], np.ones(30)], 1)
        cam *= depth[rows, cols][:, None]
        for xyz, colour in zip((cam - view["t"]) @ view["R"], rgb[rows, cols]):
            recon.add_point3D(xyz, pycolmap.Track(), (colour * 255).astype(np.uint8))
    (out / "sparse" / "0").mkdir(parents=True, exist_ok=True)
    recon.write_binary(str(out / "sparse" / "0"))
    return out


# ----------------------------------------------------------------------------- pytest side


def blender_ext_cli() -> Path:
    import importlib.util

    spec = importlib.util.find_spec("bpy")
    if spec is None or spec.origin is None:
        pytest.skip("bpy is not installed")
    cli = Path(spec.origin).parent / BL_PKG_CLI
    if not cli.is_file():
        pytest.skip(f"Blender's extension CLI not found at {cli}")
    return cli


def build_extension(out_dir: Path) -> Path:
    cli = blender_ext_cli()
    run = subprocess.run([sys.executable, str(cli), "build", "--source-dir", str(REPO), "--output-dir", str(out_dir)],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stdout + run.stderr
    zips = list(out_dir.glob("*.zip"))
    assert len(zips) == 1, run.stdout
    return zips[0]


@pytest.fixture(scope="module")
def extension_zip(tmp_path_factory) -> Path:
    return build_extension(tmp_path_factory.mktemp("build"))


def test_build_validate_and_contents(extension_zip):
    import zipfile

    cli = blender_ext_cli()
    for target in (REPO, extension_zip):
        run = subprocess.run([sys.executable, str(cli), "validate", str(target)], capture_output=True, text=True,
                             timeout=120)
        assert run.returncode == 0 and "error" not in (run.stdout + run.stderr).lower(), run.stdout + run.stderr
    names = set(zipfile.ZipFile(extension_zip).namelist())
    assert {"blender_manifest.toml", "__init__.py", "neulf_blender/operators.py", "neulf_core/worker.py",
            "neulf_core/render.py"} <= names
    for excluded in ("tests/", "neulf_synth/", "benchmarks/", "scripts/", ".venv/", ".ci/", "docs/"):
        assert not any(n.startswith(excluded) for n in names), excluded
    assert not any(n.endswith((".sh", ".pyc")) or n == "pyproject.toml" for n in names)


STEPS = ["install", "import", "cameras_match_pycolmap", "slab_planes", "reimport_no_duplicates", "train_blocking",
         "train_timer_resume", "train_cancel", "render_camera", "render_worker_process", "focus_at", "root_scale",
         "engine_f12", "spiral_video", "save_reload", "user_errors", "preferences"]


@pytest.fixture(scope="module")
def story(extension_zip, tmp_path_factory):
    pytest.importorskip("torch")
    work = tmp_path_factory.mktemp("story")
    results = work / "results.json"
    env = dict(os.environ, BLENDER_USER_RESOURCES=str(work / "blender_user"), PYTHONPATH="")
    started = time.monotonic()
    run = subprocess.run([sys.executable, __file__, str(extension_zip), str(work), str(results)], env=env,
                         capture_output=True, text=True, timeout=900)
    if not results.is_file():
        pytest.fail(f"the Blender script did not run (exit {run.returncode}):\n{run.stdout[-3000:]}\n{run.stderr[-5000:]}")
    data = json.loads(results.read_text())
    data["_log"] = run.stdout[-4000:] + run.stderr[-4000:]
    data["_seconds"] = time.monotonic() - started
    return data


@pytest.mark.slow
@pytest.mark.parametrize("step", STEPS)
def test_blender_story(story, step):
    outcome = story.get(step)
    assert outcome is not None, f"step {step} did not run; log:\n{story['_log']}"
    assert outcome["ok"], f"{step}: {outcome['detail']}"
    print(f"{step}: {outcome['detail']}")


# ----------------------------------------------------------------------------- the script (inside bpy)


class Story:
    def __init__(self, zip_path: Path, work: Path, results: Path):
        self.zip_path, self.work, self.results_path = zip_path, work, results
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


def run_story(zip_path: Path, work: Path, results: Path) -> None:  # noqa: C901 - one story, told in order
    import bpy
    from mathutils import Matrix

    story = Story(zip_path, work, results)
    ctx = {}
    scene_dir = make_scene(work / "capture")
    flip = np.diag([1.0, -1.0, -1.0, 1.0])

    def mod(name):
        return sys.modules[f"{PACKAGE}.neulf_blender.{name}"]

    def cameras():
        coll = bpy.data.collections[bpy.context.scene.neulf.collection_name]
        return sorted((o for o in coll.objects if o.type == "CAMERA"), key=lambda o: o["neulf_view"])

    def root():
        return bpy.data.objects[bpy.context.scene.neulf.root_name]

    def image_array(name):
        image = bpy.data.images[name]
        width, height = image.size
        pixels = np.empty(width * height * 4, np.float32)
        image.pixels.foreach_get(pixels)
        return pixels.reshape(height, width, 4)[::-1, :, :3]

    def psnr(a, b):
        return -10 * math.log10(max(float(np.mean((a - b) ** 2)), 1e-12))

    @story.step("install")
    def _():
        bpy.ops.extensions.package_install_files(filepath=str(zip_path), repo="user_default", enable_on_install=True)
        assert PACKAGE in bpy.context.preferences.addons, list(bpy.context.preferences.addons.keys())
        assert hasattr(bpy.types.Scene, "neulf") and hasattr(bpy.ops.neulf, "import_colmap")
        installed = Path(sys.modules[PACKAGE].__file__).parent
        assert (installed / "neulf_core" / "worker.py").is_file()
        ext_user = bpy.utils.extension_path_user(PACKAGE, create=True)
        assert str(work) in ext_user, ext_user
        return f"installed in {installed}"

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
        import pycolmap

        scene = bpy.context.scene
        recon = pycolmap.Reconstruction(str(scene_dir / "sparse" / "0"))
        points = np.array([p.xyz for p in recon.points3D.values()])
        root_inv = np.array(root().matrix_world.inverted())
        worst_px = worst_pose = 0.0
        for cam_obj, view in zip(cameras(), scene_views()):
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
            # Project the sparse points both ways (Blender: through the root, in world space).
            world = (np.array(root().matrix_world) @ np.c_[points, np.ones(len(points))].T)
            clip = P @ np.array(cam_obj.matrix_world.inverted()) @ world
            ndc = clip[:2] / clip[3]
            blender_px = np.stack([(ndc[0] + 1) / 2 * WIDTH, (1 - ndc[1]) / 2 * HEIGHT], 1)
            camera = recon.cameras[1]
            cam_points = points @ view["R"].T + view["t"]
            colmap_px = np.asarray(camera.img_from_cam(cam_points))
            worst_px = max(worst_px, float(np.abs(blender_px - colmap_px).max()))
        assert worst_pose < 1e-5, worst_pose
        assert worst_px < 1e-3, worst_px
        return f"max projection error {worst_px:.2e} px, pose error {worst_pose:.1e}"

    @story.step("slab_planes", "import")
    def _():
        from neulf_core.scene import load_scene, split_views
        from neulf_core.slab import fit_slab

        scene = load_scene(scene_dir)
        slab = fit_slab(scene, split_views(scene, 8)[0])
        ctx["slab"] = slab
        worst = 0.0
        root_inv = root().matrix_world.inverted()
        for plane in ("uv", "st"):
            obj = next(o for o in bpy.data.objects if o.get("neulf_role") == f"{plane}_plane")
            corners = np.array([list(root_inv @ obj.matrix_world @ v.co) for v in obj.data.vertices])
            worst = max(worst, float(np.abs(corners - slab.plane_corners(plane)).max()))
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

    @story.step("train_cancel", "train_timer_resume")
    def _():
        cancel_model = work / "model_cancel"
        props = bpy.context.scene.neulf
        saved = props.model_dir
        props.model_dir = str(cancel_model)
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
        finally:
            props.model_dir = saved
        return f"cancelled at step {job.state['step']}"

    @story.step("render_camera", "train_blocking")
    def _():
        scene = bpy.context.scene
        cam = cameras()[1]                       # a training view (view 0 is held out)
        scene.camera = cam
        mod("capture").apply_capture_camera(scene, cam)
        assert bpy.ops.neulf.render_camera() == {"FINISHED"}
        rendered = image_array("NeuLF Render")
        assert rendered.shape == (HEIGHT, WIDTH, 3)
        from PIL import Image

        photo = np.asarray(Image.open(scene_dir / "images" / cam["neulf_view"]), np.float32) / 255
        model_psnr = psnr(rendered, photo)
        mean_psnr = psnr(photo.mean((0, 1), keepdims=True) + 0 * photo, photo)
        assert model_psnr > mean_psnr + 3, (model_psnr, mean_psnr)
        depth = image_array("NeuLF Depth")[..., 0]
        _, true_depth = trace(scene_views()[1]["R"], scene_views()[1]["t"])
        ctx["render"] = rendered
        return f"PSNR {model_psnr:.2f} dB vs mean colour {mean_psnr:.2f} dB; depth median {np.median(depth):.3f} " \
               f"(true {np.median(true_depth):.3f})"

    @story.step("render_worker_process", "render_camera")
    def _():
        prefs = bpy.context.preferences.addons[PACKAGE].preferences
        prefs.render_mode = "WORKER"
        try:
            core = mod("preferences").get_core()
            assert not core.in_process
            assert bpy.ops.neulf.render_camera() == {"FINISHED"}
            worker_image = image_array("NeuLF Render")
            assert np.abs(worker_image - ctx["render"]).max() <= 1 / 255 + 1e-6
            assert mod("core")._worker is not None and mod("core")._worker.alive
        finally:
            prefs.render_mode = "AUTO"
            mod("core").shutdown()
        return "worker render matches the in-process one"

    @story.step("focus_at", "render_camera")
    def _():
        scene = bpy.context.scene
        result, _request = mod("operators").render_active_camera(bpy.context)
        i, j = 40, 20
        assert bpy.ops.neulf.focus_at(x=i + 0.5, y=j + 0.5) == {"FINISHED"}
        dof = scene.camera.data.dof
        expected = float(result["depth"][j, i])
        assert dof.use_dof and dof.focus_object is None
        assert abs(dof.focus_distance - expected) < 1e-4 * expected, (dof.focus_distance, expected)
        ctx["focus"] = dof.focus_distance
        return f"focus {dof.focus_distance:.4f} = model depth {expected:.4f}"

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
        finally:
            r.matrix_world = original
            bpy.context.view_layer.update()

    @story.step("engine_f12", "render_camera")
    def _():
        scene = bpy.context.scene
        scene.render.engine = "NEULF"
        settings = scene.render.image_settings
        if hasattr(settings, "media_type"):
            settings.media_type = "IMAGE"
        settings.file_format = "PNG"
        out = work / "f12.png"
        scene.render.filepath = str(out)
        bpy.ops.render.render(write_still=True)
        from PIL import Image

        still = np.asarray(Image.open(out).convert("RGB"), np.float32) / 255
        diff = np.abs(still - ctx["render"]).max()
        assert diff <= 2 / 255 + 1e-6, diff
        assert "NEULF" in bpy.types.DATA_PT_camera_dof.COMPAT_ENGINES
        # Depth of field: a wide aperture focused far behind the scene blurs the image
        # (synthetic aperture through the model) without changing its overall colour.
        dof = scene.camera.data.dof
        dof.use_dof, dof.focus_object, dof.focus_distance, dof.aperture_fstop = True, None, 1000.0, 0.05
        out_dof = work / "f12_dof.png"
        scene.render.filepath = str(out_dof)
        bpy.ops.render.render(write_still=True)
        dof.use_dof = False
        blurred = np.asarray(Image.open(out_dof).convert("RGB"), np.float32) / 255
        change = np.abs(blurred - still).mean()
        assert change > 2 / 255 and abs(blurred.mean() - still.mean()) < 0.03, (change, blurred.mean(), still.mean())
        return f"F12 matches render_camera within {diff * 255:.1f}/255; DOF changes it by {change * 255:.1f}/255 on average"

    @story.step("spiral_video", "render_camera")
    def _():
        import av

        scene = bpy.context.scene
        scene.frame_start = 1
        assert bpy.ops.neulf.spiral_path(frames=3) == {"FINISHED"}
        assert scene.frame_end == 3
        poses = []
        for frame in (1, 2, 3):
            scene.frame_set(frame)
            poses.append(np.array(scene.camera.matrix_world))
        assert not np.allclose(poses[0], poses[1])
        video = work / "spiral.mp4"
        assert bpy.ops.neulf.render_video(filepath=str(video)) == {"FINISHED"}
        written = video if video.is_file() else next(work.glob("spiral*.mp4"))
        with av.open(str(written)) as container:
            count = sum(1 for _ in container.decode(video=0))
        assert count == 3, count
        return f"{written.name}: {count} frames"

    @story.step("save_reload", "render_camera")
    def _():
        blend = work / "scenes" / "capture.blend"
        blend.parent.mkdir(exist_ok=True)
        props = bpy.context.scene.neulf
        bpy.ops.wm.save_as_mainfile(filepath=str(blend))
        assert bpy.ops.neulf.load_model(directory=str(model)) == {"FINISHED"}   # stored relative once saved
        assert props.model_dir.startswith("//"), props.model_dir
        bpy.ops.wm.save_mainfile()
        bpy.ops.wm.open_mainfile(filepath=str(blend))
        props = bpy.context.scene.neulf
        assert Path(bpy.path.abspath(props.model_dir)).resolve() == model.resolve(), props.model_dir
        assert bpy.ops.neulf.render_camera() == {"FINISHED"}
        return props.model_dir

    @story.step("user_errors", "install")
    def _():
        props = bpy.context.scene.neulf
        props.model_dir = str(work / "no_such_model")
        messages = []
        for call in (lambda: bpy.ops.neulf.render_camera(), lambda: bpy.ops.neulf.import_colmap(directory=str(work)),
                     lambda: bpy.ops.neulf.focus_at(x=1, y=1)):
            try:
                call()
            except RuntimeError as exc:  # background mode turns an ERROR report into RuntimeError
                messages.append(str(exc))
            else:
                raise AssertionError("expected an error report")
        assert all("Traceback" not in m and m.startswith("Error:") for m in messages), messages
        return " | ".join(m.strip() for m in messages)

    @story.step("preferences", "install")
    def _():
        prefs = bpy.context.preferences.addons[PACKAGE].preferences
        assert bpy.ops.neulf.check_dependencies() == {"FINISHED"}
        assert prefs.status.startswith("torch ") and "device: cpu" in prefs.status, prefs.status
        deps = Path(mod("preferences").deps_dir(create=True))
        assert str(work / "blender_user") in str(deps) and deps.is_dir()
        if not bpy.app.online_access:  # the default headless: installing must refuse, clearly
            try:
                bpy.ops.neulf.install_dependencies()
            except RuntimeError as exc:
                assert "Online access is disabled" in str(exc), exc
            else:
                raise AssertionError("install ran without online access")
        return prefs.status

    story.results_path.write_text(json.dumps(story.results, indent=1, default=str))


if __name__ == "__main__":
    # Runs inside a fresh Python with BLENDER_USER_RESOURCES set (see `story`).
    sys.path.insert(0, str(REPO))  # the test's own neulf_core (for reference values only)
    run_story(Path(sys.argv[1]), Path(sys.argv[2]), Path(sys.argv[3]))
    os._exit(0)  # skip bpy's slow teardown

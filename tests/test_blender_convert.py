"""The Blender-free half of the extension: camera conversions, the worker protocol, job parsing.

`neulf_blender` uses relative imports (`..neulf_core`), as an extension must, so it is
imported here as a subpackage of the repository root under a temporary package name.
No bpy is imported.
"""

from __future__ import annotations

import importlib
import io
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def ext(extension_module):
    convert, jobs = extension_module("convert"), extension_module("jobs")
    assert "bpy" not in sys.modules or sys.modules.get("bpy") is not None
    return type("Ext", (), {"convert": convert, "jobs": jobs})


def test_root_init_imports_without_bpy(ext):
    root = importlib.import_module("neulf_ext")
    assert callable(root.register) and callable(root.unregister)
    assert "neulf_ext.neulf_blender.operators" not in sys.modules  # nothing Blender-side at import


@pytest.mark.parametrize("fx,fy,cx,cy,width,height", [
    (500.0, 500.0, 320.0, 240.0, 640, 480),
    (812.5, 790.25, 301.7, 260.9, 640, 480),     # fy < fx, off-centre
    (412.0, 455.0, 170.2, 310.8, 360, 640),      # portrait, fy > fx
    (58.0, 61.0, 33.3, 22.6, 64, 48),
])
def test_K_round_trip(ext, fx, fy, cx, cy, width, height):
    settings = ext.convert.blender_camera_from_K(fx, fy, cx, cy, width, height)
    K = ext.convert.K_from_blender(lens=settings["lens"], sensor_width=settings["sensor_width"], sensor_height=24.0,
                                   sensor_fit=settings["sensor_fit"], shift_x=settings["shift_x"],
                                   shift_y=settings["shift_y"], width=width, height=height,
                                   pixel_aspect_x=settings["pixel_aspect_x"], pixel_aspect_y=settings["pixel_aspect_y"])
    assert np.allclose(K, [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], atol=1e-9)


def test_K_sensor_fits(ext):
    common = dict(lens=50.0, sensor_width=36.0, sensor_height=24.0, shift_x=0.0, shift_y=0.0)
    # AUTO on a portrait image fits the sensor width to the image height.
    K = ext.convert.K_from_blender(sensor_fit="AUTO", width=400, height=800, **common)
    assert K[0, 0] == pytest.approx(50 / 36 * 800) and K[1, 1] == K[0, 0]
    K = ext.convert.K_from_blender(sensor_fit="VERTICAL", width=800, height=400, **common)
    assert K[1, 1] == pytest.approx(50 / 24 * 400)
    # Shift moves the principal point by shift x the larger dimension; +y shift moves the view up, so the
    # principal point moves down the image (larger cy).
    K = ext.convert.K_from_blender(sensor_fit="AUTO", width=800, height=400, lens=50.0, sensor_width=36.0,
                                   sensor_height=24.0, shift_x=0.1, shift_y=0.1)
    assert (K[0, 2], K[1, 2]) == pytest.approx((400 - 80, 200 + 80))


def _random_rotation(rng):
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def test_pose_round_trip_and_root_scale(ext):
    rng = np.random.default_rng(1)
    for _ in range(5):
        R, t = _random_rotation(rng), rng.normal(size=3)
        M = ext.convert.matrix_from_pose(R, t)
        assert np.allclose(M[:3, :3] @ M[:3, :3].T, np.eye(3))
        # Blender cameras look down -z: the matrix's -z column is COLMAP's viewing direction R[2].
        assert np.allclose(-M[:3, 2], R[2])
        R2, t2 = ext.convert.pose_from_matrix(M)
        assert np.allclose(R2, R) and np.allclose(t2, t)
        # Through a root scaled by 3: the relative matrix carries 1/3; rotation and centre survive.
        root = np.diag([3.0, 3.0, 3.0, 1.0])
        root[:3, 3] = rng.normal(size=3)
        relative = np.linalg.inv(root) @ (root @ M)
        R3, t3 = ext.convert.pose_from_matrix(relative)
        assert np.allclose(R3, R) and np.allclose(t3, t)
        assert ext.convert.uniform_scale(root) == pytest.approx(3.0)


def test_a_sheared_camera_is_refused_and_an_unevenly_scaled_one_is_not(ext):
    """A camera under a turned parent scaled unevenly has a sheared matrix, which Blender renders
    through its normalised, non-orthogonal axes: no pinhole does (the nearest rotation had rendered
    23 px off Cycles in the Blender audit).  The camera's own uneven scale, without a turn between,
    leaves its axes perpendicular: Blender normalises them, and so does the pose."""
    rng = np.random.default_rng(2)
    R, t = _random_rotation(rng), rng.normal(size=3)
    M = ext.convert.matrix_from_pose(R, t)
    parent = np.eye(4)
    parent[:3, :3] = _random_rotation(rng) @ np.diag([1.0, 2.5, 0.6])
    with pytest.raises(ValueError, match="sheared"):
        ext.convert.pose_from_matrix(parent @ M)
    own_scale = M @ np.diag([1.0, 1.0, 3.0, 1.0])
    R2, t2 = ext.convert.pose_from_matrix(own_scale)
    assert np.allclose(R2, R)
    evenly = np.eye(4)
    evenly[:3, :3] = _random_rotation(rng) * 2.0
    ext.convert.pose_from_matrix((evenly @ M).astype(np.float32))  # (float32, as Blender's matrices)


def test_image_rows_and_colour(ext):
    rgb = np.zeros((2, 3, 3), np.float32)
    rgb[0] = 1.0  # top row white
    flat = ext.convert.image_rows_for_blender(rgb)
    assert flat.dtype == np.float32 and flat.shape == (2 * 3 * 4,)
    rows = flat.reshape(2, 3, 4)
    assert (rows[1, :, :3] == 1).all() and (rows[0, :, :3] == 0).all() and (rows[..., 3] == 1).all()
    assert ext.convert.srgb_to_linear(np.array([0.0, 0.5, 1.0])) == pytest.approx([0.0, 0.21404, 1.0], abs=1e-4)
    alpha = np.array([[1.0, 0.0, 1.0], [0.0, 1.0, 1.0]], np.float32)  # Film > Transparent: 0 off the slab
    rows = ext.convert.image_rows_for_blender(rgb, alpha).reshape(2, 3, 4)
    assert rows[..., 3].tolist() == [[0.0, 1.0, 1.0], [1.0, 0.0, 1.0]]  # bottom row first, as the colours


def test_depth_rows_for_a_z_pass(ext):
    """F12's Depth pass: Blender's bottom-row-first order, and Cycles' 1e10 where the light field
    has no depth (a compositor's Z Combine then puts CG in front, not behind a hole)."""
    depth = np.array([[1.5, np.nan, 2.0], [3.0, 4.0, np.inf]], np.float32)
    flat = ext.convert.depth_rows_for_blender(depth)
    assert flat.dtype == np.float32 and flat.shape == (6,)
    assert flat.tolist() == [3.0, 4.0, 1e10, 1.5, 1e10, 2.0]
    assert ext.convert.NO_DEPTH == 1e10


def test_single_pixel_K_is_that_pixels_ray():
    torch = pytest.importorskip("torch")
    from neulf_core.rays import pinhole_rays
    from neulf_core.rays import single_pixel_K

    K = np.array([[58.0, 0, 33.3], [0, 61.0, 22.6], [0, 0, 1]])
    R, t = np.eye(3), np.zeros(3)
    _, all_dirs = pinhole_rays(K, R, t, 64, 48, dtype=torch.float64)
    _, one = pinhole_rays(single_pixel_K(K, 40.5, 20.5), R, t, 1, 1, dtype=torch.float64)
    assert torch.allclose(one[0], all_dirs.reshape(48, 64, 3)[20, 40])


def test_a_render_region_renders_the_full_frames_pixels(ext):
    """F12 with a render region: the region's pixels (Blender's y fractions count from the
    bottom) through a cropped camera whose every pixel sees the ray the full frame's did."""
    torch = pytest.importorskip("torch")
    from neulf_core.rays import pinhole_rays

    # x from 0.25 to 0.75 of 64 pixels, y the upper half (0.5 to 1.0 from the bottom) of 48
    assert ext.convert.border_region(64, 48, (0.25, 0.75), (0.5, 1.0)) == (16, 0, 32, 24)
    assert ext.convert.border_region(64, 48, (0.0, 0.5), (0.0, 0.25)) == (0, 36, 32, 12)
    K = [[58.0, 0.0, 33.3], [0.0, 61.0, 22.6], [0.0, 0.0, 1.0]]
    R, t = np.eye(3), np.zeros(3)
    request = {"K": K, "width": 64, "height": 48, "R": R.tolist(), "t": t.tolist()}
    left, top, width, height = ext.convert.border_region(64, 48, (0.25, 0.75), (0.125, 0.5))
    crop = ext.convert.crop_request(request, left, top, width, height)
    assert (crop["width"], crop["height"]) == (width, height) and request["K"] == K  # (the request left as it was)
    _, full = pinhole_rays(K, R, t, 64, 48, dtype=torch.float64)
    _, cropped = pinhole_rays(crop["K"], R, t, width, height, dtype=torch.float64)
    window = full.reshape(48, 64, 3)[top:top + height, left:left + width]
    assert torch.allclose(cropped.reshape(height, width, 3), window)


def test_worker_protocol_errors_are_one_line(tmp_path):
    from neulf_core.worker import serve

    requests = "\n".join(json.dumps(r) for r in [
        {"id": 1, "op": "nope"},
        {"id": 2, "op": "describe_scene", "args": {"scene_dir": str(tmp_path / "missing")}},
        {"id": 3, "op": "quit"},
    ]) + "\n"
    out = io.StringIO()
    serve(io.StringIO(requests), out, tmp_path)
    answers = [json.loads(line) for line in out.getvalue().splitlines()]
    assert [a["id"] for a in answers] == [1, 2, 3]
    assert not answers[0]["ok"] and "no operation 'nope'" in answers[0]["error"]
    assert not answers[1]["ok"] and answers[1]["kind"] == "NeulfError" and "does not exist" in answers[1]["error"]
    assert answers[2]["ok"]


def test_worker_says_what_to_do_about_memory_and_missing_packages(tmp_path, monkeypatch):
    """Out of memory (torch's CPU allocator raises a plain RuntimeError) and a package the
    worker's Python lacks (or built for another Python) reach Blender as what to do, like the
    CLI's and Check's lines; a programming error still names itself."""
    from neulf_core import worker
    from neulf_core.errors import OTHER_PYTHONS_PACKAGES, OUT_OF_MEMORY

    failures = iter([RuntimeError("[enforce fail at alloc_cpu.cpp:127] DefaultCPUAllocator: can't allocate memory"),
                     ModuleNotFoundError("No module named 'torch'", name="torch"),
                     ImportError("numpy failed", name="numpy.core._multiarray_umath"),
                     RuntimeError("mat1 and mat2 shapes cannot be multiplied")])

    def failing(self, **_args):
        raise next(failures)

    monkeypatch.setattr(worker.Service, "model_info", failing)
    requests = "".join(json.dumps({"id": i, "op": "model_info", "args": {"model_dir": "m"}}) + "\n" for i in range(4))
    out = io.StringIO()
    worker.serve(io.StringIO(requests), out, tmp_path)
    errors = [json.loads(line)["error"] for line in out.getvalue().splitlines()]
    assert errors[0] == OUT_OF_MEMORY
    assert errors[1].startswith("the NeuLF Python has no 'torch'") and "Install dependencies" in errors[1]
    assert errors[2] == OTHER_PYTHONS_PACKAGES
    assert errors[3] == "RuntimeError: mat1 and mat2 shapes cannot be multiplied"


def test_an_older_python_is_told_before_any_import_fails():
    """neulf_core says which Python it needs before reading a module whose syntax an older
    one cannot parse (a Python chosen in Blender's preferences, or on the command line)."""
    code = "import sys; sys.version_info = (3, 9, 18, 'final', 0); import neulf_core"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          cwd=Path(__file__).resolve().parents[1])
    assert done.returncode == 1
    assert done.stderr.strip() == ("error: neulf_core needs Python 3.10 or newer; this is Python 3.9 (in Blender: choose "
                                   "another Python in the NeuLF preferences).")


def test_a_killed_process_is_said_to_be_killed(ext):
    """A process ended by a signal without a word (the out-of-memory killer sends SIGKILL) is
    named as such, not 'ended without a message'."""
    if os.name == "nt":
        pytest.skip("POSIX signals")
    job = ext.jobs.CommandJob([sys.executable, "-c", "import os, signal; os.kill(os.getpid(), signal.SIGKILL)"])
    state = job.wait(timeout=60)
    assert state["status"] == "failed"
    assert state["error"] == "the process was killed (SIGKILL, as the system does when memory runs out)."
    assert ext.jobs.ending_text(["Traceback", "error: disk full"], -9) == "disk full"  # (its own words first)
    assert ext.jobs.ending_text([], 1) == "the process ended without a message."


def test_thread_call_ends_with_result_error_or_cancel(ext):
    """Render Camera in the UI runs on a thread (Blender stays usable; Esc cancels): the
    thread's three endings, and its progress."""
    NeulfError = ext.jobs.NeulfError  # (the extension's own: its neulf_core is imported as the extension's)

    def counting(on_progress, should_stop):
        for i in range(1000):
            on_progress(i / 1000)
            if should_stop():
                raise InterruptedError("cancelled")
            time.sleep(0.005)
        return "done"

    finished = ext.jobs.ThreadCall(lambda on_progress, should_stop: "image")
    finished.wait(10)
    assert (finished.result, finished.error, finished.cancelled, finished.running) == ("image", None, False, False)

    def refusing(on_progress, should_stop):
        raise NeulfError("the camera is behind the light field.")

    refused = ext.jobs.ThreadCall(refusing)
    refused.wait(10)
    assert (refused.result, refused.error, refused.cancelled) == (None, "the camera is behind the light field.", False)

    cancelled = ext.jobs.ThreadCall(counting)
    while cancelled.fraction == 0.0:
        time.sleep(0.01)
    cancelled.cancel()
    cancelled.wait(10)
    assert cancelled.cancelled and cancelled.result is None and cancelled.error is None and not cancelled.running
    assert 0.0 < cancelled.fraction < 1.0

    broken = ext.jobs.ThreadCall(lambda on_progress, should_stop: 1 / 0)
    broken.wait(10)
    assert broken.error == "NeuLF failed (ZeroDivisionError: division by zero); the console has the details."


def test_worker_process_describes_a_scene(ext, tmp_path):
    pytest.importorskip("torch")
    from test_blender_extension import make_scene, scene_views

    scene = make_scene(tmp_path / "capture")
    client = ext.jobs.WorkerClient(sys.executable, tmp_path / "scratch", ext.jobs.core_environment())
    try:
        info = client.call("info", timeout=120)
        assert info["device"] in ("cpu", "cuda", "mps") and info["torch"]
        description = client.call("describe_scene", scene_dir=str(scene), timeout=120)
        assert [v["name"] for v in description["views"]] == [v["name"] for v in scene_views()]
        assert isinstance(description["points"], np.ndarray) and description["points"].shape == (270, 3)
        assert not list((tmp_path / "scratch").iterdir())  # arrays were read and removed
        with pytest.raises(Exception, match="no camera model"):
            client.call("describe_scene", scene_dir=str(tmp_path), timeout=60)
        assert client.alive  # a user error does not end the worker
        # A bug's traceback on the worker's stderr belongs to its call: a later call (which may find
        # the worker killed) does not give it as its cause.
        with pytest.raises(Exception, match="TypeError"):
            client.call("model_info", model_dir=str(tmp_path), bogus=1, timeout=60)
        time.sleep(0.2)  # (the stderr reader catches the traceback)
        assert any("TypeError" in line for line in client._stderr)
        client.call("info", timeout=60)
        assert not any("TypeError" in line for line in client._stderr), list(client._stderr)
    finally:
        client.close()
    assert not client.alive


def test_worker_that_cannot_start_explains_itself(ext, tmp_path):
    client = ext.jobs.WorkerClient(str(tmp_path / "no_python"), tmp_path / "scratch", ext.jobs.core_environment())
    with pytest.raises(Exception, match="cannot start .*NeuLF preferences"):
        client.call("info", timeout=60)


def test_worker_scratch_folder_goes_with_the_worker(ext):
    """Each Blender session's worker had left an empty /tmp/neulf_worker_* behind (58 of them on
    the development machine): shutdown, which unregister and interpreter exit run, removes it."""
    pytest.importorskip("torch")
    core = importlib.import_module("neulf_ext.neulf_blender.core")
    try:
        info = core.Core(sys.executable, mode="WORKER").call("info")
        assert info["torch"]
        scratch = core._scratch
        assert scratch is not None and scratch.is_dir()
        (scratch / "stray.npy").write_bytes(b"left by a cancelled render")
    finally:
        core.shutdown()
    assert not scratch.exists() and core._worker is None


def test_worker_scratch_folder_goes_at_interpreter_exit(tmp_path):
    """Blender quits without unregistering add-ons: the exit handler ends the worker and its folder."""
    pytest.importorskip("torch")
    (tmp_path / "neulf_ext").symlink_to(REPO, target_is_directory=True)
    script = (
        "import sys; sys.path.insert(0, sys.argv[1])\n"
        "from neulf_ext.neulf_blender import core\n"
        "core.Core(sys.executable, mode='WORKER').call('info')\n"
        "print(core._scratch)\n"
    )
    done = subprocess.run([sys.executable, "-c", script, str(tmp_path)], capture_output=True, text=True, timeout=180)
    assert done.returncode == 0, done.stderr
    scratch = Path(done.stdout.strip().splitlines()[-1])
    assert scratch.name.startswith("neulf_worker_") and not scratch.exists()


def test_train_job_parses_events(ext):
    job = ext.jobs.TrainJob.__new__(ext.jobs.TrainJob)
    job.state = {"status": "running", "fraction": 0.0, "message": "", "error": None, "started": 0.0, "step": 0,
                 "elapsed": 0.0, "val_psnr": None, "loss": None, "device": "", "warnings": []}
    job._cancelled = False
    for event in [{"event": "start", "train_views": 7, "device": "cpu (2 threads)", "held_out": []},
                  {"event": "step", "step": 10, "elapsed": 2.0, "loss": 0.01, "fraction": 0.25},
                  {"event": "validate", "step": 20, "elapsed": 4.0, "loss": 0.01, "fraction": 0.5, "val_psnr": 21.5},
                  {"event": "warning", "message": "careful"},
                  {"event": "losses", "train_views": 7, "message": "7 photos: training with the paper's multi-view losses, ..."},
                  {"event": "passes", "train_views": 7, "steps": 20, "message": "7 photos: training stops at ..."},
                  {"event": "appearance", "train_views": 7, "exposure_difference_stops": 0.31, "message": "..."},
                  {"event": "poses", "median_degrees": 0.08, "max_degrees": 0.13, "median_shift": 0.01, "max_shift": 0.02},
                  {"event": "pose_check", "refining": False, "median_degrees": 0.03, "halfway_degrees": 0.05, "step": 100,
                   "message": "the camera poses agree with the photos (...): not refining them"}]:
        job.on_stdout(json.dumps(event))
    assert job.state["message"].startswith("the camera poses agree")  # the pose check's verdict, until the next step
    job.on_stdout(json.dumps({"event": "step", "step": 20, "elapsed": 4.0, "loss": 0.01, "fraction": 0.5}))
    job.on_stdout("not json")
    assert "camera poses checked, not refined" in ext.jobs.job_status_text({**job.state, "status": "finished"})
    assert "barely trained" not in ext.jobs.job_status_text({**job.state, "status": "finished"})
    assert job.state["step"] == 20 and job.state["fraction"] == 0.5 and job.state["val_psnr"] == 21.5
    assert job.state["device"].startswith("cpu") and job.state["warnings"] == ["careful"]
    job.on_stdout(json.dumps({"event": "warning", "message": "the 1-minute budget ended after only 30 steps ...",
                              "barely_trained": True}))
    assert "; barely trained: the budget ended before a light field is more than a blur (Train trains it further)" in \
        ext.jobs.job_status_text({**job.state, "status": "finished"})
    assert job.state["poses"]["max_degrees"] == 0.13
    assert job.state["losses"] is True and job.state["pass_limit"] == 20
    job.state["status"] = "finished"  # at the limit, before the panel's minutes were up: the panel says why
    assert "more training would only memorise so few photos" in ext.jobs.job_status_text(job.state)
    assert "a colour transform per photo (exposures differ by 0.31 stops)" in ext.jobs.job_status_text(job.state)
    assert "of two random starts" not in ext.jobs.job_status_text(job.state)
    # Two members of half the batch: the step said is the first's, the limit said last the second's.
    ended = ext.jobs.TrainJob.__new__(ext.jobs.TrainJob)
    ended.state, ended._cancelled = {**job.state}, False
    ended.on_stdout(json.dumps({"event": "finished", "step": 15, "elapsed": 9.0, "val_psnr": None,
                                "member_steps": [15, 20], "members_split": "batch"}))
    assert (ended.state["step"], ended.state["last_member_step"]) == (15, 20)
    members = {**job.state, "step": 15, "last_member_step": 20}
    assert "more training would only memorise" in ext.jobs.job_status_text(members)
    assert "more training would only memorise" not in ext.jobs.job_status_text({**members, "last_member_step": 19})
    job.on_stdout(json.dumps({"event": "step", "step": 5, "elapsed": 1.0, "loss": 0.01, "fraction": 0.3, "start": 2}))
    assert job.state["message"] == "second start, step 5"
    job.on_stdout(json.dumps({"event": "stage", "message": "kept the second start (seed 101); training it on",
                              "kept": "second"}))
    assert job.state["message"].startswith("kept the second start")
    assert "the second of two random starts kept" in ext.jobs.job_status_text(job.state)
    job.state["step"] = 19
    assert "memorise" not in ext.jobs.job_status_text(job.state)
    assert "restarted" not in ext.jobs.job_status_text(job.state)
    job.on_stdout(json.dumps({"event": "field_restart", "step": 100, "median_degrees": 1.7,
                              "message": "the camera poses are far off (...): the light field starts again ..."}))
    assert job.state["message"].startswith("the camera poses are far off")
    assert "camera poses far off: restarted with smoother geometry" in ext.jobs.job_status_text(job.state)


def _job_argv(ext, tmp_path):
    """argv(**options): the command line a TrainJob with those options runs (/bin/true stands
    in for the NeuLF Python: only argv matters)."""
    def argv(**options):
        job = ext.jobs.TrainJob("/bin/true", str(tmp_path), str(tmp_path / "m"), steps=5, **options)
        job.process.wait(timeout=30)
        return job.argv

    return argv


def test_train_job_passes_the_sweep_teacher_only_to_a_new_model(ext, tmp_path):
    """The panel's "Depth from Photos" becomes `train --[no-]sweep-teacher`; a resumed model keeps
    the choice saved with it."""
    argv = _job_argv(ext, tmp_path)

    assert "--sweep-teacher" in argv(sweep_teacher=True)
    assert "--no-sweep-teacher" in argv(sweep_teacher=False)
    assert not any("sweep-teacher" in a for a in argv())  # the preset decides
    assert not any("sweep-teacher" in a for a in argv(sweep_teacher=False, resume=True))


def test_train_job_passes_the_image_scale_only_when_set(ext, tmp_path):
    """The panel's "Image Scale" becomes `train --scale F`; 0 (the operator passes None) leaves it
    out, so the trainer's rule decides; a resumed model keeps its own."""
    argv = _job_argv(ext, tmp_path)

    half = argv(scale=0.5)
    assert half[half.index("--scale") + 1] == "0.5"
    assert "--scale" not in argv(scale=None) and "--scale" not in argv()
    assert "--scale" not in argv(scale=0.5, resume=True)


def test_train_job_passes_depth_layers_only_to_a_new_model(ext, tmp_path):
    """The panel's "Depth Layers" becomes `train --depth-layers N` (-1: left out, the trainer decides)."""
    argv = _job_argv(ext, tmp_path)

    layered = argv(depth_layers=8)
    assert layered[layered.index("--depth-layers") + 1] == "8"
    none = argv(depth_layers=0)
    assert none[none.index("--depth-layers") + 1] == "0"
    assert "--depth-layers" not in argv()
    assert "--depth-layers" not in argv(depth_layers=8, resume=True)


def test_train_job_passes_exposure_and_pose_options_only_to_a_new_model(ext, tmp_path):
    """The panel's "Varying Exposure" and "Refine Poses" (Auto / On / Off) become nothing /
    `train --appearance` / `--no-appearance`, and nothing / `--refine-poses` / `--no-refine-poses`; a resumed model keeps
    what it was trained with.  "Stop Early" off becomes `train --max-passes 0`, for a
    continued model too."""
    argv = _job_argv(ext, tmp_path)

    both = argv(appearance=True, refine_poses=True)
    assert "--appearance" in both and "--refine-poses" in both
    assert "--appearance" not in argv() and "--refine-poses" not in argv()
    assert "--no-appearance" in argv(appearance=False) and "--no-appearance" not in argv()  # Auto: the trainer decides
    assert "--no-refine-poses" in argv(refine_poses=False) and "--no-refine-poses" not in argv()
    resumed = argv(appearance=True, refine_poses=True, resume=True)
    assert "--appearance" not in resumed and "--refine-poses" not in resumed
    assert "--no-appearance" not in argv(appearance=False, resume=True)
    assert "--no-refine-poses" not in argv(refine_poses=False, resume=True)
    # "Back Surface" likewise: Auto is the trainer's rule (deep scenes), and a saved field keeps its own.
    assert "--back-surface" in argv(back_surface=True) and "--no-back-surface" in argv(back_surface=False)
    assert not {"--back-surface", "--no-back-surface"} & (set(argv()) | set(argv(back_surface=True, resume=True)))
    # "Stop Early" off: no pass limit, for a new model and for one continued past its limit.
    assert "--max-passes" not in argv()
    for options in ({}, {"resume": True}):
        trains_on = argv(stop_early=False, **options)
        assert trains_on[trains_on.index("--max-passes") + 1] == "0"
    # "Two Starts" on is the trainer's rule; off asks for one start (a new model: a continued
    # one keeps the start it has).
    assert "--no-two-starts" in argv(two_starts=False) and not any("two-starts" in a for a in argv())
    assert "--no-two-starts" not in argv(two_starts=False, resume=True)
    # "Members": a new model trains that many (0: the trainer's rule); a continued one keeps its own count.
    for count in (1, 2):
        asked = argv(members=count)
        assert asked[asked.index("--members") + 1] == str(count)
    assert "--members" not in argv() and "--members" not in argv(members=2, resume=True)


def test_explain_failure(ext):
    assert ext.jobs.explain_failure(["x", "error: the scene is bad."]) == "the scene is bad."
    assert "no 'torch'" in ext.jobs.explain_failure(["ModuleNotFoundError: No module named 'torch'"])
    assert ext.jobs.explain_failure([]) == "the process ended without a message."
    # Packages installed for another Python version (say, a deps folder left by Blender 5.0's 3.11, read by 3.13).
    from neulf_core.errors import OTHER_PYTHONS_PACKAGES
    assert ext.jobs.explain_failure(["ModuleNotFoundError: No module named 'numpy.core._multiarray_umath'"]) == \
        OTHER_PYTHONS_PACKAGES


def test_camera_view_border(ext):
    border = ext.convert.camera_view_border
    common = dict(sensor_fit="AUTO", shift_x=0.0, shift_y=0.0, resolution_x=800, resolution_y=500)
    fit_zoom = 50 * (2 - math.sqrt(2))  # Blender's zoom factor 1: the frame fills a region of its aspect
    assert border(800, 500, view_camera_zoom=fit_zoom, view_camera_offset=(0, 0), **common) == pytest.approx(
        (0, 0, 800, 500))
    # A region twice as big shows the same frame twice as big, centred.
    assert border(1600, 1000, view_camera_zoom=fit_zoom, view_camera_offset=(0, 0), **common) == pytest.approx(
        (0, 0, 1600, 1000))
    # Panning the view by 0.1 (of the frame's width) moves the frame the other way.
    assert border(800, 500, view_camera_zoom=fit_zoom, view_camera_offset=(0.1, 0), **common) == pytest.approx(
        (-160, 0, 640, 500))
    # A region of another aspect: the frame keeps its own, fitted to the region's width, centred.
    assert border(1000, 500, view_camera_zoom=fit_zoom, view_camera_offset=(0, 0), **common) == pytest.approx(
        (0, -62.5, 1000, 562.5))
    # Wide pixels (aspect 2:1) make the frame twice as wide for its pixel count.
    tall = dict(common, resolution_x=400, pixel_aspect_x=2.0)
    assert border(800, 500, view_camera_zoom=fit_zoom, view_camera_offset=(0, 0), **tall) == pytest.approx(
        (0, 0, 800, 500))


def test_border_to_pixel(ext):
    to_pixel = ext.convert.border_to_pixel
    frame = (100.0, 50.0, 740.0, 530.0)  # 640 x 480 region pixels for a 64 x 48 image
    assert to_pixel(frame, 100.0, 530.0, 64, 48) == pytest.approx((0, 0))        # top-left corner
    assert to_pixel(frame, 740.0, 50.0, 64, 48) == pytest.approx((64, 48))       # bottom-right corner
    assert to_pixel(frame, 405.0, 325.0, 64, 48) == pytest.approx((30.5, 20.5))  # a pixel centre
    assert to_pixel(frame, 99.0, 300.0, 64, 48) is None and to_pixel(frame, 300.0, 531.0, 64, 48) is None


BLOCK_TORCH = """
import importlib.abc, json, sys
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in ("torch", "pycolmap", "bpy"):
            raise ImportError(f"No module named {name!r} (blocked: Blender's Python has none)")
sys.meta_path.insert(0, Block())
sys.path.insert(0, sys.argv[1])
from neulf_ext.neulf_blender import jobs
client = jobs.WorkerClient(sys.argv[2], sys.argv[3], jobs.core_environment())
try:
    description = client.call("describe_scene", scene_dir=sys.argv[4], timeout=120)
finally:
    client.close()
print(json.dumps({"points": list(description["points"].shape), "views": len(description["views"]),
                  "loaded": sorted(m for m in ("torch", "pycolmap") if m in sys.modules)}))
"""


def test_worker_route_needs_no_torch_in_blender(ext, tmp_path):
    """Blender's Python has no torch or pycolmap: the client side of the worker must not import them."""
    pytest.importorskip("torch")
    from test_blender_extension import make_scene

    scene = make_scene(tmp_path / "capture")
    parent = Path(sys.modules["neulf_ext"].__path__[0]).parent
    run = subprocess.run([sys.executable, "-c", BLOCK_TORCH, str(parent), sys.executable, str(tmp_path / "scratch"),
                          str(scene)], capture_output=True, text=True, timeout=300, cwd=tmp_path,
                         env=dict(os.environ, PYTHONPATH=""))
    assert run.returncode == 0, run.stderr[-3000:]
    answer = json.loads(run.stdout.strip().splitlines()[-1])
    assert answer == {"points": [270, 3], "views": 9, "loaded": []}


def test_a_root_scaled_unevenly_is_refused(ext):
    """A light field scales as a whole: a root of scale (1, 1, 2) had rendered 18 pixels off
    Blender's own projection without a word."""
    turned = np.eye(4)
    turned[:3, :3] = 2.5 * np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    ext.convert.refuse_uneven_scale(turned)  # (turned and scaled evenly: fine)
    with pytest.raises(Exception, match="scaled unevenly"):
        ext.convert.refuse_uneven_scale(np.diag([1.0, 1.0, 2.0, 1.0]))


def test_the_first_scene_camera_is_of_the_photos_most_common_size(ext):
    sizes = [(64, 48), (40, 56), (64, 48), (64, 48)]
    centres = [[1.0, 0, 0], [0.0, 0, 0], [-1.0, 0, 0], [0.5, 0, 0]]
    assert ext.convert.first_scene_camera(sizes, centres) == 3  # (the portrait photo stands in the middle)
    assert ext.convert.first_scene_camera([(64, 48)] * 3, [[1.0, 0, 0], [0.1, 0, 0], [-1.0, 0, 0]]) == 1


def test_the_cores_advice_in_blenders_words(extension_module):
    """Each phrase Blender rewords is one the core says (its string literals, joined where a
    message runs over several lines), so a core message reworded cannot leave its Blender form
    behind unnoticed; and the rewording names what to do in Blender, not a command-line flag."""
    import re

    wording = extension_module("wording")
    core = Path(__file__).resolve().parents[1] / "neulf_core"
    source = "".join(path.read_text() for path in sorted(core.rglob("*.py")))
    source = re.sub(r'"\s*\n\s*f?"', "", source)
    for pattern, _words in wording.PHRASES:
        assert re.search(pattern, source), pattern
    said = wording.panel_words("view a.png has no image file; pass --images with the folder that holds it.")
    assert said == "view a.png has no image file; choose the folder that holds it as Images in Import COLMAP / LLFF."
    said = wording.panel_words("no camera model in /s: ... To make one from photos run: python -m neulf_core "
                               "reconstruct PHOTOS --out /s")
    assert said.endswith("To make one from photos, use Reconstruct Photos in the NeuLF panel"), said
    said = wording.panel_words("no camera model in /s: ... To make one from photos run: python -m neulf_core "
                               "reconstruct PHOTOS --out '/home/u/My Scans/cap'")
    assert said.endswith("To make one from photos, use Reconstruct Photos in the NeuLF panel"), said
    said = wording.panel_words("scale 1e-06 makes the 48x36 photos 1x1 pixels, too small to learn from (at least 8 "
                               "pixels a side): give a larger --scale, or leave it out for the default.")
    assert "--" not in said and "a larger Image Scale, or 0 for the default" in said, said


def test_every_core_call_the_extension_makes_is_a_worker_operation():
    """Blender calls the core in its own Python or through the worker process (a chosen Python,
    Render In: Worker): an operation the worker does not serve had worked in the first and ended
    in "the worker has no operation" in the second (restore_metadata, in the session that added it)."""
    import re

    from neulf_core.worker import OPS, Service

    extension = Path(__file__).resolve().parents[1] / "neulf_blender"
    called = {op for path in extension.glob("*.py") for op in re.findall(r'\.call\(\s*"(\w+)"', path.read_text())}
    assert {"render", "restore_metadata", "describe_scene"} <= called, called
    assert called <= OPS, called - OPS
    assert all(callable(getattr(Service, op, None)) for op in OPS)

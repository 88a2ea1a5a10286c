"""The Blender-free half of the extension: camera conversions, the worker protocol, job parsing.

`neulf_blender` uses relative imports (`..neulf_core`), as an extension must, so it is
imported here as a subpackage of the repository root under a temporary package name.
No bpy is imported.
"""

from __future__ import annotations

import importlib
import io
import json
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def ext(tmp_path_factory):
    parent = tmp_path_factory.mktemp("pkg")
    (parent / "neulf_ext").symlink_to(REPO, target_is_directory=True)
    sys.path.insert(0, str(parent))
    try:
        convert = importlib.import_module("neulf_ext.neulf_blender.convert")
        jobs = importlib.import_module("neulf_ext.neulf_blender.jobs")
        assert "bpy" not in sys.modules or sys.modules.get("bpy") is not None
        yield type("Ext", (), {"convert": convert, "jobs": jobs})
    finally:
        sys.path.remove(str(parent))


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
    # Shift moves the principal point by shift x the larger dimension; +y shift moves it up (smaller cy).
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


def test_image_rows_and_colour(ext):
    rgb = np.zeros((2, 3, 3), np.float32)
    rgb[0] = 1.0  # top row white
    flat = ext.convert.image_rows_for_blender(rgb)
    assert flat.dtype == np.float32 and flat.shape == (2 * 3 * 4,)
    rows = flat.reshape(2, 3, 4)
    assert (rows[1, :, :3] == 1).all() and (rows[0, :, :3] == 0).all() and (rows[..., 3] == 1).all()
    assert ext.convert.srgb_to_linear(np.array([0.0, 0.5, 1.0])) == pytest.approx([0.0, 0.21404, 1.0], abs=1e-4)


def test_single_pixel_K_is_that_pixels_ray():
    torch = pytest.importorskip("torch")
    from neulf_core.rays import pinhole_rays
    from neulf_core.worker import single_pixel_K

    K = np.array([[58.0, 0, 33.3], [0, 61.0, 22.6], [0, 0, 1]])
    R, t = np.eye(3), np.zeros(3)
    _, all_dirs = pinhole_rays(K, R, t, 64, 48, dtype=torch.float64)
    _, one = pinhole_rays(single_pixel_K(K, 40.5, 20.5), R, t, 1, 1, dtype=torch.float64)
    assert torch.allclose(one[0], all_dirs.reshape(48, 64, 3)[20, 40])


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
    finally:
        client.close()
    assert not client.alive


def test_worker_that_cannot_start_explains_itself(ext, tmp_path):
    client = ext.jobs.WorkerClient(str(tmp_path / "no_python"), tmp_path / "scratch", ext.jobs.core_environment())
    with pytest.raises(Exception, match="cannot start .*NeuLF preferences"):
        client.call("info", timeout=60)


def test_train_job_parses_events(ext):
    job = ext.jobs.TrainJob.__new__(ext.jobs.TrainJob)
    job.state = {"status": "running", "fraction": 0.0, "message": "", "error": None, "started": 0.0, "step": 0,
                 "elapsed": 0.0, "val_psnr": None, "loss": None, "device": "", "warnings": []}
    job._cancelled = False
    for event in [{"event": "start", "train_views": 7, "device": "cpu (2 threads)", "held_out": []},
                  {"event": "step", "step": 10, "elapsed": 2.0, "loss": 0.01, "fraction": 0.25},
                  {"event": "validate", "step": 20, "elapsed": 4.0, "loss": 0.01, "fraction": 0.5, "val_psnr": 21.5},
                  {"event": "warning", "message": "careful"}]:
        job.on_stdout(json.dumps(event))
    job.on_stdout("not json")
    assert job.state["step"] == 20 and job.state["fraction"] == 0.5 and job.state["val_psnr"] == 21.5
    assert job.state["device"].startswith("cpu") and job.state["warnings"] == ["careful"]


def test_explain_failure(ext):
    assert ext.jobs.explain_failure(["x", "error: the scene is bad."]) == "the scene is bad."
    assert "no 'torch'" in ext.jobs.explain_failure(["ModuleNotFoundError: No module named 'torch'"])
    assert ext.jobs.explain_failure([]) == "the process ended without a message."

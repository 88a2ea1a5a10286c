"""The viewport preview's maths and its renderer (neulf_blender/viewport.py), without Blender.

The Blender side -- the projection of a real viewport camera, the worker route, the engine's
methods -- is checked in the Blender story (tests/blender_story.py, step viewport_preview);
drawing itself needs a GPU context, which headless Blender does not have."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import pytest

@pytest.fixture(scope="module")
def viewport(extension_module):
    return extension_module("viewport")


def blender_projection(K, width, height, near=0.1, far=100.0) -> np.ndarray:
    """The OpenGL projection Blender builds for a pinhole (the inverse of BLENDER_NOTES' formulas)."""
    fx, fy, cx, cy = K[0][0], K[1][1], K[0][2], K[1][2]
    return np.array([[2 * fx / width, 0, 1 - 2 * cx / width, 0],
                     [0, 2 * fy / height, 2 * cy / height - 1, 0],
                     [0, 0, -(far + near) / (far - near), -2 * far * near / (far - near)],
                     [0, 0, -1, 0]])


def view_matrix_of(R, t) -> np.ndarray:
    """World-to-view with Blender's camera axes (y up, looking down -z) for a COLMAP pose."""
    world_to_camera = np.eye(4)
    world_to_camera[:3, :3], world_to_camera[:3, 3] = R, t
    return np.diag([1.0, -1.0, -1.0, 1.0]) @ world_to_camera


def rotation(yaw, pitch):
    cy, sy, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
    return np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]]) @ np.array([[1, 0, 0], [0, cp, -sp], [0, sp, cp]])


def test_view_request_recovers_the_pinhole_and_pose(viewport):
    K = [[412.0, 0, 150.3], [0, 398.5, 101.7], [0, 0, 1]]
    R, t = rotation(0.3, -0.2), np.array([0.2, -0.1, 1.5])
    root = np.diag([2.0, 2.0, 2.0, 1.0])
    root[:3, 3] = (1.0, -2.0, 0.5)
    world_R, world_t = R, t  # the model frame's pose; in Blender's world it goes through the root
    camera_to_model = np.linalg.inv(view_matrix_of(world_R, world_t))
    view = np.linalg.inv(root @ camera_to_model)
    request = viewport.view_request(view, blender_projection(K, 300, 200), 300, 200, root)
    assert np.allclose(request["K"], K, atol=1e-9)
    assert np.allclose(request["R"], R, atol=1e-12) and np.allclose(request["t"], t, atol=1e-12)
    assert request["width"] == 300 and request["height"] == 200 and request["scale"] == pytest.approx(2.0)


def test_view_request_refuses_orthographic_and_empty_views(viewport):
    from neulf_core.errors import NeulfError as CoreError

    ortho = np.diag([0.5, 0.5, -0.02, 1.0])
    with pytest.raises(Exception, match=r"orthographic view .* \(Numpad 5\)") as raised:
        viewport.view_request(np.eye(4), ortho, 300, 200, np.eye(4))
    assert type(raised.value).__name__ == CoreError.__name__ and "\n" not in str(raised.value)
    with pytest.raises(Exception, match="no size"):
        viewport.view_request(np.eye(4), blender_projection([[100, 0, 50], [0, 100, 50], [0, 0, 1]], 100, 100), 0, 100,
                              np.eye(4))


def test_scaled_request_keeps_every_point_where_it_was(viewport):
    K = np.array([[412.0, 0, 150.3], [0, 398.5, 101.7], [0, 0, 1]])
    request = {"K": K.tolist(), "width": 300, "height": 200, "R": np.eye(3).tolist(), "t": [0, 0, 0]}
    small = viewport.scaled_request(request, 0.25)
    assert (small["width"], small["height"]) == (75, 50)
    point = np.array([0.3, -0.2, 2.0])
    full_xy = (K @ point)[:2] / point[2]
    small_xy = (np.asarray(small["K"]) @ point)[:2] / point[2]
    assert np.allclose(small_xy, full_xy * [75 / 300, 50 / 200])  # the image's edges stay the image's edges
    assert viewport.scaled_request(request, 1.0) == request
    renderer = viewport.PreviewRenderer(None)
    assert renderer.passes(200, 150) == [1.0] and renderer.passes(300, 200) == [viewport.coarse_factor(300, 200), 1.0]
    coarse, four_times, full = renderer.passes(1920, 1080)
    assert full == 1.0 and four_times == pytest.approx(2 * coarse)
    assert viewport.coarse_factor(200, 150) == 1.0 and viewport.coarse_factor(1920, 1080) ** 2 * 1920 * 1080 == \
        pytest.approx(viewport.PREVIEW_PIXELS)


@pytest.fixture(scope="module")
def tiny_model(tiny_scene, tmp_path_factory):
    pytest.importorskip("torch")
    from neulf_core.train import TrainConfig, train

    folder = tmp_path_factory.mktemp("viewport_model") / "model"
    train(tiny_scene, folder, TrainConfig(steps=30, validate_seconds=1e9, checkpoint_seconds=1e9))
    return folder


def tiny_request(tiny_scene, model: Path, shift=0.0, scale=8) -> dict:
    from neulf_core.scene import load_scene

    view = load_scene(tiny_scene).views[4]
    K = np.diag([scale, scale, 1.0]) @ view.camera.calibration_matrix()  # (`scale` times its pixels)
    width, height = view.size
    return {"model_dir": str(model), "K": K.tolist(), "width": width * scale, "height": height * scale,
            "R": view.R.tolist(), "t": (view.t + [shift, 0.0, 0.0]).tolist()}


def in_process_render(calls):
    from neulf_core.worker import Service

    service = Service()

    def render(request, should_stop):
        calls.append((request["width"], request["height"]))

        def report(_fraction):
            if should_stop():
                raise InterruptedError("a newer view")
        return service.render(depth=False, pixel_samples=1, chunk=4096, on_progress=report, **request)["rgb"]
    return render


def test_preview_renders_coarse_then_full_size_once(viewport, tiny_scene, tiny_model):
    from neulf_core.worker import Service

    calls, shown = [], []
    renderer = viewport.PreviewRenderer(in_process_render(calls), on_image=lambda: shown.append(renderer.image()))
    request = tiny_request(tiny_scene, tiny_model)
    key = viewport.view_key(request, str(tiny_model), 0.0)
    assert viewport.status_line(renderer, key) == "NeuLF: rendering the view"
    renderer.want(key, request)
    assert renderer.wait(120) and renderer.error is None
    width, height = request["width"], request["height"]
    assert calls[-1] == (width, height) and len(calls) == 2
    assert calls[0][0] * calls[0][1] <= viewport.PREVIEW_PIXELS * 1.02 and calls[0][0] < width
    assert [image.full_size for image in shown] == [False, True]
    final = renderer.image()
    direct = Service().render(depth=False, pixel_samples=1, **request)["rgb"]
    assert final.key == key and np.abs(final.rgb - direct).max() < 1e-6  # the view as render gives it
    assert viewport.status_line(renderer, key).startswith(f"NeuLF: {width} x {height} in ")

    for _ in range(3):  # the same view again (a redraw): nothing renders
        renderer.want(key, dict(request))
    time.sleep(0.2)
    assert len(calls) == 2 and not renderer.busy
    renderer.close()


def test_a_newer_view_replaces_the_one_rendering(viewport, tiny_scene, tiny_model):
    calls = []
    renderer = viewport.PreviewRenderer(in_process_render(calls))
    first = tiny_request(tiny_scene, tiny_model, scale=20)  # big enough to be rendering when the view moves
    second = tiny_request(tiny_scene, tiny_model, shift=0.01, scale=20)
    renderer.want(viewport.view_key(first, "m", 0.0), first)
    while not calls:
        time.sleep(0.001)
    renderer.want(viewport.view_key(second, "m", 0.0), second)
    assert renderer.wait(180)
    final = renderer.image()
    assert final.key == viewport.view_key(second, "m", 0.0) and final.full_size
    passes = [(round(second["width"] * f), round(second["height"] * f)) for f in renderer.passes(960, 720)]
    assert len(passes) == 3 and calls[-3:] == passes  # the second view: coarse, four times that, full size
    assert len(calls) <= 5  # (the first view: its coarse pass, and at most the start of the next, stopped)
    renderer.close()


def test_a_model_that_cannot_render_is_said_in_one_line(viewport, tiny_scene, tiny_model, tmp_path):
    renderer = viewport.PreviewRenderer(in_process_render([]))
    request = {**tiny_request(tiny_scene, tiny_model, scale=1), "model_dir": str(tmp_path / "nothing here")}
    key = viewport.view_key(request, request["model_dir"], 0.0)
    renderer.want(key, request)
    assert renderer.wait(60) and not renderer.busy
    line = viewport.status_line(renderer, key)
    assert line.startswith("NeuLF: ") and "\n" not in line and "Traceback" not in line and len(line) > 20, line
    assert renderer.image() is None
    renderer.close()


def test_the_thread_ends_when_idle_and_starts_again(viewport, tiny_scene, tiny_model, monkeypatch):
    monkeypatch.setattr(viewport, "IDLE_SECONDS", 0.2)
    calls = []
    renderer = viewport.PreviewRenderer(in_process_render(calls))
    request = tiny_request(tiny_scene, tiny_model, scale=1)
    renderer.want(viewport.view_key(request, "m", 0.0), request)
    assert renderer.wait(60)
    deadline = time.monotonic() + 5
    while renderer._thread is not None and time.monotonic() < deadline:
        time.sleep(0.05)
    assert renderer._thread is None
    moved = tiny_request(tiny_scene, tiny_model, shift=0.02, scale=1)
    renderer.want(viewport.view_key(moved, "m", 0.0), moved)
    assert renderer.wait(60) and renderer.image().key == viewport.view_key(moved, "m", 0.0)
    renderer.close()


def test_a_view_that_keeps_moving_still_gets_images(viewport, tiny_scene, tiny_model):
    """An orbit changes the view faster than a pass ends: the coarse passes still run to their
    end and are shown (interrupting them, as the full-size pass is, would show nothing at all)."""
    calls, arrived = [], []
    renderer = viewport.PreviewRenderer(in_process_render(calls), on_image=lambda: arrived.append(renderer.image()))
    started, index = time.monotonic(), 0
    while time.monotonic() - started < 1.5:
        request = tiny_request(tiny_scene, tiny_model, shift=0.001 * index, scale=20)
        renderer.want(viewport.view_key(request, "m", 0.0), request)
        index += 1
        time.sleep(0.005)
    moving = list(arrived)
    assert index > 3 * len(moving) and len(moving) >= 2, (index, len(moving))  # each image a view some asks old
    assert not any(image.full_size for image in moving)
    assert renderer.wait(120) and renderer.image().full_size  # once it stops: the last view at full size
    assert renderer.image().key == viewport.view_key(request, "m", 0.0)
    renderer.close()


def test_bands_of_rows_are_the_full_image(viewport, tiny_scene, tiny_model):
    """The worker route renders a view in bands it can stop between: together they are the
    image rendered at once (the same rays; chunks of another size round alike to 1e-6)."""
    from neulf_core.worker import Service

    service = Service()
    request = tiny_request(tiny_scene, tiny_model, scale=5)  # 240 x 180
    bands = list(viewport.row_bands(request, 240 * 50 + 17))  # 50 rows a band, the last 30
    assert [top for top, _ in bands] == [0, 50, 100, 150] and bands[-1][1]["height"] == 30
    stitched = np.concatenate([service.render(depth=False, pixel_samples=1, **band)["rgb"] for _, band in bands])
    whole = service.render(depth=False, pixel_samples=1, **request)["rgb"]
    assert stitched.shape == whole.shape and np.abs(stitched - whole).max() < 1e-6


def test_the_worker_route_stops_between_bands(viewport, monkeypatch):
    """A worker's call cannot be interrupted: the route asks should_stop between its bands."""
    asked = []

    class WorkerCore:  # the core's worker route as render_function sees it: calls that run to their end
        in_process = False

        def call(self, op, **args):
            asked.append(args["height"])
            return {"rgb": np.zeros((args["height"], args["width"], 3), np.float32)}

    monkeypatch.setattr(viewport, "WORKER_BAND_PIXELS", 100 * 10)
    render = viewport.render_function(WorkerCore())
    request = {"K": np.eye(3).tolist(), "width": 100, "height": 45, "R": np.eye(3).tolist(), "t": [0, 0, 0]}
    assert render(request, lambda: False).shape == (45, 100, 3) and asked == [10, 10, 10, 10, 5]
    asked.clear()
    with pytest.raises(InterruptedError):
        render(request, lambda: len(asked) >= 2)
    assert asked == [10, 10]


def test_a_depth_of_field_renders_in_the_preview_with_few_lens_samples(viewport, extension_module, tiny_scene,
                                                                      tiny_model):
    """Looking through the camera, the engine adds its depth of field to the request: it is part
    of the preview's key, and the core renders it with at most FULL_LENS_SAMPLES samples at full
    size (the coarse pass: COARSE_LENS_SAMPLES)."""
    from neulf_core.worker import Service

    core = extension_module("core").Core(sys.executable, mode="AUTO")  # (the engine's in Blender's own Python)
    assert core.in_process
    pinhole = tiny_request(tiny_scene, tiny_model, scale=4)
    lens = {**pinhole, "focus_distance": 1.5, "aperture": 0.05}  # focused well before the plane at 3: a blur
    assert viewport.view_key(lens, "m", 0.0) != viewport.view_key(pinhole, "m", 0.0)
    asked, through_core = [], viewport.render_function(core)
    renderer = viewport.PreviewRenderer(lambda request, stop: asked.append(request["max_lens_samples"])
                                        or through_core(request, stop), preview_pixels=5000)
    renderer.want(viewport.view_key(lens, "m", 0.0), lens)
    assert renderer.wait(120) and renderer.error is None, renderer.error
    shown = renderer.image().rgb
    service = Service()
    few = service.render(depth=False, pixel_samples=1, max_lens_samples=viewport.FULL_LENS_SAMPLES, **lens)["rgb"]
    sharp = service.render(depth=False, pixel_samples=1, **pinhole)["rgb"]
    assert asked == [viewport.COARSE_LENS_SAMPLES] * 2 + [viewport.FULL_LENS_SAMPLES]  # (coarse, 4 x, full)
    assert np.abs(shown - few).max() < 1e-5
    assert np.abs(shown - sharp).mean() > 5e-3  # (the blur is there)
    many = service.render(depth=False, pixel_samples=1, **lens)["rgb"]  # F12's: up to refocus.MAX_SAMPLES
    assert 0 < np.abs(few - many).mean() < 0.3 * np.abs(few - sharp).mean()  # fewer samples, the same blur
    renderer.close()

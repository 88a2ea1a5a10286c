"""Captures whose photos differ: other sizes, orientations, focal lengths, a wide or fisheye
photo among them.  What a camera path takes as its camera, and what render and eval say about a
view that sees past the captured region (a reader's audit found these, 2026-12-01)."""

from __future__ import annotations

import json
from dataclasses import replace
from types import SimpleNamespace

import pycolmap
import pytest

from neulf_core import evaluate
from neulf_core.cli import main
from neulf_core.render import LightField
from neulf_core.scene import load_scene
from neulf_core.train import path_camera_view


def _photo(name: str, width: int, height: int, focal: float):
    return SimpleNamespace(name=name, size=(width, height), camera=SimpleNamespace(focal_length_x=focal))


def test_a_camera_path_takes_the_most_common_photo_size_and_the_median_focal_length():
    """The first training photo's camera had made a 48x64 portrait video of a landscape capture
    with one portrait photo first, and a fisheye's focal length a 94-degree pinhole."""
    views = [_photo("a_portrait", 48, 64, 60.0), *(_photo(f"b{i}", 64, 48, 58.0 + i) for i in range(5)),
             _photo("c_wide", 64, 48, 30.0)]
    chosen = path_camera_view(views)
    assert chosen.size == (64, 48) and chosen.camera.focal_length_x == 59.0  # median of 30, 58, 59, 60, 61, 62
    assert path_camera_view([_photo("only", 32, 24, 20.0)]).name == "only"


@pytest.fixture(scope="module")
def model(tiny_scene, tmp_path_factory):
    out = tmp_path_factory.mktemp("mixed") / "model"
    assert main(["train", str(tiny_scene), "--out", str(out), "--steps", "20", "--batch-size", "512",
                 "--validate-seconds", "1e9", "--members", "1"]) == 0
    return out


def _widened(view, factor: float = 0.3):
    """The view with a lens `factor` times its focal length: it sees far past what the capture saw."""
    c = view.camera
    return replace(view, camera=pycolmap.Camera(model="PINHOLE", width=c.width, height=c.height,
                                                params=[c.params[0] * factor, c.params[0] * factor, c.params[2], c.params[3]]))


def test_a_registered_view_that_sees_past_the_capture_is_said(model, tiny_scene):
    """render_view counted no rays outside the captured region, so render --views and eval said
    nothing of a wide view whose rays mostly leave it (78 % in the audit's, scored 11.4 dB)."""
    light_field = LightField.load(model, "cpu")
    view = load_scene(tiny_scene).views[0]
    assert not any("leave the region" in w for w in light_field.render_view(view, 1.0).warnings)
    wide = light_field.render_view(_widened(view), 1.0).warnings
    assert any("leave the region the cameras captured" in w for w in wide), wide


def test_eval_reports_each_view_s_warnings(model, tiny_scene, tmp_path, monkeypatch):
    scene = load_scene(tiny_scene)
    moved = replace(scene, views=[_widened(v) if v.name == "view_00.png" else v for v in scene.views])
    monkeypatch.setattr(evaluate, "load_scene", lambda *args, **kwargs: moved)
    report = evaluate.evaluate_model(model, tiny_scene, out_dir=tmp_path, pixel_samples=1, save_images=False)
    assert any("have another camera" in w for w in report["warnings"])  # (the widened lens is not the trained one)
    views = [w for w in report["warnings"] if w.startswith("view_")]
    assert [w.split(":")[0] for w in views] == ["view_00.png"] and "leave the region" in views[0], report["warnings"]
    assert json.loads((tmp_path / "eval.json").read_text())["warnings"] == report["warnings"]


def test_a_video_takes_a_fractional_frame_rate(model, tmp_path):
    import av

    assert main(["video", str(model), "--out", str(tmp_path / "ntsc.mp4"), "--frames", "3", "--fps", "29.97"]) == 0
    with av.open(str(tmp_path / "ntsc.mp4")) as container:
        assert float(container.streams.video[0].average_rate) == pytest.approx(29.97, abs=1e-3)


def test_a_photo_that_sees_far_wider_than_the_others_is_said(tiny_scene, tmp_path):
    """One wide or fisheye photo stretches the slab over what it sees: training names it, once,
    as a note (on a real capture such a photo helped the held-out views, benchmarks/wide_photo.py;
    a warning had told the user to hold it out)."""
    from neulf_core.scene import split_views
    from neulf_core.slab import fit_slab, wide_views
    from neulf_core.train import TrainConfig, train

    scene = load_scene(tiny_scene)
    train_views, _ = split_views(scene, 8)
    assert wide_views(fit_slab(scene, train_views), train_views, 1.0) == []
    wide_scene = replace(scene, views=[_widened(v) if v.name == "view_03.png" else v for v in scene.views])
    train_views, _ = split_views(wide_scene, 8)
    found = wide_views(fit_slab(wide_scene, train_views), train_views, 1.0)
    assert [name for name, _ in found] == ["view_03.png"] and found[0][1] > 2.5, found
    said = []
    train(wide_scene, tmp_path / "model", TrainConfig(steps=4, batch_size=256, validate_seconds=1e9, members=2),
          progress=said.append)
    wide = [event for event in said if event.get("event") == "stage" and event.get("views") == ["view_03.png"]]
    assert len(wide) == 1 and "view_03.png" in wide[0]["message"] and "--exclude" in wide[0]["message"], said
    assert not [event for event in said if event.get("event") == "warning" and "as wide" in event["message"]]

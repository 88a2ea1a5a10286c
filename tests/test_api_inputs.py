"""Library calls given inputs a user can get wrong (or a little unusual) either take them or
raise NeulfError with one line saying what to do, never a raw numpy, torch or PyAV error.

Built from numpy arrays and stand-ins: no training, no scene on disk."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from neulf_core import evaluate
from neulf_core.device import pick_device
from neulf_core.errors import NeulfError
from neulf_core.video import write_video

av = pytest.importorskip("av")


def _frame(height=16, width=24, value=0.5):
    return np.full((height, width, 3), value, np.float32)


def _read_back(path: Path):
    """(frame count, (height, width), frame rate) of a written video."""
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        frames = [frame.to_ndarray(format="rgb24") for frame in container.decode(stream)]
        return len(frames), frames[0].shape[:2], stream.average_rate


# ----------------------------------------------------------------------------- write_video


@pytest.mark.parametrize("fps, rate", [(29.97, 29.97), (30000 / 1001, 30000 / 1001), (30, 30), (np.float64(24.0), 24)])
def test_video_takes_a_fractional_frame_rate(tmp_path, fps, rate):
    path = tmp_path / "v.mp4"
    assert write_video([_frame(), _frame()], path, fps=fps) == 2
    count, _, written_rate = _read_back(path)
    assert count == 2 and float(written_rate) == pytest.approx(rate, rel=1e-6)


@pytest.mark.parametrize("fps", [0, -1, float("nan"), float("inf"), 1e-9, "fast", None])
def test_video_refuses_a_frame_rate_that_is_not_positive(tmp_path, fps):
    with pytest.raises(NeulfError, match="frames per second"):
        write_video([_frame()], tmp_path / "v.mp4", fps=fps)
    assert not (tmp_path / "v.mp4").exists()


@pytest.mark.parametrize("second", [(32, 40), (8, 12), (16, 25)])
def test_video_refuses_frames_of_another_size(tmp_path, second):
    with pytest.raises(NeulfError, match=r"frame 1 is \d+x\d+ but the first frame is 24x16"):
        write_video([_frame(), _frame(*second)], tmp_path / "v.mp4")


def test_video_of_another_size_late_leaves_no_cut_short_file(tmp_path):
    """x264 holds frames back before its first packet: enough frames that some were written."""
    path = tmp_path / "v.mp4"
    frames = [_frame(value=i / 80) for i in range(80)] + [_frame(8, 8)]
    with pytest.raises(NeulfError, match="frame 80 is 8x8"):
        write_video(frames, path)
    assert not path.exists()


def test_video_takes_grey_and_rgba_frames(tmp_path):
    grey = np.linspace(0, 1, 16 * 24, dtype=np.float32).reshape(16, 24)
    rgba = np.concatenate([_frame(value=0.25), np.zeros((16, 24, 1), np.float32)], axis=2)  # alpha 0: dropped
    grey_single_channel = (grey[..., None] * 255).astype(np.uint8)
    path = tmp_path / "v.mp4"
    assert write_video([grey, rgba, grey_single_channel], path) == 3
    count, size, _ = _read_back(path)
    assert (count, size) == (3, (16, 24))


def test_video_rgba_keeps_its_colour(tmp_path):
    path = tmp_path / "v.mp4"
    rgba = np.zeros((16, 24, 4), np.uint8)
    rgba[..., 0], rgba[..., 3] = 200, 0
    write_video([rgba], path)
    with av.open(str(path)) as container:
        decoded = next(container.decode(video=0)).to_ndarray(format="rgb24").astype(int)
    assert abs(decoded[..., 0].mean() - 200) < 8 and decoded[..., 2].mean() < 20


@pytest.mark.parametrize("frame", [np.zeros((16, 24, 2)), np.zeros((16,)), np.zeros((2, 16, 24, 3)),
                                   np.zeros((0, 24, 3)), np.full((16, 24, 3), "x")])
def test_video_refuses_frames_that_are_not_images(tmp_path, frame):
    with pytest.raises(NeulfError, match="video frame 0 .*give \\(H, W, 3\\)"):
        write_video([frame], tmp_path / "v.mp4")


@pytest.mark.parametrize("name", ["v.png", "v.gif", "v", "v.MP4.txt"])
def test_video_refuses_a_file_name_that_is_not_a_video(tmp_path, name):
    with pytest.raises(NeulfError, match=r"\.mp4"):
        write_video([_frame()], tmp_path / name)
    assert not (tmp_path / name).exists()


def test_video_refuses_a_folder(tmp_path):
    (tmp_path / "v.mp4").mkdir()
    with pytest.raises(NeulfError, match="give a file name"):
        write_video([_frame()], tmp_path / "v.mp4")


@pytest.mark.parametrize("name", ["v.mov", "v.MKV", "v.m4v"])
def test_video_writes_the_other_suffixes(tmp_path, name):
    assert write_video([_frame(15, 21)], tmp_path / name) == 1  # (odd sizes padded to even)
    assert _read_back(tmp_path / name)[0] == 1


def test_video_with_a_nan_frame_writes_it_black(tmp_path):
    path = tmp_path / "v.mp4"
    write_video([np.full((16, 24, 3), np.nan)], path)
    with av.open(str(path)) as container:
        assert next(container.decode(video=0)).to_ndarray(format="rgb24").max() < 20


def test_video_float_frames_keep_their_brightness(tmp_path):
    """Renders are float [0, 1]: they are scaled to 8 bits (taken as 0-255 the video was black)."""
    path = tmp_path / "v.mp4"
    write_video([_frame(value=0.25), _frame(value=0.75)], path)
    with av.open(str(path)) as container:
        means = [frame.to_ndarray(format="rgb24").mean() for frame in container.decode(video=0)]
    assert means == pytest.approx([0.25 * 255, 0.75 * 255], abs=4)


def test_depth_colours_are_warm_near_and_cool_far():
    """The depth preview (render --depth's _depth.png): near warm, far cool, no depth black."""
    from neulf_core.video import depth_to_colour

    depth = np.array([[1.0, 2.0, 4.0, 8.0, np.nan]])
    colour = depth_to_colour(depth).astype(int)[0]
    red_minus_blue = colour[:4, 0] - colour[:4, 2]
    assert red_minus_blue[0] > 0 > red_minus_blue[3], colour
    assert colour[4].tolist() == [0, 0, 0]


# ----------------------------------------------------------------------------- evaluate_model


class _Stop(Exception):
    """Raised by the stand-in scene at the first view looked up: the names are all the test needs."""


def _names_evaluated(monkeypatch, views, held_out=("view_00_00",)):
    """The view names evaluate_model looks up for `views`, with a stand-in model and scene."""
    looked_up = []

    def view(name):
        looked_up.append(name)
        raise _Stop

    scene = SimpleNamespace(views=[SimpleNamespace(name=f"view_0{i}_00.png") for i in range(3)], view=view)
    light_field = SimpleNamespace(meta={"scene": {"held_out": list(held_out), "mean_colour": [0.5, 0.5, 0.5]}},
                                  trained_scale=1.0, device="cpu", check_scene=lambda scene: None)
    monkeypatch.setattr(evaluate.LightField, "load", staticmethod(lambda *args, **kwargs: light_field))
    monkeypatch.setattr(evaluate, "load_scene", lambda *args, **kwargs: scene)
    monkeypatch.setattr(evaluate, "load_lpips", lambda: None)
    with pytest.raises(_Stop):
        evaluate.evaluate_model("model", "scene", views=views, save_images=False)
    return looked_up


@pytest.mark.parametrize("views", ["view_01_01", ["view_01_01"], ("view_01_01",), Path("view_01_01")])
def test_evaluate_takes_one_view_name_as_a_string(monkeypatch, views):
    assert _names_evaluated(monkeypatch, views) == ["view_01_01"]


@pytest.mark.parametrize("views", [None, [], "", "held-out", ["held-out"]])
def test_evaluate_defaults_to_the_held_out_views(monkeypatch, views):
    assert _names_evaluated(monkeypatch, views, held_out=["view_02_00"]) == ["view_02_00"]


@pytest.mark.parametrize("views", ["all", ["all"]])
def test_evaluate_all_means_every_view(monkeypatch, views):
    assert _names_evaluated(monkeypatch, views) == ["view_00_00.png"]  # (the first of the three)


def test_evaluate_without_held_out_views_says_to_name_some(monkeypatch):
    with pytest.raises(NeulfError, match="name views"):
        _names_evaluated(monkeypatch, "held-out", held_out=[])


def test_evaluate_refuses_views_that_are_not_names(monkeypatch):
    with pytest.raises(NeulfError, match="give a view name"):
        _names_evaluated(monkeypatch, 3)


# ----------------------------------------------------------------------------- pick_device


@pytest.mark.parametrize("name", ["xpu", "meta", "hpu", "ipu", torch.device("meta")])
def test_device_other_than_cpu_cuda_mps_is_refused(name):
    with pytest.raises(NeulfError, match=r"not supported; use cpu, cuda, cuda:N or mps"):
        pick_device(name)


@pytest.mark.parametrize("name", ["tpu", "gpu", "CPU", "cuda:abc", ["cpu"]])
def test_device_unknown_name_is_refused(name):
    with pytest.raises(NeulfError, match=r"unknown device .*use cpu, cuda, cuda:N or mps"):
        pick_device(name)


@pytest.mark.parametrize("name", ["cpu", "cpu:0", torch.device("cpu")])
def test_device_cpu_is_taken(name):
    assert pick_device(name).type == "cpu"


def test_device_absent_cuda_and_mps_say_use_cpu(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(torch.backends.mps, "is_available", lambda: False)
    for name in ("cuda", "cuda:1", torch.device("cuda"), "mps"):
        with pytest.raises(NeulfError, match="--device cpu"):
            pick_device(name)


def test_device_cuda_index_past_the_gpus_is_refused(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    assert pick_device("cuda:0") == torch.device("cuda:0")
    with pytest.raises(NeulfError, match="1 CUDA GPU"):
        pick_device("cuda:1")


@pytest.mark.parametrize("name", [None, ""])
def test_device_not_named_is_picked(name):
    assert pick_device(name).type in ("cpu", "cuda", "mps")


def test_the_worker_s_check_needs_every_module_training_imports(monkeypatch):
    """Blender's Check ran Service.info, which imported only torch and pycolmap: a Python without
    Pillow passed, and training then failed.  It now fails the check, naming the module."""
    import sys

    from neulf_core.worker import Service

    monkeypatch.setitem(sys.modules, "PIL", None)  # (an import of it raises ImportError)
    with pytest.raises(ImportError, match="PIL"):
        Service().info()


def test_the_worker_reloads_a_model_whose_second_member_trained_on(tmp_path):
    """The worker's cached model was keyed on the first member's checkpoint alone: a second
    member trained on rendered stale in Blender until a restart (39.8 dB from a fresh load)."""
    import os

    from neulf_core.cli import main
    from neulf_core.worker import Service, model_stamp

    from conftest import make_tiny_scene

    scene = make_tiny_scene(tmp_path / "scene")
    model = tmp_path / "model"
    assert main(["train", str(scene), "--out", str(model), "--steps", "4", "--batch-size", "256",
                 "--validate-seconds", "1e9", "--members", "2"]) == 0
    service = Service()
    first = service.light_field(str(model))
    assert service.light_field(str(model)) is first  # (cached while nothing changed)
    member = model / "members" / "2" / "checkpoint.pt"
    stamp = model_stamp(model)
    os.utime(member, ns=(member.stat().st_atime_ns, member.stat().st_mtime_ns + 10**9))
    assert model_stamp(model) != stamp
    assert service.light_field(str(model)) is not first


@pytest.mark.parametrize("options, named", [
    (dict(back_surface=True), "--back-surface (TrainConfig.back_surface)"),
    (dict(coarse_to_fine=False), "--coarse-to-fine (TrainConfig.coarse_to_fine)"),
    (dict(field_overrides={"geometry_layers": 8}), "--depth-layers (TrainConfig.field_overrides['geometry_layers'])"),
], ids=["back surface", "coarse to fine", "depth layers"])
def test_options_of_the_fast_field_are_refused_for_another_preset(options, named, tmp_path):
    """The Python API had dropped them without a word for the MLP presets (only the CLI
    refused), and depth layers failed naming an option the user never gave."""
    from neulf_core.errors import NeulfError
    from neulf_core.train import TrainConfig, check_config

    for preset in ("authors", "paper", "planes"):
        with pytest.raises(NeulfError) as refused:
            check_config(TrainConfig(preset=preset, steps=10, **options))
        assert named in str(refused.value) and "depth_detail_shift" not in str(refused.value)
    check_config(TrainConfig(preset="fast", steps=10, **options))  # (the fast field's own)


def test_the_worker_s_depth_pick_is_the_light_field_s(tmp_path):
    """Blender's depth pick (focus) goes through the worker: its depth is LightField.depth_at's,
    and where there is none the one message says so, with what to do in Blender."""
    from neulf_core.cli import main
    from neulf_core.errors import NeulfError
    from neulf_core.render import LightField
    from neulf_core.scene import load_scene
    from neulf_core.worker import Service

    from conftest import make_tiny_scene

    scene = make_tiny_scene(tmp_path / "scene")
    model = tmp_path / "model"
    assert main(["train", str(scene), "--out", str(model), "--steps", "4", "--batch-size", "256",
                 "--validate-seconds", "1e9"]) == 0
    view = load_scene(scene).views[1]
    K = view.camera.calibration_matrix()
    picked = Service().depth_at(str(model), K, view.R, view.t, 20.5, 15.5)
    assert picked["depth"] == LightField.load(model, "cpu").depth_at(K, view.R, view.t, 20.5, 15.5)
    away = np.diag([-1.0, 1.0, -1.0]) @ view.R  # (turned to look back over the capture)
    with pytest.raises(NeulfError, match=r"no depth at pixel \(20.5, 15.5\).*click on the captured scene itself"):
        Service().depth_at(str(model), K, away, view.t, 20.5, 15.5)

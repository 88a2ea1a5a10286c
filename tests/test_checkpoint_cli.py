"""Metrics, checkpoints (save, load, resume, cancel, damage) and the command line, on the
tiny synthetic scene from conftest.py (no reference data needed)."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image
skimage_metrics = pytest.importorskip("skimage.metrics", reason="scikit-image (the dev extra) is not installed")
peak_signal_noise_ratio, structural_similarity = skimage_metrics.peak_signal_noise_ratio, skimage_metrics.structural_similarity

from conftest import assert_same_weights
from neulf_core.checkpoint import CHECKPOINT_NAME, METADATA_NAME, load_checkpoint
from neulf_core.files import atomic_write_bytes
from neulf_core.cli import main
from neulf_core.errors import NeulfError
from neulf_core.metrics import psnr, ssim
from neulf_core.render import LightField
from neulf_core.scene import load_scene
from neulf_core.train import TrainConfig, train

REPO = Path(__file__).resolve().parents[1]
SMALL_PLANES = {"spatial_res": [16, 32], "channels": 4, "hidden": 16}
SMALL_MLP = {"depth": 3, "width": 24, "head_width": 16}


def small_config(steps: int, **overrides) -> TrainConfig:
    """A few-second run: tiny planes, small batches, no timed validation or checkpoints."""
    options = dict(preset="planes", steps=steps, batch_size=256, field_overrides=dict(SMALL_PLANES),
                   validate_seconds=1e9, checkpoint_seconds=1e9)
    options.update(overrides)
    return TrainConfig(**options)


# ----------------------------------------------------------------------------- metrics


def structured_pair(rng):
    y, x = np.mgrid[0:48, 0:64] / 64.0
    image = np.stack([0.5 + 0.4 * np.sin(9 * x + 3 * y), x * y, 0.5 + 0.5 * np.cos(20 * x) * np.sin(13 * y)], axis=2)
    noisy = np.clip(image + rng.normal(0, 0.05, image.shape), 0, 1)
    return image, noisy


@pytest.mark.parametrize("kind", ["random", "structured", "uint8"])
def test_metrics_match_scikit_image(kind):
    rng = np.random.default_rng({"random": 0, "structured": 1, "uint8": 2}[kind])
    if kind == "random":
        a, b = rng.uniform(size=(37, 41, 3)), rng.uniform(size=(37, 41, 3))
    else:
        a, b = structured_pair(rng)
    if kind == "uint8":
        a8, b8 = (np.round(a * 255).astype(np.uint8), np.round(b * 255).astype(np.uint8))
        ours_p, ours_s = psnr(a8, b8), ssim(a8, b8)
        a, b = a8 / 255.0, b8 / 255.0
    else:
        ours_p, ours_s = psnr(a, b), ssim(a, b)
    reference_p = peak_signal_noise_ratio(b, a, data_range=1)
    reference_s = structural_similarity(a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                                        data_range=1, channel_axis=2)
    assert ours_p == pytest.approx(reference_p, abs=1e-6)
    assert ours_s == pytest.approx(reference_s, abs=1e-6)
    assert psnr(a, a) == float("inf") and ssim(a, a) == pytest.approx(1.0, abs=1e-12)
    assert ssim(a, b) < 1.0


def test_ssim_grayscale_and_float32():
    rng = np.random.default_rng(4)
    a, b = structured_pair(rng)
    reference = structural_similarity(a[..., 0], b[..., 0], gaussian_weights=True, sigma=1.5,
                                      use_sample_covariance=False, data_range=1)
    assert ssim(a[..., 0], b[..., 0]) == pytest.approx(reference, abs=1e-6)
    assert ssim(a.astype(np.float32), b.astype(np.float32)) == pytest.approx(ssim(a, b), abs=1e-6)


# ----------------------------------------------------------------------------- training and checkpoints


@pytest.fixture(scope="module")
def trained(tiny_scene, tmp_path_factory):
    """A small model trained for 8 steps (the scene and its result)."""
    model_dir = tmp_path_factory.mktemp("trained") / "model"
    result = train(tiny_scene, model_dir, small_config(8))
    return tiny_scene, model_dir, result


def copy_model(model_dir: Path, destination: Path) -> Path:
    shutil.copytree(model_dir, destination)
    return destination


def test_train_writes_checkpoint_and_metadata(trained):
    scene_dir, model_dir, result = trained
    assert result.status == "finished" and result.step == 8
    assert (model_dir / CHECKPOINT_NAME).is_file() and (model_dir / METADATA_NAME).is_file()
    assert not [p for p in model_dir.iterdir() if p.name.endswith(".tmp")]
    meta = json.loads((model_dir / METADATA_NAME).read_text())
    assert "state_dict" not in meta and "optimizer" not in meta
    assert meta["progress"]["step"] == 8 and meta["progress"]["status"] == "finished"
    assert meta["scene"]["held_out"] == ["view_00.png", "view_08.png"]
    assert meta["scene"]["fingerprint"] == load_scene(scene_dir).fingerprint()
    assert meta["field"] == "planes" and meta["field_config"]["spatial_res"] == [16, 32]
    assert meta["rig"]["width"] == 48 and len(meta["rig"]["centres"]) == 7
    assert set(meta["slab"]) >= {"rotation", "origin", "z_uv", "z_st", "lo", "hi", "uv_corners_world"}
    assert result.history[-1]["step"] == 8 and result.val_psnr == result.history[-1]["val_psnr"]


def test_loaded_model_reproduces_the_trained_one(trained):
    """The validation PSNR the trainer measured with its in-memory field equals the PSNR of
    the reloaded model's renders of the same held-out views."""
    scene_dir, model_dir, result = trained
    light_field = LightField.load(model_dir, "cpu")
    scene = load_scene(scene_dir)
    light_field.check_scene(scene)
    squared, count = 0.0, 0
    renders = []
    for name in light_field.meta["scene"]["held_out"]:
        view = scene.view(name)
        rendering = light_field.render_view(view)
        assert rendering.valid.all() and np.isfinite(rendering.depth).all()
        target = view.load_image().astype(np.float64) / 255.0
        squared += float(((rendering.rgb.astype(np.float64) - target) ** 2).sum())
        count += target.size
        renders.append(rendering)
    assert -10 * np.log10(squared / count) == pytest.approx(result.val_psnr, abs=1e-4)

    again = LightField.load(model_dir, "cpu")
    for name, first in zip(light_field.meta["scene"]["held_out"], renders):
        second = again.render_view(scene.view(name))
        np.testing.assert_array_equal(first.rgb, second.rgb)
        np.testing.assert_array_equal(first.depth, second.depth)
        # The pinhole renderer (render) agrees with the camera-model one for a PINHOLE view.
        view = scene.view(name)
        pinhole = again.render(view.camera.calibration_matrix(), *view.size, view.R, view.t)
        np.testing.assert_allclose(pinhole.rgb, first.rgb, atol=1e-5)
        np.testing.assert_allclose(pinhole.depth, first.depth, rtol=1e-5)


def test_resume_continues_step_and_history(trained, tmp_path):
    scene_dir, model_dir, first = trained
    model = copy_model(model_dir, tmp_path / "model")
    events = []
    result = train(scene_dir, model, small_config(12), resume=True, progress=events.append)
    assert result.status == "finished" and result.step == 12
    assert result.history[: len(first.history)] == first.history
    assert result.history[-1]["step"] == 12
    steps = [e["step"] for e in events if e.get("event") in ("step", "validate")]
    assert steps == list(range(9, 13))
    meta = json.loads((model / METADATA_NAME).read_text())
    assert meta["progress"]["step"] == 12 and meta["train_config"]["steps"] == 12
    assert meta["progress"]["elapsed"] >= first.elapsed
    # Resuming a finished budget does no more steps.
    again = train(scene_dir, model, small_config(12), resume=True)
    assert again.step == 12


def weights(model_dir: Path) -> dict:
    return torch.load(Path(model_dir) / CHECKPOINT_NAME, map_location="cpu", weights_only=False)


def test_split_training_equals_straight_training_with_a_step_schedule(tiny_scene, tmp_path):
    """`authors` decays the learning rate per epoch (a function of the step alone), so N
    steps + resume to 2N must give bit-identical weights to 2N steps straight."""
    config = dict(preset="authors", field_overrides=dict(SMALL_MLP))
    train(tiny_scene, tmp_path / "straight", small_config(10, **config))
    train(tiny_scene, tmp_path / "split", small_config(5, **config))
    train(tiny_scene, tmp_path / "split", small_config(10, **config), resume=True)
    assert_same_weights(tmp_path / "straight", tmp_path / "split")


def test_the_seed_decides_the_run(tiny_scene, tmp_path):
    """The same seed trains the same weights; another seed other ones (members and the seed
    studies rely on it: runs of a seed ignored would all be one)."""
    train(tiny_scene, tmp_path / "a", small_config(3, seed=0))
    train(tiny_scene, tmp_path / "b", small_config(3, seed=0))
    train(tiny_scene, tmp_path / "c", small_config(3, seed=1))
    assert_same_weights(tmp_path / "a", tmp_path / "b")
    a, c = weights(tmp_path / "a")["state_dict"], weights(tmp_path / "c")["state_dict"]
    assert any(not torch.equal(a[key], c[key]) for key in a)


def test_a_step_with_a_non_finite_loss_is_skipped(tiny_scene, tmp_path, monkeypatch):
    """A NaN objective (a diverging step) is not stepped on: the weights stay finite, three in a
    row halve the learning rate, and the skips are reported."""
    import neulf_core.train as train_module

    real, calls = train_module._objective, []

    def nan_at_steps_2_to_4(*args, **kwargs):
        loss, objective = real(*args, **kwargs)
        calls.append(1)
        return (loss, objective * float("nan")) if 2 <= len(calls) <= 4 else (loss, objective)

    monkeypatch.setattr(train_module, "_objective", nan_at_steps_2_to_4)
    events = []
    result = train(tiny_scene, tmp_path / "m", small_config(8), progress=events.append)
    assert result.status == "finished" and result.step == 8 and len(calls) == 8
    warnings = [e["message"] for e in events if e.get("event") == "warning"]
    assert any("learning rate lowered to x0.5" in w for w in warnings), warnings
    assert any("3 training steps had a non-finite loss and were skipped" in w for w in warnings), warnings
    saved = weights(tmp_path / "m")
    assert all(torch.isfinite(t).all() for t in saved["state_dict"].values())
    view = load_scene(tiny_scene).views[1]
    assert np.isfinite(LightField.load(tmp_path / "m", "cpu").render_view(view).rgb).all()


def test_each_preset_trains_with_its_own_adam_betas(tiny_scene, tmp_path):
    """`fast` uses Adam's second-moment decay 0.99 (presets.py), except with `--appearance`;
    the paper's recipe keeps PyTorch's 0.999.  The betas are saved with Adam's state in the
    checkpoint, which a resumed run loads, so a model keeps the betas it started with."""
    small_fast = {"texture_size": [16, 16]}
    for name, options, beta2 in (("fast", dict(preset="fast", field_overrides=small_fast), 0.99),
                                 ("appearance", dict(preset="fast", field_overrides=small_fast, appearance=True), 0.999),
                                 ("authors", dict(preset="authors", field_overrides=dict(SMALL_MLP)), 0.999)):
        train(tiny_scene, tmp_path / name, small_config(2, **options))
        groups = load_checkpoint(tmp_path / name)["optimizer"]["param_groups"]
        assert {tuple(group["betas"]) for group in groups} == {(0.9, beta2)}


def test_adam_runs_fused_with_the_same_update_and_reads_an_unfused_state():
    """The trainer's Adam uses the fused kernel where torch has it (8 % less time per step on
    one CPU thread); the update is Adam's, the same as the per-tensor loop's to float
    precision, with the fast field's eps of 1e-15 and its groups' own rates, and a checkpoint
    written by the unfused optimizer (models trained before) resumes into it."""
    from neulf_core.train import _optimizer

    class Field(torch.nn.Module):
        def __init__(self):
            super().__init__()
            torch.manual_seed(0)
            self.grid, self.decoder = torch.nn.Parameter(torch.randn(4, 8)), torch.nn.Linear(8, 3)

        def param_groups(self, lr):
            return [{"params": [self.grid], "lr": 10 * lr}, {"params": self.decoder.parameters(), "lr": lr}]

    def run(make, state=None, steps=5):
        field = Field()
        optimizer = make(field)
        if state is not None:
            optimizer.load_state_dict(state)
        for step in range(steps):
            optimizer.zero_grad()
            (field.decoder(torch.sin(field.grid * (step + 1))) ** 2).mean().backward()
            optimizer.step()
        return field, optimizer

    fused, optimizer = run(lambda f: _optimizer(f, 2e-3, 0.99))
    assert optimizer.defaults["fused"] and optimizer.defaults["eps"] == 1e-15
    looped, looped_optimizer = run(lambda f: torch.optim.Adam(f.param_groups(2e-3), betas=(0.9, 0.99), eps=1e-15))
    for a, b in zip(fused.parameters(), looped.parameters()):
        assert torch.allclose(a, b, rtol=0, atol=1e-6), (a - b).abs().max()
    resumed, _ = run(lambda f: _optimizer(f, 2e-3, 0.99), state=looped_optimizer.state_dict(), steps=1)
    assert all(torch.isfinite(p).all() for p in resumed.parameters())


def test_cancel_then_resume_equals_straight_training(tiny_scene, tmp_path):
    """`fast` decays the learning rate over the budget; with the same total budget, a run
    cancelled after k steps and resumed matches an uninterrupted one bit for bit."""
    calls = {"n": 0}

    def stop_after_four():
        calls["n"] += 1
        return calls["n"] > 4

    cancelled = train(tiny_scene, tmp_path / "split", small_config(9), should_stop=stop_after_four)
    assert cancelled.status == "cancelled" and cancelled.step == 4
    saved = load_checkpoint(tmp_path / "split")
    assert saved["progress"]["step"] == 4 and saved["progress"]["status"] == "cancelled"
    resumed = train(tiny_scene, tmp_path / "split", small_config(9), resume=True)
    assert resumed.status == "finished" and resumed.step == 9
    train(tiny_scene, tmp_path / "straight", small_config(9))
    assert_same_weights(tmp_path / "straight", tmp_path / "split")


def test_a_paused_fast_field_resumes_from_its_weights_before_the_fill(tiny_scene, tmp_path):
    """At the end of a run the texels no training ray read take their neighbours' features,
    for rendering; a resumed run trains on from the weights before that fill (texels unseen
    at the pause may be read once the geometry moves), so a run paused and resumed is the
    uninterrupted run bit for bit, and model.pt has the filled texels."""
    from neulf_core.checkpoint import TRAINING_STATE_KEY

    calls = {"n": 0}

    def stop_after_six():
        calls["n"] += 1
        return calls["n"] > 6

    config = dict(preset="fast", field_overrides={"texture_size": [96, 96]}, teacher=False, refine_poses=False,
                  max_passes=0)
    train(tiny_scene, tmp_path / "split", small_config(12, **config), should_stop=stop_after_six)
    paused = load_checkpoint(tmp_path / "split")
    before, filled = paused[TRAINING_STATE_KEY], paused["state_dict"]
    assert any(not torch.equal(before[k], filled[k]) for k in before), "no texel was unseen: the test tests nothing"
    rendered = LightField.load(tmp_path / "split", "cpu").field.state_dict()
    texture = next(k for k in before if not torch.equal(before[k], filled[k]))
    assert torch.allclose(rendered[texture].float(), filled[texture].float(), atol=0.05)  # model.pt: 8-bit codes
    train(tiny_scene, tmp_path / "split", small_config(12, **config), resume=True)
    train(tiny_scene, tmp_path / "straight", small_config(12, **config))
    straight, split = load_checkpoint(tmp_path / "straight"), load_checkpoint(tmp_path / "split")
    for key in straight[TRAINING_STATE_KEY]:
        assert torch.equal(straight[TRAINING_STATE_KEY][key], split[TRAINING_STATE_KEY][key]), f"{key} differs"
        assert torch.equal(straight["state_dict"][key], split["state_dict"][key]), f"{key} differs once filled"


def test_cancel_before_the_first_step(tiny_scene, tmp_path):
    result = train(tiny_scene, tmp_path / "m", small_config(5), should_stop=lambda: True)
    assert result.status == "cancelled" and result.step == 0
    assert load_checkpoint(tmp_path / "m")["progress"]["step"] == 0
    LightField.load(tmp_path / "m", "cpu")  # an untrained but complete model


def test_train_refuses_to_overwrite_and_needs_a_budget(trained, tmp_path):
    scene_dir, model_dir, _ = trained
    with pytest.raises(NeulfError, match="already holds a trained model"):
        train(scene_dir, model_dir, small_config(9))
    with pytest.raises(NeulfError, match="training budget"):
        train(scene_dir, tmp_path / "m", TrainConfig())
    with pytest.raises(NeulfError, match="scale"):
        train(scene_dir, tmp_path / "m", small_config(3, scale=0.0))


def test_the_default_scale_keeps_each_photo_under_the_pixel_budget(tiny_scene, tmp_path, monkeypatch, capsys):
    """Without a scale a run trains at the largest 1/k at which the largest photo has at most
    DEFAULT_SCALE_PIXELS pixels, says so, and keeps it in the model; a resumed model keeps its
    own scale whatever the rule says now; a given scale is used as it is."""
    import neulf_core.rules as rules_module
    from neulf_core.rules import default_scale

    assert [default_scale(size) for size in ((960, 540), (512, 512), (504, 378), (320, 240))] == [0.5, 0.5, 1.0, 1.0]
    assert default_scale((4032, 3024)) == 1 / 8 and default_scale((3840, 2160)) == 1 / 7  # 504x378, 549x309
    monkeypatch.setattr(rules_module, "DEFAULT_SCALE_PIXELS", 500)  # the tiny scene's 48x36 photos: 1/2
    events = []
    train(tiny_scene, tmp_path / "m", small_config(3), progress=events.append)
    meta = json.loads((tmp_path / "m" / METADATA_NAME).read_text())
    assert meta["train_config"]["scale"] == 0.5 and (meta["rig"]["width"], meta["rig"]["height"]) == (24, 18)
    said = [e["message"] for e in events if e.get("event") == "stage" and "scale" in e]
    assert said == ["training at 1/2 of the photos' size (24x18; their full 48x36 with --scale 1: slower, for detail "
                    "the model's texture cannot keep)"]
    monkeypatch.setattr(rules_module, "DEFAULT_SCALE_PIXELS", 100)  # would now say 1/5
    train(tiny_scene, tmp_path / "m", small_config(6), resume=True)
    meta = json.loads((tmp_path / "m" / METADATA_NAME).read_text())
    assert meta["train_config"]["scale"] == 0.5 and meta["progress"]["step"] == 6
    assert main(["train", str(tiny_scene), "--out", str(tmp_path / "cli"), "--steps", "2", "--preset", "planes",
                 "--batch-size", "256"]) == 0
    assert "training at 1/5 of the photos' size (10x7; their full 48x36 with --scale 1" in capsys.readouterr().err
    # A scale asked for is used; far above the default's pixels it is warned about, once a run
    # (here with two members, each of which asks again).
    events = []
    train(tiny_scene, tmp_path / "given", small_config(4, scale=1.0, members=2), progress=events.append)
    assert json.loads((tmp_path / "given" / METADATA_NAME).read_text())["train_config"]["scale"] == 1.0
    assert not [e for e in events if e.get("event") == "stage" and "scale" in e]
    assert [e["message"] for e in events if e.get("event") == "warning"] == [
        "scale 1 trains on photos of 48x36 (0 M pixels in all, 25 times the default's): slow to start and to train, and "
        "memory-hungry, for detail the model's texture cannot keep; the default scale (no --scale; Image Scale 0 in "
        "Blender) trains at 10x7"]
    monkeypatch.setattr(rules_module, "DEFAULT_SCALE_PIXELS", 200)  # 24x18 = 432 is within 4 times 200
    events = []
    train(tiny_scene, tmp_path / "within", small_config(2, scale=0.5), progress=events.append)
    assert not [e for e in events if e.get("event") == "warning"]


def test_leftover_temp_file(trained, tmp_path):
    _, model_dir, _ = trained
    # A crash during the very first save leaves only the temporary file: no model yet.
    crashed = tmp_path / "crashed"
    crashed.mkdir()
    data = (model_dir / CHECKPOINT_NAME).read_bytes()
    (crashed / f".{CHECKPOINT_NAME}.k2j4h1.tmp").write_bytes(data[: len(data) // 3])
    with pytest.raises(NeulfError, match="holds no trained model"):
        LightField.load(crashed, "cpu")
    # A crash during a later save leaves the previous checkpoint intact beside the temp file.
    model = copy_model(model_dir, tmp_path / "model")
    (model / f".{CHECKPOINT_NAME}.x8f0q.tmp").write_bytes(data[:100])
    LightField.load(model, "cpu")
    # Resuming (which holds the folder's training lock) clears the leftover away.
    train(trained[0], model, small_config(9), resume=True)
    assert not list(model.glob(".*.tmp"))


def test_truncated_checkpoint(trained, tmp_path):
    _, model_dir, _ = trained
    model = copy_model(model_dir, tmp_path / "model")
    path = model / CHECKPOINT_NAME
    size = path.stat().st_size
    with open(path, "r+b") as handle:
        handle.truncate(size // 2)
    with pytest.raises(NeulfError, match="truncated or corrupted"):
        LightField.load(model, "cpu")
    path.write_bytes(b"")
    with pytest.raises(NeulfError, match="truncated or corrupted"):
        LightField.load(model, "cpu")


def test_atomic_write_failure_keeps_the_old_file(tmp_path):
    target = tmp_path / "file.bin"
    atomic_write_bytes(target, b"old contents")

    class Unwritable:  # not bytes: the write into the temporary file fails
        pass

    with pytest.raises(TypeError):
        atomic_write_bytes(target, Unwritable())
    assert target.read_bytes() == b"old contents"
    assert [p.name for p in tmp_path.iterdir()] == ["file.bin"]
    atomic_write_bytes(target, b"new")
    assert target.read_bytes() == b"new" and [p.name for p in tmp_path.iterdir()] == ["file.bin"]


def test_a_signal_as_the_temporary_is_made_leaves_none_behind(tmp_path, monkeypatch):
    """Ctrl-C or SIGTERM is raised as soon as a system call returns: one landing just as the
    temporary file was made left it behind (test_outputs' SIGTERM render found one once)."""
    import neulf_core.files as files

    target = tmp_path / "file.bin"
    atomic_write_bytes(target, b"old contents")
    real_open = os.open

    def made_then_interrupted(*args, **kwargs):
        os.close(real_open(*args, **kwargs))
        raise KeyboardInterrupt  # (the signal's handler, run as os.open returns)

    monkeypatch.setattr(files.os, "open", made_then_interrupted)
    with pytest.raises(KeyboardInterrupt):
        atomic_write_bytes(target, b"new contents")
    assert [p.name for p in tmp_path.iterdir()] == ["file.bin"] and target.read_bytes() == b"old contents"


@pytest.mark.skipif(os.name != "posix", reason="file modes are POSIX")
def test_written_files_get_the_users_permissions(tmp_path, cli_model):
    """A model, a render's EXR: readable by the user's group and others as any file the user
    writes (0666 less the umask), not 0600 as tempfile.mkstemp made them (a render farm or a
    second account could not read the model)."""
    from neulf_core.exr import write_exr

    previous = os.umask(0o022)
    try:
        atomic_write_bytes(tmp_path / "a.bin", b"x")
        write_exr(tmp_path / "b.exr", {"R": np.zeros((2, 2))})
        os.umask(0o077)
        atomic_write_bytes(tmp_path / "c.bin", b"x")
    finally:
        os.umask(previous)
    modes = {p.name: p.stat().st_mode & 0o777 for p in tmp_path.iterdir()}
    assert modes == {"a.bin": 0o644, "b.exr": 0o644, "c.bin": 0o600}, modes
    current = os.umask(0o022)
    os.umask(current)
    trained = {p.name: p.stat().st_mode & 0o777 for p in cli_model.iterdir() if p.is_file()}
    assert trained and all(mode == 0o666 & ~current for mode in trained.values()), (trained, oct(current))


def rewrite_checkpoint(model: Path, change) -> None:
    payload = weights(model)
    change(payload)
    torch.save(payload, model / CHECKPOINT_NAME)


def test_other_version_format_and_damage(trained, tmp_path):
    scene_dir, model_dir, _ = trained
    model = copy_model(model_dir, tmp_path / "version")
    rewrite_checkpoint(model, lambda p: p.update(version=99))
    with pytest.raises(NeulfError, match="another version"):
        LightField.load(model, "cpu")
    with pytest.raises(NeulfError, match="another version"):
        train(scene_dir, model, small_config(12), resume=True)

    other = tmp_path / "other"
    other.mkdir()
    torch.save({"weights": [1, 2, 3]}, other / CHECKPOINT_NAME)
    with pytest.raises(NeulfError, match="not a NeuLF checkpoint"):
        LightField.load(other, "cpu")

    damaged = copy_model(model_dir, tmp_path / "damaged")
    rewrite_checkpoint(damaged, lambda p: p["state_dict"].pop(next(iter(p["state_dict"]))))
    with pytest.raises(NeulfError, match="damaged or incomplete"):
        LightField.load(damaged, "cpu")


def test_resume_with_another_scene(trained, tmp_path, tiny_scene_factory):
    _, model_dir, _ = trained
    other_scene = tiny_scene_factory(tmp_path / "other_scene", shift=(0.05, 0.0, 0.0))
    model = copy_model(model_dir, tmp_path / "model")
    with pytest.raises(NeulfError, match="another reconstruction"):
        train(other_scene, model, small_config(12), resume=True)
    light_field = LightField.load(model, "cpu")
    with pytest.raises(NeulfError, match="another reconstruction"):
        light_field.check_scene(load_scene(other_scene))


# ----------------------------------------------------------------------------- command line: errors


def cameras_json(path: Path, **changes) -> str:
    R = np.eye(3)
    camera = {"name": "novel", "K": [[40.0, 0, 16.0], [0, 40.0, 12.0], [0, 0, 1]], "width": 32, "height": 24,
              "R": R.tolist(), "t": [0.0, 0.0, 0.0]}
    camera.update(changes)
    for key, value in list(camera.items()):
        if value is None:
            del camera[key]
    path.write_text(json.dumps({"cameras": [camera]}))
    return str(path)


@pytest.fixture(scope="module")
def cli_model(tiny_scene, tmp_path_factory):
    """A model trained through the CLI (default preset, a few small steps)."""
    model = tmp_path_factory.mktemp("cli") / "model"
    code = main(["train", str(tiny_scene), "--out", str(model), "--steps", "3", "--batch-size", "256",
                 "--progress", "json", "--seed", "1"])
    assert code == 0
    return model


def broken_scene(tiny_scene: Path, tmp: Path, how: str) -> str:
    scene = tmp / f"scene_{how}"
    shutil.copytree(tiny_scene, scene)
    model = scene / "sparse" / "0"
    if how == "random_cameras":
        (model / "cameras.bin").write_bytes(np.random.default_rng(0).bytes(300))
    elif how == "truncated_images":
        data = (model / "images.bin").read_bytes()
        (model / "images.bin").write_bytes(data[: len(data) // 2])
    elif how == "missing_images":
        for name in ("view_03.png", "view_05.png"):
            (scene / "images" / name).unlink()
    elif how == "no_model":
        shutil.rmtree(scene / "sparse")
    elif how == "corrupt_image":
        (scene / "images" / "view_04.png").write_bytes(b"garbage")
    return str(scene)


ERROR_CASES = {
    # name: (argv builder(ctx), text expected in the message)
    "missing scene folder": (lambda c: ["train", str(c["tmp"] / "nope"), "--out", c["new"], "--steps", "1"], "does not exist"),
    "folder without a model": (lambda c: ["train", broken_scene(c["scene"], c["tmp"], "no_model"), "--out", c["new"], "--steps", "1"],
                               "no camera model"),
    "random cameras.bin": (lambda c: ["train", broken_scene(c["scene"], c["tmp"], "random_cameras"), "--out", c["new"], "--steps", "1"],
                           "cannot read the COLMAP model"),
    "truncated images.bin": (lambda c: ["train", broken_scene(c["scene"], c["tmp"], "truncated_images"), "--out", c["new"], "--steps", "1"],
                             "cannot read the COLMAP model"),
    "missing images": (lambda c: ["train", broken_scene(c["scene"], c["tmp"], "missing_images"), "--out", c["new"], "--steps", "1"],
                       "2 of 9 images"),
    "unreadable image": (lambda c: ["train", broken_scene(c["scene"], c["tmp"], "corrupt_image"), "--out", c["new"], "--steps", "1"],
                         "cannot read image"),
    "render: missing model folder": (lambda c: ["render", str(c["tmp"] / "nomodel"), "--scene", str(c["scene"]), "--views", "all",
                                                "--out", c["out"]], "does not exist"),
    "eval: missing model folder": (lambda c: ["eval", str(c["tmp"] / "nomodel"), "--scene", str(c["scene"])], "does not exist"),
    "model folder without checkpoint": (lambda c: ["render", c["empty"], "--cameras", cameras_json(c["tmp"] / "c.json"),
                                                   "--out", c["out"]], "holds no trained model"),
    "cameras: invalid JSON": (lambda c: ["render", c["model"], "--cameras", write(c["tmp"] / "bad.json", "{not json"),
                                         "--out", c["out"]], "not valid JSON"),
    "cameras: missing key": (lambda c: ["render", c["model"], "--cameras", cameras_json(c["tmp"] / "c.json", K=None),
                                        "--out", c["out"]], "needs K"),
    "cameras: not a rotation": (lambda c: ["render", c["model"], "--cameras",
                                           cameras_json(c["tmp"] / "c.json", R=[[1, 0, 0], [0, 2, 0], [0, 0, 1]]),
                                           "--out", c["out"]], "not a rotation"),
    "cameras: a reflection": (lambda c: ["render", c["model"], "--cameras",
                                         cameras_json(c["tmp"] / "c.json", R=[[1, 0, 0], [0, 1, 0], [0, 0, -1]]),
                                         "--out", c["out"]], "not a rotation"),
    "cameras: empty list": (lambda c: ["render", c["model"], "--cameras", write(c["tmp"] / "e.json", "[]"), "--out", c["out"]],
                            "list of cameras"),
    "cameras: missing file": (lambda c: ["render", c["model"], "--cameras", str(c["tmp"] / "none.json"), "--out", c["out"]],
                              "does not exist"),
    "cameras: zero focal length": (lambda c: ["render", c["model"], "--cameras",
                                              cameras_json(c["tmp"] / "c.json", K=[[0, 0, 16], [0, 0, 12], [0, 0, 1]]),
                                              "--out", c["out"]], "positive focal lengths"),
    "render: zero scale": (lambda c: ["render", c["model"], "--scene", str(c["scene"]), "--views", "all", "--scale", "0",
                                      "--out", c["out"]], "--scale: '0': give a finite number above 0"),
    "negative batch size": (lambda c: ["train", str(c["scene"]), "--out", c["new"], "--steps", "1", "--batch-size", "-5"],
                            "--batch-size: '-5': give a whole number above 0"),
    "zero batch size": (lambda c: ["train", str(c["scene"]), "--out", c["new"], "--steps", "1", "--batch-size", "0"],
                        "--batch-size: '0': give a whole number above 0"),
    "zero-size camera": (lambda c: ["render", c["model"], "--cameras", cameras_json(c["tmp"] / "c.json", width=0),
                                    "--out", c["out"]], "at least 1 pixel"),
    # Sizes and rates past any real one (a typo, a damaged file) had failed in numpy, pycolmap or the
    # encoder with their own tracebacks.
    "camera a billion pixels wide": (lambda c: ["render", c["model"], "--cameras",
                                                cameras_json(c["tmp"] / "c.json", width=10**9, height=10**9),
                                                "--out", c["out"]], "a side is at most 65535 pixels"),
    "camera 1e300 pixels wide": (lambda c: ["render", c["model"], "--cameras", cameras_json(c["tmp"] / "c.json", width=1e300),
                                            "--out", c["out"]], "a side is at most 65535 pixels"),
    "render: absurd scale": (lambda c: ["render", c["model"], "--scene", str(c["scene"]), "--views", "all", "--scale",
                                        "1e300", "--out", c["out"]], "give a smaller --scale"),
    "video: absurd frame rate": (lambda c: ["video", c["model"], "--out", str(c["tmp"] / "v.mp4"), "--frames", "2",
                                            "--fps", "1e300"], "frames per second up to 1000"),
    "cameras: empty name": (lambda c: ["render", c["model"], "--cameras", cameras_json(c["tmp"] / "c.json", name=""),
                                       "--out", c["out"]], "give it a file name"),
    "cameras: named only an extension": (lambda c: ["render", c["model"], "--cameras",
                                                    cameras_json(c["tmp"] / "c.json", name=".png"), "--out", c["out"]],
                                         "give it a file name"),
    "cameras: lists nested deep": (lambda c: ["render", c["model"], "--cameras",
                                              write(c["tmp"] / "deep.json", "[" * 100000 + "]" * 100000), "--out", c["out"]],
                                   "nests its lists too deep"),
    "f-stop without focal length": (lambda c: ["render", c["model"], "--scene", str(c["scene"]), "--views", "all",
                                               "--focus-distance", "1", "--f-stop", "2", "--out", c["out"]], "--focal-length"),
    "f-stop and aperture": (lambda c: ["render", c["model"], "--scene", str(c["scene"]), "--views", "all", "--focus-distance",
                                       "1", "--f-stop", "2", "--focal-length", "0.05", "--aperture", "0.1", "--out", c["out"]],
                            "not both"),
    "render: neither scene nor cameras": (lambda c: ["render", c["model"], "--out", c["out"]], "either --scene"),
    "render: unknown view": (lambda c: ["render", c["model"], "--scene", str(c["scene"]), "--views", "view_99",
                                        "--out", c["out"]], "no view named"),
    "render: another scene": (lambda c: ["render", c["model"], "--scene", c["other_scene"], "--views", "all",
                                         "--out", c["out"]], "another reconstruction"),
    "unknown preset": (lambda c: ["train", str(c["scene"]), "--out", c["new"], "--steps", "1", "--preset", "huge"],
                       "unknown preset 'huge'"),
    "no budget": (lambda c: ["train", str(c["scene"]), "--out", c["new"]], "training budget"),
    "minutes and steps": (lambda c: ["train", str(c["scene"]), "--out", c["new"], "--steps", "1", "--minutes", "1"],
                          "not allowed with argument"),
    "negative steps": (lambda c: ["train", str(c["scene"]), "--out", c["new"], "--steps", "-3"], "--steps: '-3': give a whole number above 0"),
    "unknown option": (lambda c: ["train", str(c["scene"]), "--out", c["new"], "--steps", "1", "--bogus"],
                       "unrecognized arguments: --bogus"),
    "unknown command": (lambda c: ["fly"], "invalid choice"),
    "existing model without --resume": (lambda c: ["train", str(c["scene"]), "--out", c["model"], "--steps", "1"],
                                        "already holds a trained model"),
    "resume with another scene": (lambda c: ["train", c["other_scene"], "--out", c["model"], "--steps", "9", "--resume"],
                                  "another reconstruction"),
}


def write(path: Path, text: str) -> str:
    path.write_text(text)
    return str(path)


@pytest.fixture(scope="module")
def other_scene(tmp_path_factory, tiny_scene_factory):
    return tiny_scene_factory(tmp_path_factory.mktemp("other"), shift=(0.05, 0.0, 0.0))


@pytest.mark.parametrize("case", list(ERROR_CASES))
def test_cli_errors_are_one_line(case, tiny_scene, cli_model, other_scene, tmp_path, capfd, record_property):
    (tmp_path / "empty").mkdir()
    context = {"tmp": tmp_path, "scene": tiny_scene, "model": str(cli_model), "new": str(tmp_path / "new_model"),
               "out": str(tmp_path / "out"), "empty": str(tmp_path / "empty"), "other_scene": str(other_scene)}
    build, expected = ERROR_CASES[case]
    argv = build(context)
    capfd.readouterr()
    code = main(argv)
    captured = capfd.readouterr()
    lines = captured.err.splitlines()
    assert code == 2, captured.err
    assert len(lines) == 1, f"stderr should be one line, got: {captured.err!r}"
    assert lines[0].startswith("error: "), lines[0]
    assert expected in lines[0]
    assert "Traceback" not in captured.err + captured.out
    record_property("message", lines[0])
    if argv[0] == "train" and "--resume" not in argv and argv[argv.index("--out") + 1] != context["model"]:
        assert not (tmp_path / "new_model" / CHECKPOINT_NAME).exists()


# ----------------------------------------------------------------------------- command line: a damaged model folder


def garble_zip_version(path: Path) -> None:
    """Flipped bytes in a zip's central directory that read as "version needed 14.1": zipfile
    raises NotImplementedError for it (the fuzz audit's model.pt with 20 bytes XORed)."""
    data = bytearray(path.read_bytes())
    entry = data.rfind(b"PK\x01\x02")
    data[entry + 6:entry + 8] = (141).to_bytes(2, "little")
    path.write_bytes(bytes(data))


def edit_checkpoint(change):
    def damage(model: Path) -> None:
        payload = weights(model)
        torch.save(change(payload), model / CHECKPOINT_NAME)
    return damage


def nan_weights(payload: dict) -> dict:
    """Every float weight NaN (a diverged training, or a damaged file)."""
    for key in ("state_dict", "state_dict_before_fill"):
        for tensor in (payload.get(key) or {}).values():
            if tensor.is_floating_point():
                tensor.fill_(float("nan"))
    return payload


def both_files(change):
    """`change` made to the checkpoint and to model.json alike (an edit by hand of both)."""
    def damage(model: Path) -> None:
        edit_checkpoint(change)(model)
        meta = json.loads((model / "model.json").read_text())
        (model / "model.json").write_text(json.dumps(change(meta)))
    return damage


def without_model_pt(damage):
    """`damage`, and model.pt deleted: what is rendered is checkpoint.pt."""
    def both(model: Path) -> None:
        damage(model)
        (model / "model.pt").unlink()
    return both


def folder_in_place_of(name: str):
    def damage(model: Path) -> None:
        (model / name).unlink()
        (model / name).mkdir()
        (model / name / "keep.txt").write_text("the user's")
    return damage


def write_file(name: str, text: str):
    return lambda model: (model / name).write_text(text)


def render_argv(c):
    return ["render", c["model"], "--scene", str(c["scene"]), "--views", "view_01", "--out", c["out"], "--pixel-samples", "1"]


def resume_argv(c):
    return ["train", str(c["scene"]), "--out", c["model"], "--steps", "6", "--resume", "--progress", "json"]


def eval_argv(c):
    return ["eval", c["model"], "--scene", str(c["scene"]), "--out", c["out"], "--pixel-samples", "1"]


DAMAGED_MODEL_CASES = {
    # name: (damage(model folder), argv builder(ctx), text expected in the one-line message)
    "model.pt garbled zip": (lambda model: garble_zip_version(model / "model.pt"), render_argv,
                             "is truncated or corrupted (ValueError: a member cannot be read (zip file version "
                             "14.1)); delete it: rendering then reads checkpoint.pt beside it"),
    "members.json finished not numbers": (write_file("members.json", json.dumps(
        {"count": 2, "seed": 0, "split": "batch", "finished": ["two"]})), render_argv, "members.json is damaged"),
    "members.json finished null": (write_file("members.json", json.dumps(
        {"count": 2, "seed": 0, "split": "batch", "finished": None})), render_argv, "members.json is damaged"),
    "members.json finished dicts": (write_file("members.json", json.dumps(
        {"count": 2, "seed": 0, "split": "batch", "finished": [{"m": 2}]})), render_argv, "members.json is damaged"),
    "members.json garbled, resume": (write_file("members.json", json.dumps(
        {"count": 2, "seed": "zero", "split": 7, "finished": ["x"]})), resume_argv, "members.json is damaged"),
    "members.json not JSON": (write_file("members.json", '{"count": 2, "se'), render_argv, "members.json"),
    "starts.json a list, resume": (write_file("starts.json", "[1, 2, 3]"), resume_argv, "starts.json is damaged"),
    "starts.json missing keys, resume": (write_file("starts.json", '{"stage": "second"}'), resume_argv,
                                         "starts.json is damaged"),
    "checkpoint missing keys, resume": (edit_checkpoint(lambda p: {"format": p["format"], "version": p["version"]}),
                                        resume_argv, "it has no 'field'"),
    "checkpoint missing keys, render": (without_model_pt(edit_checkpoint(
        lambda p: {"format": p["format"], "version": p["version"]})), render_argv, "it has no 'field'"),
    "checkpoint wrong types, resume": (edit_checkpoint(lambda p: {**p, "step": "ten", "progress": [], "scene": 5}),
                                       resume_argv, "is damaged"),
    "checkpoint progress wrong types, resume": (edit_checkpoint(
        lambda p: {**p, "progress": {**p["progress"], "step": "ten"}}), resume_argv, "its step is 'ten'"),
    "checkpoint wrong types, render": (without_model_pt(edit_checkpoint(
        lambda p: {**p, "scene": "x", "rig": 5, "slab": [1, 2]})), render_argv, "is damaged"),
    "checkpoint train_config wrong types, resume": (edit_checkpoint(lambda p: {**p, "train_config": {
        **p["train_config"], "preset": 5, "scale": "half"}}), resume_argv, "its train_config's 'preset' is an int"),
    "checkpoint train_config wrong types, model.json too, resume": (both_files(lambda p: {**p, "train_config": {
        **p["train_config"], "seed": [1], "holdout_every": "8"}}), resume_argv, "its train_config's 'holdout_every' is a str"),
    "checkpoint NaN weights, resume": (without_model_pt(edit_checkpoint(nan_weights)), resume_argv, "NaN or infinite"),
    "checkpoint NaN weights, render": (without_model_pt(edit_checkpoint(nan_weights)), render_argv, "NaN or infinite"),
    "checkpoint NaN weights, eval": (without_model_pt(edit_checkpoint(nan_weights)), eval_argv, "NaN or infinite"),
    "model.pt a folder, resume": (folder_in_place_of("model.pt"), resume_argv,
                                  "model.pt: a folder of that name is in the way"),
    "model.json a folder, resume": (folder_in_place_of("model.json"), resume_argv,
                                    "model.json: a folder of that name is in the way"),
}


@pytest.mark.parametrize("case", list(DAMAGED_MODEL_CASES))
def test_a_damaged_model_folder_is_one_line(case, tiny_scene, cli_model, tmp_path, capfd, record_property):
    """Each file of a model folder damaged as the fuzz audit damaged it: one line that names
    the file and what to do, exit status 2, no traceback, no picture or scores of NaN."""
    model = copy_model(cli_model, tmp_path / "model")
    damage, build, expected = DAMAGED_MODEL_CASES[case]
    damage(model)
    argv = build({"scene": tiny_scene, "model": str(model), "out": str(tmp_path / "out")})
    capfd.readouterr()
    code = main(argv)
    captured = capfd.readouterr()
    errors = [line for line in captured.err.splitlines() if line.startswith("error: ")]
    assert code == 2, captured.err
    assert len(errors) == 1 and captured.err.rstrip().splitlines()[-1] == errors[0], captured.err
    assert expected in errors[0], errors[0]
    assert "Traceback" not in captured.err + captured.out
    assert ".tmp" not in errors[0]  # (a hidden temporary is not what the user knows)
    assert not list((tmp_path / "out").glob("*.png"))
    record_property("message", errors[0])
    for folder in model.iterdir():  # a folder in the way is the user's: kept
        if folder.is_dir() and folder.name.endswith((".pt", ".json")):
            assert (folder / "keep.txt").read_text() == "the user's"


def test_a_render_onto_a_folder_names_it_and_keeps_it(cli_model, tiny_scene, tmp_path, capfd):
    (tmp_path / "out" / "view_01.png").mkdir(parents=True)
    (tmp_path / "out" / "view_01.png" / "keep.txt").write_text("keep")
    code = main(render_argv({"scene": tiny_scene, "model": str(cli_model), "out": str(tmp_path / "out")}))
    err = capfd.readouterr().err
    assert code == 2 and err.rstrip().splitlines()[-1].startswith("error: cannot write ") and "Traceback" not in err
    assert "view_01.png: a folder of that name is in the way" in err and ".tmp" not in err, err
    assert (tmp_path / "out" / "view_01.png" / "keep.txt").read_text() == "keep"


def test_an_unreadable_model_file_is_not_called_damaged(cli_model, tiny_scene, tmp_path, capfd, monkeypatch,
                                                        record_property):
    """A model.pt we may not read is a good file: the message says how to read it, not to delete it."""
    model = copy_model(cli_model, tmp_path / "model")
    os.chmod(model / "model.pt", 0)
    try:
        with open(model / "model.pt", "rb"):  # (root reads it anyway: the refusal is simulated)
            import neulf_core.checkpoint as checkpoint

            def refuse(path, *args, **kwargs):
                raise PermissionError(13, "Permission denied", str(path))
            monkeypatch.setattr(checkpoint.torch, "load", refuse)
    except PermissionError:
        pass
    code = main(render_argv({"scene": tiny_scene, "model": str(model), "out": str(tmp_path / "out")}))
    os.chmod(model / "model.pt", 0o644)
    err = capfd.readouterr().err
    line = err.rstrip().splitlines()[-1]
    assert code == 2 and "Traceback" not in err, err
    assert line.startswith(f"error: cannot read {model / 'model.pt'}: permission denied") and "chmod" in line, line
    assert "delete" not in line and "corrupted" not in line, line
    record_property("message", line)


@pytest.mark.parametrize("metadata", [
    {"train_config": {"preset": 5, "scale": "x", "seed": [1]}, "scene": "x", "progress": 5, "rules": []},
    {"scene": {"images": 5, "photo_sizes": "x"}},
])
def test_resume_over_a_damaged_model_json(metadata, cli_model, tiny_scene, tmp_path, capfd):
    """model.json is only a copy of the checkpoint's metadata: one of other types is read as none
    (as an unreadable one is), the resume goes on from checkpoint.pt and writes it again."""
    model = copy_model(cli_model, tmp_path / "model")
    (model / METADATA_NAME).write_text(json.dumps(metadata))
    code = main(resume_argv({"scene": tiny_scene, "model": str(model)}))
    captured = capfd.readouterr()
    assert code == 0 and "Traceback" not in captured.err, captured.err
    meta = json.loads((model / METADATA_NAME).read_text())
    assert meta["progress"]["step"] == 6 and isinstance(meta["scene"], dict)


def test_cli_subprocess_exit_status(tmp_path):
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    completed = subprocess.run([sys.executable, "-m", "neulf_core", "train", "/nonexistent", "--out", str(tmp_path / "x"),
                                "--steps", "1"], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    assert completed.returncode == 2
    lines = completed.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "/nonexistent" in lines[0], completed.stderr
    assert not (tmp_path / "x").exists()


# ----------------------------------------------------------------------------- command line: happy path


def test_cli_train_render_eval(cli_model, tiny_scene, tmp_path, capfd):
    meta = json.loads((cli_model / METADATA_NAME).read_text())
    assert meta["progress"]["step"] == 3 and meta["train_config"]["preset"] == "fast"
    assert meta["train_config"]["seed"] == 1 and meta["train_config"]["batch_size"] == 256

    # Held-out views with depth.
    out = tmp_path / "held"
    assert main(["render", str(cli_model), "--scene", str(tiny_scene), "--views", "held-out", "--depth", "--out", str(out)]) == 0
    for stem in ("view_00", "view_08"):
        image = Image.open(out / f"{stem}.png")
        assert image.size == (48, 36) and image.mode == "RGB"
        depth = np.load(out / f"{stem}_depth.npy")
        assert depth.shape == (36, 48) and depth.dtype == np.float32
        assert np.isfinite(depth).all() and (depth > 0).all()
        # Slab-axis depths lie in [z_near, z_far]; these cameras are within 3 degrees of the axis.
        slab = meta["slab"]
        assert depth.min() > 0.95 * slab["z_near"] and depth.max() < 1.05 * slab["z_far"]
        assert 2.0 < float(np.median(depth)) < 4.5  # the plane is at depth 2.76 .. 3.24
        assert Image.open(out / f"{stem}_depth.png").size == (48, 36)
    assert "rendered 2 image(s)" in capfd.readouterr().out

    # The same for compositing: --exr writes the colour scene-linear and the depth as Z.
    from exr_file import read_exr
    from neulf_core.exr import srgb_to_linear

    assert main(["render", str(cli_model), "--scene", str(tiny_scene), "--views", "view_00", "--depth", "--exr",
                 "--out", str(out)]) == 0
    channels = read_exr(out / "view_00.exr")
    assert sorted(channels) == ["A", "B", "G", "R", "Z"] and channels["Z"].shape == (36, 48)
    assert (channels["A"] == 1.0).all()  # every ray of a training rig's view crosses the slab
    assert np.array_equal(channels["Z"], np.load(out / "view_00_depth.npy"))  # finite here: no 1e10
    png = np.asarray(Image.open(out / "view_00.png"), np.float32) / 255
    linear = np.stack([channels[c] for c in "RGB"], axis=2)
    assert np.abs(linear - srgb_to_linear(png)).max() < 0.01  # the PNG rounds the same colours to 8 bits

    # Arbitrary pinhole cameras from JSON, at another size.
    cams = tmp_path / "cams.json"
    R = np.eye(3)
    cams.write_text(json.dumps([
        {"name": "wide", "K": [[30.0, 0, 20.0], [0, 30.0, 15.0], [0, 0, 1]], "width": 40, "height": 30, "R": R.tolist(), "t": [0, 0, 0]},
        {"K": [[60.0, 0, 8.0], [0, 60.0, 11.0], [0, 0, 1]], "width": 16, "height": 22, "R": R.tolist(), "t": [0.02, 0, 0]},
    ]))
    out = tmp_path / "novel"
    assert main(["render", str(cli_model), "--cameras", str(cams), "--out", str(out)]) == 0
    assert Image.open(out / "wide.png").size == (40, 30)
    assert Image.open(out / "camera_001.png").size == (16, 22)
    assert not (out / "wide_depth.npy").exists()

    # All views, at half scale.
    out = tmp_path / "all"
    assert main(["render", str(cli_model), "--scene", str(tiny_scene), "--views", "all", "--scale", "0.5", "--out", str(out)]) == 0
    assert len(list(out.glob("view_*.png"))) == 9 and Image.open(out / "view_04.png").size == (24, 18)

    # Evaluation.
    capfd.readouterr()
    assert main(["eval", str(cli_model), "--scene", str(tiny_scene)]) == 0
    printed = capfd.readouterr().out
    report = json.loads((cli_model / "eval" / "eval.json").read_text())
    assert [row["view"] for row in report["views"]] == ["view_00.png", "view_08.png"]
    for row in report["views"]:
        assert row["view"] in printed and f"{row['psnr']:9.3f}" in printed
        assert 5 < row["psnr"] < 60 and -1 <= row["ssim"] <= 1
        assert (row["width"], row["height"]) == (48, 36)
    assert report["mean_psnr"] == pytest.approx(np.mean([r["psnr"] for r in report["views"]]))
    assert (cli_model / "eval" / "eval.csv").is_file() and (cli_model / "eval" / "view_00.png").is_file()
    # The PSNR eval reports is the PSNR of the image it wrote against the photo (up to 8-bit rounding).
    written = np.asarray(Image.open(cli_model / "eval" / "view_00.png"), dtype=np.float64) / 255
    photo = np.asarray(Image.open(tiny_scene / "images" / "view_00.png"), dtype=np.float64) / 255
    assert psnr(written, photo) == pytest.approx(report["views"][0]["psnr"], abs=0.05)

    # Evaluating named views into another folder.
    out = tmp_path / "eval_named"
    assert main(["eval", str(cli_model), "--scene", str(tiny_scene), "--views", "view_04", "--out", str(out)]) == 0
    assert [r["view"] for r in json.loads((out / "eval.json").read_text())["views"]] == ["view_04.png"]


def test_cli_resume(tiny_scene, tmp_path, capfd):
    model = tmp_path / "model"
    assert main(["train", str(tiny_scene), "--out", str(model), "--steps", "2", "--batch-size", "128", "--progress", "json"]) == 0
    assert main(["train", str(tiny_scene), "--out", str(model), "--steps", "4", "--batch-size", "128", "--resume",
                 "--progress", "json"]) == 0
    lines = [json.loads(line) for line in capfd.readouterr().out.splitlines()]
    assert lines[-1]["event"] == "finished" and lines[-1]["step"] == 4
    assert [e["step"] for e in lines if e["event"] in ("step", "validate")][-2:] == [3, 4]


def interrupt_training(scene, model: Path, *options: str, signal_number: int = signal.SIGINT):
    """Run `train` in a subprocess, send `signal_number` (SIGINT) after its first training step:
    (exit code, stdout, stderr)."""
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    process = subprocess.Popen([sys.executable, "-m", "neulf_core", "train", str(scene), "--out", str(model), *options,
                                "--steps", "100000", "--batch-size", "64", "--progress", "json"],
                               cwd=model.parent, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        for line in process.stdout:
            if json.loads(line)["event"] == "step":
                break
        process.send_signal(signal_number)
        out, err = process.communicate(timeout=120)
    finally:
        if process.poll() is None:
            process.kill()
    return process.returncode, out, err


def test_cli_sigint_cancels_and_saves(tiny_scene, tmp_path):
    """Ctrl+C during training: the step in progress finishes, the checkpoint is saved, exit 130."""
    model = tmp_path / "model"
    code, out, err = interrupt_training(tiny_scene, model)
    assert code == 130, err
    events = [json.loads(line) for line in out.splitlines()]
    assert events[-1]["event"] == "cancelled"
    assert "cancelled at step" in err and "Traceback" not in err
    saved = load_checkpoint(model)
    assert saved["progress"]["status"] == "cancelled" and saved["progress"]["step"] == events[-1]["step"] >= 1


def test_cli_sigint_during_the_auto_size_search_says_nothing_was_saved(tiny_scene, tmp_path):
    """Ctrl+C while `auto` is still choosing the size (a candidate is training): no model exists
    yet, and the message says so."""
    model = tmp_path / "model"
    code, out, err = interrupt_training(tiny_scene, model, "--preset", "auto")
    assert code == 130, err
    assert "nothing was saved" in err and "Traceback" not in err, err
    assert not (model / CHECKPOINT_NAME).exists()


def test_a_saved_config_of_the_declared_types_passes_and_others_are_named():
    """What training saves (asdict of a TrainConfig, numpy scalars and tuples included) passes the
    resume's type check; a value of another type is named with its field."""
    from dataclasses import asdict

    import numpy as np

    from neulf_core.saved_config import type_problem, upgraded
    from neulf_core.rules import LOSSES_UNTIL_POSES_RIGHT
    from neulf_core.train import TrainConfig

    saved = asdict(TrainConfig(steps=np.int64(10), minutes=None, scale=np.float64(0.5), exclude=("a.png",),
                               consistency=LOSSES_UNTIL_POSES_RIGHT, max_passes=100, field_overrides={"x": 1}))
    assert type_problem(saved, TrainConfig) is None
    assert type_problem({**saved, "unknown_field": object()}, TrainConfig) is None  # (another version's: dropped)
    assert "'seed' is a bool" in type_problem({**saved, "seed": True}, TrainConfig)
    assert "'exclude' is a list" in type_problem({**saved, "exclude": ["a.png", 3]}, TrainConfig)
    assert "not a number or None" in type_problem({**saved, "scale": "half"}, TrainConfig)
    assert "'appearance' is an int (1), not true or false or None" in type_problem({**saved, "appearance": 1}, TrainConfig)
    assert type_problem({**saved, "appearance": np.bool_(True)}, TrainConfig) is None
    # pixel_jitter was a switch in the version of 2026-11-27 (on: anywhere in the pixel): read as its width
    assert upgraded({**saved, "pixel_jitter": True})["pixel_jitter"] == 1.0
    assert type_problem(upgraded({**saved, "pixel_jitter": False}), TrainConfig) is None


def test_a_lost_model_json_is_written_again_from_its_checkpoint(cli_model, tmp_path):
    """Blender's Python reads a model's progress from model.json (it has no torch for the
    checkpoint): a damaged one had been read as step 0, and Train added its budget to that.  The
    core writes it again from checkpoint.pt, in the model folder and each member's, and leaves a
    readable one alone."""
    from neulf_core.worker import Service

    model = copy_model(cli_model, tmp_path / "model")
    shutil.copytree(cli_model, model / "members" / "2")
    (model / "members.json").write_text(json.dumps({"count": 2, "seed": 1, "split": "batch", "finished": [2]}))
    original = json.loads((model / METADATA_NAME).read_text())
    (model / METADATA_NAME).write_text('{"progress": {"st')
    (model / "members" / "2" / METADATA_NAME).unlink()
    assert Service().restore_metadata(str(model)) == [str(model), str(model / "members" / "2")]
    for folder in (model, model / "members" / "2"):
        again = json.loads((folder / METADATA_NAME).read_text())
        assert again["progress"] == original["progress"] and again["scene"] == original["scene"]
        assert again["format"] == "neulf-checkpoint"
    stamp = (model / METADATA_NAME).stat().st_mtime_ns
    assert Service().restore_metadata(str(model)) == [] and (model / METADATA_NAME).stat().st_mtime_ns == stamp


def test_a_minutes_budget_that_ends_before_training_is_said(tiny_scene, tmp_path, capsys, record_property):
    """A minutes budget spent before many steps (a busy machine's plane sweep had taken a whole
    minute, and the model "finished" at 0 steps) ends with a warning that says what to do; a
    steps budget asked that small does not."""
    out = tmp_path / "short"
    assert main(["train", str(tiny_scene), "--out", str(out), "--minutes", "0.0005", "--batch-size", "256",
                 "--progress", "json"]) == 0
    events = [json.loads(line) for line in capsys.readouterr().out.splitlines() if line.startswith("{")]
    said = [e for e in events if e.get("barely_trained")]
    meta = json.loads((out / METADATA_NAME).read_text())
    steps = meta["progress"]["step"]
    assert steps < 200 and meta["sweep_seconds"] > 0, meta["progress"]
    assert len(said) == 1 and said[0]["event"] == "warning", said
    message = said[0]["message"]
    record_property("message", f"warning: {message}")
    assert message.startswith(f"the 0.0005-minute budget ended after only {steps} steps ("), message
    assert "s of it went to the plane sweep of the photos" in message
    assert "Train it further: --resume with a larger --minutes" in message

    assert main(["train", str(tiny_scene), "--out", str(tmp_path / "steps"), "--steps", "2", "--batch-size", "256",
                 "--progress", "json"]) == 0
    assert "barely_trained" not in capsys.readouterr().out


def test_a_size_search_candidate_short_by_design_is_not_said_barely_trained():
    from neulf_core.autosize import _rescaled

    seen = []
    warning = {"event": "warning", "message": "the 0.1-minute budget ended after only 9 steps", "barely_trained": True}
    _rescaled(seen.append, 0.0, 0.5, "x0.5")(warning)  # a candidate's
    _rescaled(seen.append, 0.5, 0.5, None)(warning)    # the model's own run
    assert seen == [warning]

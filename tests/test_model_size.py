"""Small model files (model.pt: 8-bit feature grids, float16 and float32 weights), the faster DisparityField forward, and the `auto`
preset's size search, on the tiny synthetic scene from conftest.py."""

from __future__ import annotations

import inspect
import json
import os
import shutil

import numpy as np
import pytest
import torch

from neulf_core.autosize import Candidate, choose, train_auto, validation_split
from neulf_core.presets import FAST_FIELD
from neulf_core.checkpoint import CHECKPOINT_NAME, METADATA_NAME, MODEL_NAME, load_checkpoint, render_path
from neulf_core.cli import main
from neulf_core.errors import NeulfError
from neulf_core.fields import build_field, make_config
from neulf_core.render import LightField
from neulf_core.scene import load_scene
from neulf_core.train import TrainConfig, train


def fast_config(steps: int, **overrides) -> TrainConfig:
    options = dict(preset="fast", steps=steps, batch_size=256, validate_seconds=1e9, checkpoint_seconds=1e9)
    options.update(overrides)
    return TrainConfig(**options)


@pytest.fixture(scope="module")
def fast_model(tiny_scene, tmp_path_factory):
    model_dir = tmp_path_factory.mktemp("fast") / "model"
    train(tiny_scene, model_dir, fast_config(30))
    return tiny_scene, model_dir


def test_model_file_holds_8_bit_grids_and_renders_like_the_checkpoint(fast_model):
    scene_dir, model_dir = fast_model
    small, full = model_dir / MODEL_NAME, model_dir / CHECKPOINT_NAME
    assert render_path(model_dir) == small
    payload = torch.load(small, map_location="cpu", weights_only=False)
    assert "optimizer" not in payload and "rng" not in payload
    texture = payload["grids"]["textures.0"]
    assert texture["codes"].dtype == torch.uint8 and texture["step"].shape == (1, texture["codes"].shape[1], 1, 1)
    assert "textures.0" not in payload["state_dict"]
    assert payload["state_dict"]["decoder.0.weight"].dtype == torch.float32  # small tensors stay float32
    float32_bytes = sum(t.numel() * 4 for t in load_checkpoint(model_dir)["state_dict"].values())
    # (under 0.35 before the coarser geometry planes: this 8-photo scene's grids are
    # now a smaller share of its model, and its small tensors stay float32)
    assert small.stat().st_size < 0.5 * float32_bytes < full.stat().st_size

    view = load_scene(scene_dir).view("view_00.png")
    half = LightField.load(model_dir, "cpu").render_view(view)
    single = LightField.load(full, "cpu").render_view(view)
    assert np.abs(half.rgb - single.rgb).max() < 2e-3
    np.testing.assert_allclose(half.depth, single.depth, rtol=1e-3)


def test_a_newer_checkpoint_wins_and_resume_needs_it(fast_model, tmp_path):
    scene_dir, model_dir = fast_model
    model = tmp_path / "model"
    shutil.copytree(model_dir, model)
    full = model / CHECKPOINT_NAME
    later = (model / MODEL_NAME).stat().st_mtime_ns + 10**9
    os.utime(full, ns=(later, later))  # as after a crash between the two writes
    assert render_path(model) == full
    (model / CHECKPOINT_NAME).unlink()
    assert render_path(model) == model / MODEL_NAME
    LightField.load(model, "cpu")  # the small file alone renders
    with pytest.raises(NeulfError, match="render-only"):
        load_checkpoint(model / MODEL_NAME)


def test_geometry_features_match_the_planes_field():
    """The batched DisparityField geometry sampling equals PlanesField.features (values and
    gradients), so rendering and training see the same field as before."""
    torch.manual_seed(0)
    field = build_field("disparity", make_config("disparity", {"texture_size": [20, 30]}))
    with torch.no_grad():
        for plane in field.geometry.scales.parameters():
            plane.add_(torch.rand_like(plane) * 0.5)
    uvst = torch.rand(500, 4) * 2.2 - 1.1
    fast = field._geometry_features(uvst)
    reference = field.geometry.features(uvst)
    torch.testing.assert_close(fast, reference, rtol=1e-5, atol=1e-6)
    grads = [torch.autograd.grad(f.square().sum(), list(field.geometry.scales.parameters())) for f in (fast, reference)]
    for a, b in zip(*grads):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-6)


# ----------------------------------------------------------------------------- auto


def test_choose_takes_the_smallest_within_tolerance():
    candidates = [Candidate(1.0, {}, val_psnr=30.0, model_bytes=300), Candidate(0.7, {}, val_psnr=29.8, model_bytes=200),
                  Candidate(0.5, {}, val_psnr=29.6, model_bytes=100)]
    assert choose(candidates, 0.3).factor == 0.7
    assert choose(candidates, 0.5).factor == 0.5
    assert choose(candidates, 0.0).factor == 1.0


def test_validation_views_come_from_the_training_views(tiny_scene):
    fit, validation, held = validation_split(load_scene(tiny_scene), TrainConfig())
    names = lambda views: {v.name for v in views}  # noqa: E731
    assert names(held) == {"view_00.png", "view_08.png"} and names(validation) == {"view_01.png"}
    assert not names(fit) & (names(held) | names(validation)) and len(fit) == 6


@pytest.mark.parametrize("tolerance", [100.0, 0.0])
def test_auto_picks_the_smallest_candidate_within_tolerance(tiny_scene, tmp_path, tolerance, monkeypatch):
    """Real short trainings: the recorded choice follows the rule for the PSNRs it measured.
    The candidates, which train on the same photos, build their rays once."""
    from neulf_core import dataset

    built, build = [], dataset.build_rayset
    monkeypatch.setattr(dataset, "build_rayset", lambda views, *a, **k: built.append(len(views)) or build(views, *a, **k))
    events = []
    result = train_auto(tiny_scene, tmp_path / "auto", fast_config(90, preset="auto"), progress=events.append,
                        tolerance_db=tolerance)
    assert result.status == "finished"
    record = load_checkpoint(tmp_path / "auto")["autosize"]
    candidates = [Candidate(**c) for c in record["candidates"]]
    assert [c.factor for c in candidates] == [1.0, 0.7, 0.5] and all(c.steps == 12 for c in candidates)
    assert [c.model_bytes for c in candidates] == sorted((c.model_bytes for c in candidates), reverse=True)
    largest = candidates[0].val_psnr
    within = [c for c in candidates if c.val_psnr >= largest - tolerance]
    assert record["chosen"]["factor"] == min(within, key=lambda c: c.model_bytes).factor
    if tolerance == 100.0:
        assert record["chosen"]["factor"] == 0.5
    assert record["validation_views"] == ["view_01.png"]
    meta = json.loads((tmp_path / "auto" / METADATA_NAME).read_text())
    assert meta["autosize"]["chosen"] == record["chosen"]
    assert meta["field_config"]["texture_size"] == record["chosen"]["overrides"]["texture_size"]
    assert meta["progress"]["step"] == 90 - 3 * 12 and meta["scene"]["held_out"] == ["view_00.png", "view_08.png"]
    assert [e["stage"] for e in events if e["event"] == "autosize"] == ["candidate"] * 3 + ["chosen"]
    assert [e["event"] for e in events].count("finished") == 1
    assert all(e.get("val_psnr") is None for e in events if e.get("candidate"))  # no test-view PSNR leaks
    fractions = [e["fraction"] for e in events if "fraction" in e]
    assert fractions == sorted(fractions) and fractions[-1] == pytest.approx(1.0)
    assert built == [6, 3, 7, 2]  # the candidates' training and held-out rays, then the model's


def test_auto_with_a_time_budget_gives_every_candidate_the_same_steps(tiny_scene, tmp_path):
    train_auto(tiny_scene, tmp_path / "auto", fast_config(None, preset="auto", minutes=0.05))
    record = load_checkpoint(tmp_path / "auto")["autosize"]
    steps = [c["steps"] for c in record["candidates"]]
    assert steps[0] >= 1 and steps == [steps[0]] * 3


def test_a_time_budget_counts_the_time_before_the_search(tiny_scene, tmp_path, monkeypatch):
    """The photos' loading and the rules' decisions come out of the search's share: the first
    candidate gets the share's even part less the time they took (a quarter of it at least), so
    the model keeps the rest of the minutes."""
    import time

    from neulf_core import autosize

    config = fast_config(None, preset="auto", minutes=1.5)
    even = 1.5 * autosize.SEARCH_SHARE / 3
    assert autosize._first_candidate_minutes(config, 3, time.monotonic()) == pytest.approx(even, rel=1e-3)
    assert autosize._first_candidate_minutes(config, 3, time.monotonic() - 6) == pytest.approx(even - 2 / 60, rel=1e-3)
    assert autosize._first_candidate_minutes(config, 3, time.monotonic() - 600) == pytest.approx(even / 4)
    loading, budgets = autosize.load_scene, []
    monkeypatch.setattr(autosize, "load_scene", lambda *a, **k: (time.sleep(1.5), loading(*a, **k))[1])
    monkeypatch.setattr(autosize, "candidate_config", lambda c, cand, budget, views: (
        budgets.append(budget), autosize.replace(c, **budget, exclude=[v.name for v in views],
                                                 field_overrides=cand.overrides, teacher=False))[1])
    train_auto(tiny_scene, tmp_path / "auto", fast_config(None, preset="auto", minutes=0.2))
    assert budgets[0]["minutes"] < (0.2 * autosize.SEARCH_SHARE - 1.5 / 60) / 3 + 1e-9
    assert [b["steps"] for b in budgets[1:]] == [budgets[1]["steps"]] * 2  # the rest train the first's steps


def test_cli_trains_and_resumes_auto(tiny_scene, tmp_path, capsys):
    out = tmp_path / "m"
    base = ["train", str(tiny_scene), "--out", str(out), "--preset", "auto", "--batch-size", "256", "--progress", "json"]
    assert main(base + ["--steps", "30"]) == 0
    chosen = load_checkpoint(out)["autosize"]["chosen"]
    assert main(base + ["--steps", "40", "--resume"]) == 0
    saved = load_checkpoint(out)
    # (the final model's share of the new budget: the search's steps taken off, as a run of 40 never stopped)
    searched = sum(c["steps"] for c in saved["autosize"]["candidates"])
    assert saved["autosize"]["chosen"] == chosen and saved["progress"]["step"] == 40 - searched
    LightField.load(out, "cpu").render_view(load_scene(tiny_scene).view("view_00.png"))


@pytest.mark.parametrize("extras", [{}, {"geometry_layers": 8, "back_surface": True}], ids=["plain", "rules' extras"])
@pytest.mark.parametrize("image_size", [(480, 270), (504, 378), (1008, 567), (1920, 1080), (4032, 3024)])
def test_default_model_weights_stay_under_3_mb_at_any_training_resolution(image_size, extras):
    """The default field's texture follows the training images up to a texel budget, so the
    weights of model.pt stay under the 3 MB target however large the photos: a member's under
    1.6 MB with what the rules add (8 depth layers, the back surface), so that a model of two
    members (the CPU default from 12 passes) holds at most 3.2 MB."""
    from neulf_core.checkpoint import compact_state_dict
    from neulf_core.fields.disparity import MAX_TEXELS, texture_size_for
    from neulf_core.presets import get_preset

    rows, cols = texture_size_for(image_size)
    assert rows * cols <= MAX_TEXELS * 1.01
    assert abs(cols / rows - image_size[0] / image_size[1]) < 0.02  # the image's aspect is kept
    options = {**get_preset("fast").field_config, "texture_size": [rows, cols], **extras}
    field = build_field("disparity", make_config("disparity", options))
    dense, grids = compact_state_dict(field.state_dict())
    tensors = [*dense.values(), *(t for grid in grids.values() for t in grid.values())]
    assert sum(t.numel() * t.element_size() for t in tensors) < 1.6e6
    if image_size == (480, 270):  # small photos keep about one texel per pixel
        assert [rows, cols] == [338, 600]


def test_a_damaged_8_bit_grid_gives_a_clear_message(fast_model, tmp_path):
    _, model_dir = fast_model
    model = tmp_path / "model"
    shutil.copytree(model_dir, model)
    payload = torch.load(model / MODEL_NAME, map_location="cpu", weights_only=False)
    del payload["grids"]["textures.0"]["step"]
    torch.save(payload, model / MODEL_NAME)
    os.utime(model / MODEL_NAME)  # still the newer file, so rendering reads it
    with pytest.raises(NeulfError, match="damaged"):
        LightField.load(model, "cpu")


def test_half_precision_keeps_tensors_float16_would_overflow():
    """model.pt keeps large float tensors as float16, except one float16 would turn to inf (a
    value past 65504): it stays float32, as do small and integer tensors."""
    from neulf_core.checkpoint import HALF_MIN_ELEMENTS, half_state_dict

    large = torch.linspace(-1, 1, HALF_MIN_ELEMENTS)
    out = half_state_dict({"plain": large, "huge": large * 1e5, "small": torch.ones(3), "ints": torch.arange(HALF_MIN_ELEMENTS)})
    assert out["plain"].dtype == torch.float16 and out["huge"].dtype == torch.float32
    assert out["small"].dtype == torch.float32 and out["ints"].dtype == torch.int64
    assert torch.equal(out["huge"], large * 1e5)


def test_8_bit_grids_round_trip_within_half_a_step_per_channel():
    from neulf_core.checkpoint import compact_state_dict, dequantise_grid
    grid = torch.randn(2, 3, 17, 9) * torch.tensor([0.01, 1.0, 100.0]).view(1, 3, 1, 1)
    dense, grids = compact_state_dict({"grid": grid, "matrix": torch.randn(128, 64), "bias": torch.randn(5)})
    assert set(grids) == {"grid"} and dense["matrix"].dtype == torch.float16 and dense["bias"].dtype == torch.float32
    step = grids["grid"]["step"]
    assert step.shape == (2, 3, 1, 1)  # one step per channel: a small channel keeps its precision
    assert bool(((dequantise_grid(grids["grid"]) - grid).abs() <= step / 2 + 1e-6).all())


@pytest.mark.parametrize("max_views, expected", [(13, True), (6, False)])
def test_auto_decides_the_losses_once_for_its_search_and_its_model(tiny_scene, tmp_path, monkeypatch, max_views, expected):
    """The search runs train on fewer views (the validation view is carved out): with the
    rule's threshold between the two counts they must still train as the final model does."""
    import neulf_core.train as train_module
    import neulf_core.rules as rules_module

    monkeypatch.setattr(rules_module, "CONSISTENCY_MAX_VIEWS", max_views)  # 7 training views, 6 in the search
    monkeypatch.setattr(rules_module, "LOSSES_MIN_PASSES", 0.0)  # 12 steps of a tiny scene: the budget rule aside
    calls = []
    real = train_module.multiview_losses
    monkeypatch.setattr(train_module, "multiview_losses", lambda *a, **k: calls.append(1) or real(*a, **k))
    events = []
    train_auto(tiny_scene, tmp_path / "auto", fast_config(12, preset="auto", near=1.0, far=6.0, consistency_rays=32,
                                                         teacher=False), progress=events.append)
    assert len(calls) == (12 if expected else 0)  # every step of the 3 candidates and of the final run, or none
    assert [e["event"] for e in events].count("losses") == (1 if expected else 0)
    assert json.loads((tmp_path / "auto" / METADATA_NAME).read_text())["multiview_losses"] is expected


@pytest.mark.parametrize("rate, expected", [(None, True), (0.0, False)])
def test_auto_with_a_time_budget_decides_the_losses_once_at_the_measured_rate(tiny_scene, tmp_path, monkeypatch,
                                                                              rate, expected):
    """A minutes budget: the step rate is measured once, before the search, and the losses'
    verdict at that rate holds for every candidate and the final model."""
    import neulf_core.autosize as autosize_module
    import neulf_core.rules as rules_module

    monkeypatch.setattr(rules_module, "LOSSES_MIN_PASSES", 1e-9)
    measured = []
    real_rate = autosize_module._steps_per_minute

    def rate_probe(*args):
        measured.append(real_rate(*args) if rate is None else rate)
        return measured[-1]

    monkeypatch.setattr(autosize_module, "_steps_per_minute", rate_probe)
    runs = []
    real_train = autosize_module.train
    monkeypatch.setattr(autosize_module, "train", lambda scene, folder, config, **k: runs.append(config.consistency)
                        or real_train(scene, folder, config, **k))
    train_auto(tiny_scene, tmp_path / "auto", fast_config(None, preset="auto", minutes=0.05, near=1.0, far=6.0,
                                                         consistency_rays=32, teacher=False))
    assert len(measured) == 1 and measured[0] >= 0
    probe = [None] if rate is None else []  # the measuring run leaves the losses to the default
    assert runs == probe + [expected] * 4  # then the 3 candidates and the final run
    assert json.loads((tmp_path / "auto" / METADATA_NAME).read_text())["multiview_losses"] is expected


def test_auto_rate_probe_that_cannot_measure_counts_no_steps(tiny_scene, monkeypatch):
    """A probe whose run ends before the rate is measured says 0 steps a minute (the losses
    then stay off), not a missing key."""
    import neulf_core.autosize as autosize_module
    import neulf_core.rules as rules_module

    config = fast_config(None, preset="auto", minutes=0.05, near=1.0, far=6.0, teacher=False)
    assert autosize_module._steps_per_minute(tiny_scene, config) > 0
    monkeypatch.setattr(rules_module, "LOSSES_DECISION_STEP", 10_000)  # never reached in the probe's steps
    assert autosize_module._steps_per_minute(tiny_scene, config) == 0.0


@pytest.mark.parametrize("max_views, expected", [(13, True), (6, False)])
def test_auto_decides_coarse_to_fine_once_for_its_search_and_its_model(tiny_scene, tmp_path, monkeypatch, max_views, expected):
    """As with the losses: 7 training views, 6 in the search runs; with the threshold between
    the two, every run trains as the final model does."""
    import neulf_core.train as train_module
    import neulf_core.rules as rules_module

    monkeypatch.setattr(rules_module, "COARSE_TO_FINE_MAX_VIEWS", max_views)
    ramps, surfaces = [], []
    real = train_module._build_field
    signature = inspect.signature(real)

    def recording(*args, **kwargs):
        asked = signature.bind(*args, **kwargs).arguments
        ramps.append(asked.get("coarse_to_fine"))
        surfaces.append(asked.get("back_surface"))
        return real(*args, **kwargs)

    monkeypatch.setattr(train_module, "_build_field", recording)
    train_auto(tiny_scene, tmp_path / "auto", fast_config(8, preset="auto", teacher=False))
    assert ramps == [expected] * 4  # 3 candidates and the final run
    assert len(set(surfaces)) == 1 and surfaces[0] is not None  # the back surface too: decided once
    config = json.loads((tmp_path / "auto" / METADATA_NAME).read_text())["field_config"]
    assert config["geometry_coarse_to_fine"] == (rules_module.COARSE_TO_FINE if expected else 0.0)


@pytest.mark.parametrize("max_views, expected", [(7, 2), (6, 1)])
def test_auto_decides_the_depth_detail_reads_once_for_its_search_and_its_model(tiny_scene, tmp_path, monkeypatch,
                                                                               max_views, expected):
    """The same for reading the depth detail twice, the geometry's smoothness prior, and
    the pass limit: 7 training views, 6 in the search runs; the decoders learn at the preset's factor."""
    import neulf_core.train as train_module
    import neulf_core.rules as rules_module

    monkeypatch.setattr(rules_module, "FEW_PHOTOS_MAX_VIEWS", max_views)
    reads, passes = [], []
    real = train_module._build_field
    real_limit = rules_module.pass_step_limit
    monkeypatch.setattr(rules_module, "pass_step_limit", lambda config, field, n, *rest: passes.append(
        rules_module.max_passes(config, field, n)) or real_limit(config, field, n, *rest))

    def recording(*args, **kwargs):
        field, preset = real(*args, **kwargs)
        reads.append((field.config.depth_detail_reads, field.config.tv_weight, field.config.decoder_lr_factor,
                      field.config.geometry_spatial_res))  # the preset's for any count
        return field, preset

    monkeypatch.setattr(train_module, "_build_field", recording)
    train_auto(tiny_scene, tmp_path / "auto", fast_config(8, preset="auto", teacher=False))
    tv = rules_module.FEW_VIEWS_GEOMETRY_TV if expected == 2 else 1e-3
    scales = FAST_FIELD["geometry_spatial_res"]
    assert reads == [(expected, tv, FAST_FIELD["decoder_lr_factor"], scales)] * 4  # 3 candidates and the final run
    assert passes == [rules_module.FEW_PHOTOS_MAX_PASSES if expected == 2 else 0.0] * 4
    assert json.loads((tmp_path / "auto" / METADATA_NAME).read_text())["field_config"]["depth_detail_reads"] == expected


def test_auto_is_the_fast_preset_with_its_texture_sized_per_scene():
    """`auto` trains what `fast` trains (the sweep teacher, the pose check, the SfM points' pull)
    and only sizes the texture: it was left without the teacher once, when `fast` gained it."""
    from dataclasses import asdict

    from neulf_core.presets import get_preset

    fast, auto = asdict(get_preset("fast")), asdict(get_preset("auto"))
    assert {key: value for key, value in fast.items() if auto[key] != value} == {"description": fast["description"]}


def test_auto_searches_the_size_without_the_sweep_teacher_and_trains_the_model_with_it(tiny_scene, tmp_path,
                                                                                      monkeypatch):
    """The teacher's early pull evens short candidates out (CanClip's search then picked the
    smallest texture and lost 1.5 dB): the candidates train without it, the model as `fast` does."""
    import neulf_core.autosize as autosize

    teachers, real_train = [], autosize.train

    def recording_train(scene, folder, config, **kwargs):
        teachers.append(config.teacher)
        return real_train(scene, folder, config, **kwargs)

    monkeypatch.setattr(autosize, "train", recording_train)
    events = []
    train_auto(tiny_scene, tmp_path / "auto", fast_config(30, preset="auto"), progress=events.append)
    assert teachers == [False, False, False, None]  # three candidates, then the model (None: the preset's, on)
    assert any(e.get("message", "").startswith("sweep depth of") for e in events)  # the model's sweep ran

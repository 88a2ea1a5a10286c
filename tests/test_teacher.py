"""The classic plane sweep as a depth teacher: its depth per training ray matches the true
surface, and training with it counts the sweep in the budget and resumes."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from conftest import plane_hit
from neulf_core.dataset import build_rayset
from neulf_core.render import LightField
from neulf_core.rays import view_rays
from neulf_core.scene import load_scene, split_views
from neulf_core.slab import fit_slab
from neulf_core import dataset, memo, teacher
from neulf_core.teacher import (TEACHER_FADE, TEACHER_FADE_FEW, TEACHER_FEW_VIEWS, TEACHER_FULL_VIEWS, sweep_depth_targets,
                                teacher_fade, teacher_weight)
from neulf_core.train import TrainConfig, train


def _true_units(views, slab, scale: float) -> torch.Tensor:
    """The slanted plane's slab-axis depth per ray (build_rayset's order), as a unit."""
    units = []
    for view in views:
        camera = view.scaled_camera(scale)
        origin, directions = view_rays(camera, view.R, view.t)
        uvst, valid = slab.rays_to_uvst(torch.from_numpy(origin), torch.from_numpy(directions))
        depth = slab.to_slab(plane_hit(origin, directions))[:, 2]
        units.append(slab.unit_from_depth(torch.from_numpy(depth))[valid.numpy()])
    return torch.cat(units).float()


def test_sweep_depth_per_training_ray_matches_the_surface(tiny_scene):
    scene = load_scene(tiny_scene)
    views, _ = split_views(scene, holdout_every=0)
    slab = fit_slab(scene, views)
    units, confidence = sweep_depth_targets(views, slab, 1.0)
    assert units.shape == confidence.shape == (len(build_rayset(views, slab, 1.0)),)
    assert float(confidence.min()) >= 0 and float(confidence.max()) <= 1
    error = (units - _true_units(views, slab, 1.0)).abs()
    trusted = confidence > 0.5
    assert float(trusted.float().mean()) > 0.3
    # 32 planes: one plane step is 1/31 of the unit range.
    assert float(error[trusted].median()) < 1.5 / 31, float(error[trusted].median())


def test_the_same_photos_are_swept_once_and_other_poses_again(tiny_scene, monkeypatch):
    """A model's members and the better of two starts sweep the same photos: within a training
    call the second sweep gets the first one's result (copies, so a change to one leaves the kept
    result alone); a photo's pose moved, or another scale, sweeps again."""
    scene = load_scene(tiny_scene)
    views, _ = split_views(scene, holdout_every=0)
    slab = fit_slab(scene, views)
    sweeps = []
    original = teacher.compute_sweep_depth_targets
    monkeypatch.setattr(teacher, "compute_sweep_depth_targets", lambda *a, **k: sweeps.append(1) or original(*a, **k))
    with memo.kept_while_training():  # (what a training call holds)
        first = sweep_depth_targets(views, slab, 1.0)
        first[0].zero_()
        again = sweep_depth_targets(views, slab, 1.0)
        fresh = original(views, slab, 1.0)
        assert len(sweeps) == 1 and torch.equal(again[0], fresh[0]) and torch.equal(again[1], fresh[1])
        moved = [replace(views[0], t=views[0].t + 1e-3)] + views[1:]
        sweep_depth_targets(moved, slab, 1.0)
        sweep_depth_targets(moved, slab, 0.5)
        assert len(sweeps) == 3 and memo._entries
    assert not memo._entries  # let go when the training call ends
    sweep_depth_targets(views, slab, 1.0)
    sweep_depth_targets(views, slab, 1.0)
    assert len(sweeps) == 5  # (outside one, each call sweeps)


def test_two_members_sweep_and_read_the_photos_once_and_train_as_each_would_alone(tiny_scene, tmp_path, monkeypatch):
    from conftest import assert_same_weights
    from neulf_core.members import MEMBER_SEED_OFFSET, member_dir

    sweeps, rays = [], []
    original = teacher.compute_sweep_depth_targets
    monkeypatch.setattr(teacher, "compute_sweep_depth_targets", lambda *a, **k: sweeps.append(1) or original(*a, **k))
    build = dataset.build_rayset
    monkeypatch.setattr(dataset, "build_rayset", lambda views, *a, **k: rays.append(len(views)) or build(views, *a, **k))
    options = dict(batch_size=256, teacher=True, two_starts=False, refine_poses=False, validate_seconds=1e9,
                   checkpoint_seconds=1e9)
    events = []
    train(tiny_scene, tmp_path / "m", TrainConfig(steps=20, members=2, seed=4, **options), progress=events.append)
    assert len(sweeps) == 1 and any(e.get("member") == 2 for e in events)
    assert len(rays) == 2  # the training views' rays and the held-out views', for both members
    # The second member, on the first one's sweep and rays, is the run its seed and share give
    # alone (on a CPU the default's share: all the steps with half the batch).
    train(tiny_scene, tmp_path / "alone", TrainConfig(steps=20, members=1, seed=4 + MEMBER_SEED_OFFSET,
                                                      **{**options, "batch_size": 128}))
    assert len(sweeps) == 2 and len(rays) == 4
    assert_same_weights(member_dir(tmp_path / "m", 2), tmp_path / "alone")


def test_the_same_photos_are_read_once_and_other_poses_again(tiny_scene):
    """Within a training call a second request for the same views' rays gets the first set
    and its masks without reading a photo; a moved pose, another scale or pixel steps build
    again; outside a training call every request builds."""
    scene = load_scene(tiny_scene)
    views, _ = split_views(scene, holdout_every=0)
    slab = fit_slab(scene, views)
    with memo.kept_while_training():
        first_masks, again_masks = [], []
        first = dataset.kept_rayset("rays", views, slab, 1.0, masks=first_masks)
        again = dataset.kept_rayset("rays", views, slab, 1.0, masks=again_masks)
        assert again is first and len(again_masks) == len(views)
        assert all(a is b for a, b in zip(first_masks, again_masks))
        fresh = build_rayset(views, slab, 1.0)
        assert torch.equal(first.uvst, fresh.uvst) and torch.equal(first.rgb, fresh.rgb)
        moved = [replace(views[0], t=views[0].t + 1e-3)] + views[1:]
        assert dataset.kept_rayset("rays", moved, slab, 1.0) is not first
        for other in (dict(scale=0.5), dict(scale=1.0, pixel_steps=True)):
            assert dataset.kept_rayset("rays", views, slab, **other) is not first
    assert dataset.kept_rayset("rays", views, slab, 1.0) is not dataset.kept_rayset("rays", views, slab, 1.0)


def test_the_sweep_on_photos_read_with_the_rays_is_the_sweep_that_reads_them(tiny_scene):
    """build_rayset's photos at the sweep's scale (one decode for both sizes) give the sweep
    exactly the targets it computes reading the photos itself."""
    scene = load_scene(tiny_scene)
    views, _ = split_views(scene)
    slab = fit_slab(scene, views)
    masks, photos = [], []
    small = teacher.sweep_photo_scale(views, 1.0, slab)
    build_rayset(views, slab, 1.0, masks=masks, photos_at=small, photos=photos)
    assert [p.shape[:2] for p in photos] == [v.load_image(small).shape[:2] for v in views]
    given = teacher.compute_sweep_depth_targets(views, slab, 1.0, representable=masks, photos=photos)
    read = teacher.compute_sweep_depth_targets(views, slab, 1.0, representable=masks)
    assert torch.equal(given[0], read[0]) and torch.equal(given[1], read[1])


def test_the_pull_fades_out_halfway():
    assert teacher_weight(0.0) > teacher_weight(TEACHER_FADE / 2) > 0
    assert teacher_weight(TEACHER_FADE) == 0 and teacher_weight(1.0) == 0


def test_the_pull_strengthens_for_sparse_captures_only():
    assert teacher_weight(0.0, 4) == pytest.approx(teacher_weight(0.0) * TEACHER_FULL_VIEWS / 4)
    assert teacher_weight(0.0, TEACHER_FULL_VIEWS) == teacher_weight(0.0, 80) == teacher_weight(0.0)
    assert teacher_weight(TEACHER_FADE_FEW, 4) == 0


def test_the_pull_lasts_longer_for_the_fewest_photos():
    assert TEACHER_FADE_FEW > TEACHER_FADE
    few, more = TEACHER_FEW_VIEWS, TEACHER_FEW_VIEWS + 1
    assert teacher_fade(few) == TEACHER_FADE_FEW and teacher_fade(2) == TEACHER_FADE_FEW
    assert teacher_fade(more) == teacher_fade(80) == TEACHER_FADE
    assert teacher_weight(TEACHER_FADE, few) > 0 and teacher_weight(TEACHER_FADE, more) == 0
    for strong in (False, True):  # halfway through its own fade, either pull is at half its start
        assert teacher_weight(TEACHER_FADE_FEW / 2, few, strong) == pytest.approx(teacher_weight(0.0, few, strong) / 2)


def test_a_resumed_run_sweeps_again_while_its_own_fade_lasts(tiny_scene, tmp_path, monkeypatch):
    """Resumed at a third of its budget, a run of at most TEACHER_FEW_VIEWS photos is still in
    its pull's part of the budget and sweeps again; one with more photos is past it."""
    monkeypatch.setattr(teacher, "SWEEP_SCALE", 1.0)
    names = sorted(p.name for p in (tiny_scene / "images").iterdir())
    for kept, sweeps in ((TEACHER_FEW_VIEWS, True), (TEACHER_FEW_VIEWS + 1, False)):
        exclude = names[kept:]  # the last views: the held-out rule then leaves `kept` to train on
        out, events = tmp_path / f"m{kept}", []
        options = dict(batch_size=256, teacher=True, exclude=exclude, validate_seconds=1e9, checkpoint_seconds=1e9)
        train(tiny_scene, out, TrainConfig(steps=10, **options))
        train(tiny_scene, out, TrainConfig(steps=30, **options), resume=True, progress=events.append)
        swept = [e for e in events if "sweep depth of" in e.get("message", "")]
        assert bool(swept) == sweeps, kept
        if swept:
            assert swept[-1]["total"] == kept


def test_the_strong_pull_unless_dense_or_exposures_differ():
    from neulf_core.teacher import TEACHER_WEIGHT_STRONG, strong_pull

    assert teacher_weight(0.0, 17, strong=True) == TEACHER_WEIGHT_STRONG > 10 * teacher_weight(0.0, 17)
    assert teacher_weight(0.0, 2, strong=True) == TEACHER_WEIGHT_STRONG >= teacher_weight(0.0, 2)
    assert teacher_weight(TEACHER_FADE, 17, strong=True) == 0
    from neulf_core.teacher import TEACHER_DENSE_VIEWS

    # CanClip (26 views), Statue (23), fern (17), a 6-view capture: strong; HCI (71): gentle.
    assert all(strong_pull(n, appearance=False) for n in (6, 17, 23, 26, TEACHER_DENSE_VIEWS - 1))
    assert not strong_pull(TEACHER_DENSE_VIEWS, appearance=False) and not strong_pull(71, appearance=False)
    assert not strong_pull(6, appearance=True) and not strong_pull(26, appearance=True)


def test_training_takes_the_pull_its_photos_allow(tiny_scene, tmp_path, monkeypatch):
    """The trainer asks for the strong pull unless --appearance is on."""
    import neulf_core.train as train_module

    asked = []
    real = train_module.teacher_weight
    monkeypatch.setattr(train_module, "teacher_weight", lambda f, n, strong: asked.append(strong) or real(f, n, strong))
    monkeypatch.setattr(teacher, "SWEEP_SCALE", 1.0)
    for appearance in (False, True):
        asked.clear()
        train(tiny_scene, tmp_path / f"m{appearance}", TrainConfig(steps=2, batch_size=256, teacher=True, appearance=appearance,
                                                                   validate_seconds=1e9, checkpoint_seconds=1e9))
        assert asked and set(asked) == {not appearance}


def test_training_with_the_teacher_learns_the_depth_and_resumes(tiny_scene, tmp_path, monkeypatch):
    # A stronger pull than the default's gentle one, so 120 steps show it (the default's
    # effect at full budgets is measured in docs/DEPTH.md).
    monkeypatch.setattr(teacher, "TEACHER_WEIGHT", 0.05)
    monkeypatch.setattr(teacher, "TEACHER_FULL_VIEWS", 1)  # this weight as it is, whatever the view count
    monkeypatch.setattr(teacher, "SWEEP_SCALE", 1.0)  # the tiny scene's images are tiny already
    events = []
    config = TrainConfig(steps=120, teacher=True, validate_seconds=1e9, checkpoint_seconds=1e9, members=1)
    result = train(tiny_scene, tmp_path / "m", config, progress=events.append)
    assert result.status == "finished"
    assert any("sweep depth of" in e.get("message", "") for e in events)
    scene = load_scene(tiny_scene)
    views, _ = split_views(scene)
    field = LightField.load(tmp_path / "m", "cpu")
    rays = build_rayset(views, field.slab, 1.0)
    with torch.no_grad():
        _, unit = field.field(rays.uvst)
    error = (unit.reshape(-1) - _true_units(views, field.slab, 1.0)).abs()
    # Without the teacher the median error at this step count is 0.045; with it, 0.038 (the
    # default field's 4 geometry channels; with 8: 0.047 and 0.029).
    assert float(error.median()) < 0.042, float(error.median())
    # Past the teacher's part of the budget a resumed run does not sweep again.
    events.clear()
    train(tiny_scene, tmp_path / "m", TrainConfig(steps=150, teacher=True, validate_seconds=1e9), resume=True,
          progress=events.append)
    assert not any("sweep depth of" in e.get("message", "") for e in events)


def test_cli_flag_turns_the_teacher_off_and_it_is_remembered(tiny_scene, tmp_path, capsys):
    from neulf_core.checkpoint import load_checkpoint
    from neulf_core.cli import main

    out = tmp_path / "m"
    base = ["train", str(tiny_scene), "--out", str(out), "--batch-size", "256", "--progress", "json"]
    assert main(base + ["--steps", "10", "--no-sweep-teacher"]) == 0
    assert "sweep depth of" not in capsys.readouterr().out
    assert load_checkpoint(out)["train_config"]["teacher"] is False
    assert main(["train", str(tiny_scene), "--out", str(tmp_path / "default"), "--steps", "5", "--progress", "json"]) == 0
    assert "sweep depth of" in capsys.readouterr().out  # on by default for the fast preset


def test_a_deep_scenes_sweep_keeps_to_its_pixel_budget(tiny_scene):
    from neulf_core.scene import load_scene
    from neulf_core.slab import Slab
    from neulf_core.teacher import DEEP_SWEEP_PIXELS, SWEEP_SCALE, sweep_scale_for

    views = load_scene(tiny_scene).views
    width, height = views[0].size

    def slab(near, far):
        return Slab(np.eye(3), np.zeros(3), 0.0, (near + far) / 2, near, far, -np.ones(4), np.ones(4))

    assert sweep_scale_for(views, 1.0, slab(10.0, 20.0)) == SWEEP_SCALE  # shallow: half resolution
    for scale in (1.0, 4.0, 16.0):
        fraction = sweep_scale_for(views, scale, slab(10.0, 50.0))
        assert fraction <= SWEEP_SCALE
        assert (width * scale * fraction) * (height * scale * fraction) <= DEEP_SWEEP_PIXELS * 1.01 or fraction == SWEEP_SCALE

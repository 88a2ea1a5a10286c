"""Members (neulf_core/members.py): light fields trained apart and rendered as the mean of
their colours -- each member is exactly the run its seed and budget share would give alone,
the render is their mean, and a stop at any point resumes."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from conftest import assert_same_weights
from neulf_core.errors import NeulfError
from neulf_core.members import (MEMBER_SEED_OFFSET, MEMBERS_DIR, STATE_NAME, finished_members, member_budget,
                                member_dir)
from neulf_core.render import LightField
from neulf_core.scene import load_scene, split_views
from neulf_core.train import TrainConfig, train


def config(steps=None, **overrides) -> TrainConfig:
    """A small run; members split the steps unless a test says otherwise (members_split=None: the
    default's split, the batch on a CPU)."""
    options = dict(preset="fast", steps=steps, batch_size=512, field_overrides={"texture_size": [16, 16]},
                   validate_seconds=1e9, checkpoint_seconds=1e9, teacher=False, refine_poses=False, two_starts=False,
                   members_split="steps")
    options.update(overrides)
    return TrainConfig(**options)


def run(scene, folder, cfg, resume=False, stop_when=None):
    events = []
    result = train(scene, folder, cfg, resume=resume, progress=events.append,
                   should_stop=(lambda: stop_when(events)) if stop_when else None)
    return result, events


def test_what_blender_imports_loads_without_torch():
    """members and model_files are what the Blender layer imports, where torch may be missing."""
    import subprocess
    import sys

    code = "import sys, neulf_core.members, neulf_core.model_files; assert 'torch' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True, cwd=Path(__file__).resolve().parents[1])


def test_the_budget_is_shared():
    assert member_budget(config(steps=101), 2, 1) == (51, None, 512)
    assert member_budget(config(steps=101), 2, 2) == (50, None, 512)
    assert member_budget(config(minutes=3.0), 3, 2) == (None, 1.0, 512)
    with pytest.raises(NeulfError, match="cannot be shared"):
        member_budget(config(steps=1), 2, 2)
    # ... or by the batch: all the steps each, 1/N of the rays a step (the preset's batch by default)
    assert member_budget(config(steps=101), 2, 2, "batch") == (101, None, 256)
    assert member_budget(config(minutes=3.0), 3, 2, "batch") == (None, 1.0, 170)
    assert member_budget(config(steps=101, batch_size=None), 2, 1, "batch") == (101, None, 4096)


def test_members_that_split_the_batch_are_the_runs_alone_at_any_budget(tiny_scene, tmp_path):
    """--members-split batch: two members by the rule whatever the passes (here about 3), each
    the ordinary run with its seed, all the steps and half the batch; the split is kept in
    members.json, so a resume goes on as the model began, and a bad split is a clear error."""
    from neulf_core.members import member_split, members_by_rule

    from neulf_core.members import BATCH_MEMBERS_PASSES

    # The rule counts passes for members of the batch too, from fewer of them; asked for, two at any budget.
    assert members_by_rule(None, "batch") is None and members_by_rule(BATCH_MEMBERS_PASSES - 1, "batch") == 1
    assert members_by_rule(BATCH_MEMBERS_PASSES, "batch") == 2
    result, events = run(tiny_scene, tmp_path / "ens", config(steps=30, seed=3, members_split="batch"))
    assert result.status == "finished" and finished_members(tmp_path / "ens") == [2]
    assert json.loads((tmp_path / "ens" / STATE_NAME).read_text())["split"] == "batch"
    assert any(e.get("event") == "stage" and "1/2 of the rays" in e.get("message", "") for e in events)
    run(tiny_scene, tmp_path / "a", config(steps=30, seed=3, batch_size=256))
    run(tiny_scene, tmp_path / "b", config(steps=30, seed=3 + MEMBER_SEED_OFFSET, batch_size=256))
    assert_same_weights(tmp_path / "ens", tmp_path / "a")
    assert_same_weights(member_dir(tmp_path / "ens", 2), tmp_path / "b")
    assert member_split(config(), tmp_path / "ens") == "batch"  # the model's own, whatever is asked now
    assert member_split(config(members_split="steps")) == "steps" and member_split(config(members_split="batch")) == "batch"
    # Unasked: the batch on a CPU, the steps on a GPU (members.default_split).
    unasked = config(members_split=None)
    assert member_split(unasked) == "batch" and member_split(unasked, None, "cuda") == "steps"
    assert member_split(unasked, None, "mps") == "steps"
    with pytest.raises(NeulfError, match="--members-split takes steps or batch"):
        member_split(config(members_split="rays"))
    # A minutes budget with the batch split needs no step rate: both members, half the minutes each.
    result, _ = run(tiny_scene, tmp_path / "timed", config(minutes=0.02, members_split="batch"))
    assert result.status == "finished" and finished_members(tmp_path / "timed") == [2]
    budgets = [json.loads((member_dir(tmp_path / "timed", m) / "model.json").read_text())["train_config"]
               for m in (1, 2)]
    assert [(b["minutes"], b["batch_size"]) for b in budgets] == [(0.01, 256), (0.01, 256)]


def test_members_are_the_runs_alone_and_render_as_their_mean(tiny_scene, tmp_path):
    result, events = run(tiny_scene, tmp_path / "ens", config(steps=60, seed=2, members=2))
    assert result.status == "finished" and result.model_dir == tmp_path / "ens"
    assert json.loads((tmp_path / "ens" / STATE_NAME).read_text())["finished"] == [2]
    assert finished_members(tmp_path / "ens") == [2]
    # Each member is the ordinary run with its seed and half the steps.
    run(tiny_scene, tmp_path / "a", config(steps=30, seed=2))
    run(tiny_scene, tmp_path / "b", config(steps=30, seed=2 + MEMBER_SEED_OFFSET))
    assert_same_weights(tmp_path / "ens", tmp_path / "a")
    assert_same_weights(member_dir(tmp_path / "ens", 2), tmp_path / "b")
    assert member_dir(tmp_path / "ens", 2) == tmp_path / "ens" / MEMBERS_DIR / "2"
    # The progress runs once from 0 to 1 over both members, and training ends once.
    fractions = [e["fraction"] for e in events if "fraction" in e]
    assert fractions == sorted(fractions) and fractions[-1] == pytest.approx(1.0)
    assert max(e["fraction"] for e in events if e.get("member") == 1 and "fraction" in e) <= 0.5 + 1e-9
    assert [e["event"] for e in events].count("finished") == 1
    finished = next(e for e in events if e["event"] == "finished")  # the model's, all members together
    assert (finished["step"], finished["model_dir"], finished["val_psnr"]) == (60, str(tmp_path / "ens"), None)
    # The ensemble renders the mean of the members' colours; depth the mean of their disparities.
    scene = load_scene(tiny_scene)
    view = split_views(scene)[1][0]
    both = LightField.load(tmp_path / "ens", "cpu", precision="full")
    one, two = (LightField.load(tmp_path / name, "cpu", precision="full") for name in ("a", "b"))
    assert both.meta["members"] == [1, 2]
    images = [lf.render_view(view, depth=True) for lf in (both, one, two)]
    np.testing.assert_allclose(images[0].rgb, (images[1].rgb + images[2].rgb) / 2, atol=2e-6)
    disparity = [1.0 / r.depth for r in images]
    np.testing.assert_allclose(disparity[0], (disparity[1] + disparity[2]) / 2, rtol=1e-4)
    # Pixel samples go through the same mean.
    # (in every pixel: which pixels take the points follows each render's own centre colours)
    four = [lf.render_view(view, depth=False, pixel_samples=4, sample_contrast=0).rgb for lf in (both, one, two)]
    np.testing.assert_allclose(four[0], (four[1] + four[2]) / 2, atol=2e-6)


def test_a_stop_in_the_second_member_resumes_to_the_same_model(tiny_scene, tmp_path):
    run(tiny_scene, tmp_path / "whole", config(steps=60, seed=1, members=2))

    def in_second_member(events):
        return any(e.get("member") == 2 and e.get("event") == "step" and e["step"] >= 10 for e in events)

    result, _ = run(tiny_scene, tmp_path / "cut", config(steps=60, seed=1, members=2), stop_when=in_second_member)
    assert result.status == "cancelled" and result.model_dir == tmp_path / "cut"
    # Cancelled mid-way, the model renders from the members that finished: the first alone.
    assert finished_members(tmp_path / "cut") == []
    assert "members" not in LightField.load(tmp_path / "cut", "cpu").meta
    # --resume without --members keeps the model's count and finishes the second member.
    result, events = run(tiny_scene, tmp_path / "cut", config(steps=60, seed=1), resume=True)
    assert result.status == "finished" and finished_members(tmp_path / "cut") == [2]
    assert_same_weights(tmp_path / "cut", tmp_path / "whole")
    assert_same_weights(member_dir(tmp_path / "cut", 2), member_dir(tmp_path / "whole", 2))


def test_later_members_train_with_the_first_members_pose_corrections(tiny_scene, tmp_path):
    """Each member refining its own poses would settle the scene in a frame of its own, and
    their mean would blur the two; so the first member's corrections carry over, fixed."""
    cfg = config(steps=60, seed=3, members=2, refine_poses=True)
    run(tiny_scene, tmp_path / "ens", cfg)
    first = json.loads((tmp_path / "ens" / "model.json").read_text())
    second = json.loads((member_dir(tmp_path / "ens", 2) / "model.json").read_text())
    assert first["pose_corrections"]["median_degrees"] > 0
    assert second["poses_from"]["model"] == str(tmp_path / "ens")
    assert second["poses_from"]["median_degrees"] == pytest.approx(first["pose_corrections"]["median_degrees"])
    assert second["train_config"]["refine_poses"] is False and "pose_corrections" not in second
    # The corrections change what the second member learns: not the run its seed gives alone.
    run(tiny_scene, tmp_path / "alone", config(steps=30, seed=3 + MEMBER_SEED_OFFSET, refine_poses=False))
    with pytest.raises(AssertionError):
        assert_same_weights(member_dir(tmp_path / "ens", 2), tmp_path / "alone")
    # A stop in the second member resumes with the same corrections, to the same weights.
    def in_second_member(events):
        return any(e.get("member") == 2 and e.get("event") == "step" and e["step"] >= 10 for e in events)

    result, _ = run(tiny_scene, tmp_path / "cut", cfg, stop_when=in_second_member)
    assert result.status == "cancelled"
    run(tiny_scene, tmp_path / "cut", config(steps=60, seed=3), resume=True)
    assert_same_weights(member_dir(tmp_path / "cut", 2), member_dir(tmp_path / "ens", 2))


def test_later_members_follow_the_first_members_verdict_on_the_poses(tiny_scene, tmp_path, monkeypatch):
    """Where the first member's pose check drops the refinement, the second neither refines nor
    checks its own (a check of its own could refine on a borderline capture, in a frame of its own)."""
    import neulf_core.poses as poses_module

    monkeypatch.setattr(poses_module, "POSE_CHECK_STEP", 5)
    monkeypatch.setattr(poses_module, "POSE_CHECK_DEGREES", 90.0)  # any correction: the poses are right
    monkeypatch.setattr(poses_module, "POSE_CHECK_UNSURE_DEGREES", 90.0)
    result, events = run(tiny_scene, tmp_path / "ens", config(steps=40, seed=3, members=2, refine_poses=None))
    assert result.status == "finished" and finished_members(tmp_path / "ens") == [2]
    checks = [e for e in events if e["event"] == "pose_check"]
    assert [e["member"] for e in checks] == [1] and checks[0]["refining"] is False
    second = json.loads((member_dir(tmp_path / "ens", 2) / "model.json").read_text())
    assert second["train_config"]["refine_poses"] is False and "pose_check" not in second
    assert second["poses_from"] == {"model": str(tmp_path / "ens"), "refined": False}
    # The second member is the run its seed gives alone without refinement.
    run(tiny_scene, tmp_path / "alone", config(steps=20, seed=3 + MEMBER_SEED_OFFSET, members=1, refine_poses=False))
    assert_same_weights(member_dir(tmp_path / "ens", 2), tmp_path / "alone")


def test_a_second_member_that_refined_its_own_poses_resumes_so(tiny_scene, tmp_path, monkeypatch):
    """A second member stopped by a version that refined each member's poses apart (or whose
    first member did not refine) holds corrections of its own: resumed, it goes on with them."""
    import neulf_core.pose_check as pose_check_module

    cfg = config(steps=60, seed=3, members=2, refine_poses=True)

    def in_second_member(events):
        return any(e.get("member") == 2 and e.get("event") == "step" and e["step"] >= 10 for e in events)

    with monkeypatch.context() as patch:
        # as before the corrections were shared: each member refines and checks its own
        patch.setattr(pose_check_module, "first_members_poses", lambda config, *args: (config, None, False))
        result, _ = run(tiny_scene, tmp_path / "old", cfg, stop_when=in_second_member)
    assert result.status == "cancelled"
    result, _ = run(tiny_scene, tmp_path / "old", config(steps=60, seed=3), resume=True)
    assert result.status == "finished" and finished_members(tmp_path / "old") == [2]
    second = json.loads((member_dir(tmp_path / "old", 2) / "model.json").read_text())
    assert "poses_from" not in second and second["pose_corrections"]["median_degrees"] > 0


def test_member_errors_are_one_line(tiny_scene, tmp_path):
    run(tiny_scene, tmp_path / "m", config(steps=20, members=2))
    with pytest.raises(NeulfError, match="was trained with 2 members"):
        run(tiny_scene, tmp_path / "m", config(steps=40, members=3), resume=True)
    with pytest.raises(NeulfError, match="1 to 8"):
        run(tiny_scene, tmp_path / "n", config(steps=20, members=0))
    run(tiny_scene, tmp_path / "single", config(steps=20))
    with pytest.raises(NeulfError, match="trained with 1 member;"):
        run(tiny_scene, tmp_path / "single", config(steps=40, members=2), resume=True)
    # A member moved away or damaged: a clear message, not a traceback.
    model = member_dir(tmp_path / "m", 2)
    model.rename(tmp_path / "elsewhere")
    with pytest.raises(NeulfError, match="member 2 .* is missing"):
        LightField.load(tmp_path / "m", "cpu")
    (tmp_path / "elsewhere").rename(model)
    for name in ("model.pt", "checkpoint.pt"):
        (model / name).write_bytes(b"not a checkpoint")
    with pytest.raises(NeulfError) as caught:
        LightField.load(tmp_path / "m", "cpu")
    assert "\n" not in str(caught.value) and "members/2" in str(caught.value).replace("\\", "/")


def test_cli_members(tiny_scene, tmp_path, capsys):
    from neulf_core.cli import main

    out = tmp_path / "cli"
    code = main(["train", str(tiny_scene), "--out", str(out), "--steps", "20", "--members", "2", "--batch-size", "512",
                 "--no-sweep-teacher", "--no-refine-poses"])
    assert code == 0 and finished_members(out) == [2]
    assert json.loads((member_dir(out, 2) / "model.json").read_text())["train_config"]["seed"] == MEMBER_SEED_OFFSET
    assert torch.isfinite(torch.as_tensor(LightField.load(out, "cpu").render_view(
        split_views(load_scene(tiny_scene))[1][0], depth=False).rgb)).all()


def test_work_done_counts_every_member(tiny_scene, tmp_path):
    from neulf_core.members import budget_done, work_done

    assert work_done(tmp_path / "none") == (0, 0.0) == budget_done(tmp_path / "none")
    run(tiny_scene, tmp_path / "one", config(steps=20))
    assert work_done(tmp_path / "one")[0] == 20 == budget_done(tmp_path / "one")[0]
    run(tiny_scene, tmp_path / "m", config(steps=30, members=3))
    steps, seconds = work_done(tmp_path / "m")
    assert steps == 30 and seconds > 0 and budget_done(tmp_path / "m") == (steps, seconds)
    # Members of half the batch each train all the steps: the budget counts them once, so that
    # Blender's Train, which continues a model with what is done plus its budget, asks for 30 + 10.
    result, events = run(tiny_scene, tmp_path / "b", config(steps=30, members=2, members_split="batch"))
    assert work_done(tmp_path / "b")[0] == 60 and budget_done(tmp_path / "b")[0] == 30
    finished = next(e for e in events if e["event"] == "finished")
    assert (finished["step"], finished["member_steps"], finished["members_split"]) == (30, [30, 30], "batch")
    from neulf_core.progress import members_text

    assert members_text(finished) == " (30 + 30 in its 2 members, each with 1/2 of the rays a step)"
    assert members_text({"member_steps": [10, 10], "members_split": "steps"}) == " (10 + 10 in its 2 members)"
    assert members_text({"step": 20}) == ""
    run(tiny_scene, tmp_path / "b", config(steps=budget_done(tmp_path / "b")[0] + 10), resume=True)
    assert [json.loads((member_dir(tmp_path / "b", m) / "model.json").read_text())["progress"]["step"]
            for m in (1, 2)] == [40, 40]


def test_the_benchmark_trains_both_ways_and_tables_the_spread(benchmark_script, tiny_scene, tmp_path):
    bench = benchmark_script("members")
    args = bench.parse_args(["--configurations", "canclip", "--seeds", "0-1", "--budgets", "20,40",
                             "--canclip", str(tiny_scene), "--canclip-scale", "1"])
    work = bench.plan(args)
    assert [(job.seed, job.steps, members) for _, job, members in work] == [
        (0, 20, 1), (0, 20, 2), (1, 20, 1), (1, 20, 2), (0, 40, 1), (0, 40, 2), (1, 40, 1), (1, 40, 2)]
    again = bench.plan(bench.parse_args(["--configurations", "canclip", "--seeds", "0", "--budgets", "20",
                                         "--member-counts", "2", "--canclip", str(tiny_scene)]))
    assert [(job.seed, job.steps, members) for _, job, members in again] == [(0, 20, 2)]  # the members alone
    # One model each way, through the product's trainer and renderer.
    label, job, _ = work[0]
    one = bench.train_and_score(label, job, 1, tmp_path)
    two = bench.train_and_score(label, job, 2, tmp_path)
    assert (one["members"], two["members"], one["steps"], two["steps"]) == (1, 2, 20, 20)
    assert one["passes"] == two["passes"] == round(20 * 8192 / (7 * 48 * 36), 1)
    assert finished_members(bench.model_folder(tmp_path, label, 0, 20, 2)) == [2]
    assert np.isfinite([one["psnr"], two["psnr"], two["psnr_4"]]).all() and two["train_seconds"] > 0

    def row(seed, members, value):
        return {"configuration": "scene", "seed": seed, "budget": 2000, "passes": 61.0, "members": members, "psnr": value,
                "psnr_4": value + 0.1, "ssim": 0.9, "train_seconds": 10.0 * members, "steps": 2000}

    rows = [row(0, 1, 30.0), row(1, 1, 30.4), row(2, 1, 30.1), row(0, 2, 30.3), row(1, 2, 30.5), row(2, 2, 30.35)]
    text = bench.table(rows)
    assert "| scene | 2000 | 61.0 | 3 | 30.17 ± 0.170, range 0.40 | 30.38 ± 0.085, range 0.20 | +0.22 (better in 3 of 3) |" in text
    assert "3 members" not in text  # the larger counts' table only where they were trained
    rows += [row(0, 3, 30.5), row(1, 3, 30.6), row(2, 3, 30.4)]
    text = bench.table(rows)
    assert ("| scene | 2000 | 61.0 | 3 | 30.17 ± 0.170, range 0.40 | 30.38 ± 0.085, range 0.20 | "
            "30.50 ± 0.082, range 0.20 | +0.12 |") in text
    bench.chart(rows, tmp_path / "chart.png")
    assert (tmp_path / "chart.png").stat().st_size > 0
    # Rows are logged as each run ends; a re-run replaces its own rows and keeps the others.
    assert bench.merged(rows[:3], [row(1, 1, 31.0)]) == [rows[0], rows[2], row(1, 1, 31.0)]


def test_the_rule_counts_the_passes_of_a_steps_budget(tiny_scene, tmp_path):
    from neulf_core.members import MEMBERS_PASSES, members_by_rule, training_pixels

    assert members_by_rule(None) is None and members_by_rule(MEMBERS_PASSES - 1) == 1
    assert members_by_rule(MEMBERS_PASSES) == 2
    scene = load_scene(tiny_scene)
    pixels = training_pixels(scene, config())
    assert pixels == 7 * 48 * 36  # the tiny scene's 7 training views (every 8th held out)
    # 60 passes of 512 rays over its pixels take 1418 steps: two members from there.
    just_under, enough = 1417, 1418
    assert just_under * 512 / pixels < MEMBERS_PASSES <= enough * 512 / pixels
    _, events = run(tiny_scene, tmp_path / "under", config(steps=40, batch_size=8192 * 0 + 512))
    assert not (tmp_path / "under" / STATE_NAME).exists()
    result, events = run(tiny_scene, tmp_path / "rule", config(steps=2 * 89, batch_size=8192))  # 120 passes
    assert result.status == "finished" and finished_members(tmp_path / "rule") == [2]
    assert any(e.get("event") == "stage" and "2 members" in e.get("message", "") for e in events)
    steps = [json.loads((member_dir(tmp_path / "rule", m) / "model.json").read_text())["progress"]["step"]
             for m in (1, 2)]
    assert steps == [89, 89]
    # --members 1 turns it off.
    run(tiny_scene, tmp_path / "one", config(steps=2 * 89, batch_size=8192, members=1))
    assert not (tmp_path / "one" / STATE_NAME).exists()


def _time_the_first_steps(monkeypatch) -> None:
    """The rule's rate timed over steps 11-30 (not after the pose check): a tiny scene's short
    minutes budget reaches its decision on a slow machine too."""
    import neulf_core.train as train_module

    monkeypatch.setattr(train_module, "MEMBERS_RATE_FROM_STEP", 10)
    monkeypatch.setattr(train_module, "MEMBERS_RATE_DECISION_STEP", 30)


def test_the_rule_on_a_minutes_budget_decides_from_the_step_rate(tiny_scene, tmp_path, monkeypatch):
    import neulf_core.members as members

    # Forced both ways (a measured rate differs between machines): the threshold at 0 passes
    # makes two members, an unreachable one keeps one.  Timed early, so that a slow machine's
    # 1.2 s still reach the decision.
    _time_the_first_steps(monkeypatch)
    monkeypatch.setattr(members, "MEMBERS_PASSES", 0.0)
    result, events = run(tiny_scene, tmp_path / "two", config(minutes=0.04))
    assert result.status == "finished" and finished_members(tmp_path / "two") == [2]
    decided = [e for e in events if e.get("event") == "members"]
    assert len(decided) == 1 and decided[0]["count"] == 2
    metas = [json.loads((member_dir(tmp_path / "two", m) / "model.json").read_text()) for m in (1, 2)]
    assert metas[0]["members_rule"]["count"] == 2 and metas[0]["train_config"]["members"] is None
    assert metas[1]["train_config"]["members"] == 2 and metas[1]["train_config"]["minutes"] == pytest.approx(0.02)
    # Each member trained its half of the 2.4 s: the first stopped at its share, not at the whole.
    for meta in metas:
        assert 1.2 <= meta["progress"]["elapsed"] < 2.4
    monkeypatch.setattr(members, "MEMBERS_PASSES", 1e12)
    run(tiny_scene, tmp_path / "one", config(minutes=0.02))
    meta = json.loads((tmp_path / "one" / "model.json").read_text())
    assert meta["members_rule"]["count"] == 1 and not (tmp_path / "one" / STATE_NAME).exists()


def test_a_first_member_past_its_share_at_the_decision_stays_one(tiny_scene, tmp_path, monkeypatch):
    """Where the first member's steps up to the rule's decision took longer than its share of the
    minutes, two members would overrun the budget (the second takes its whole share after): one."""
    import time

    import neulf_core.members as members
    from neulf_core.members import share_spent

    assert share_spent(1.0, 2, 30.0) and not share_spent(1.0, 2, 29.9) and not share_spent(1.0, 1, 50.0)
    assert not share_spent(None, 2, 1e6)
    _time_the_first_steps(monkeypatch)  # the decision at step 30
    monkeypatch.setattr(members, "MEMBERS_PASSES", 0.0)  # two by the passes, at any pace
    events = []

    def slow_first_steps(event):  # 29 steps of at least 0.12 s before it: past 3 s, a member's share of 6
        events.append(event)
        if event.get("event") == "step" and event["step"] <= 30:
            time.sleep(0.12)

    result = train(tiny_scene, tmp_path / "m", config(minutes=0.1), progress=slow_first_steps)
    assert result.status == "finished"
    rule = json.loads((tmp_path / "m" / "model.json").read_text())["members_rule"]
    assert rule["count"] == 1 and rule["share_spent"] is True
    assert not (tmp_path / "m" / STATE_NAME).exists() and finished_members(tmp_path / "m") == []
    assert any("more than a member's share" in e.get("message", "") for e in events)


@pytest.mark.parametrize("kept, written", [(1, 2), (2, 1)])
def test_a_resume_follows_the_kept_starts_verdict_not_the_first_starts(tiny_scene, tmp_path, monkeypatch, kept, written):
    """Of two starts the first writes members.json when its rule decides; the kept one's verdict
    (model.json) is the model's.  Stopped before the first member finished with the two at odds,
    the model resumes as the kept start decided (here the odds are written by hand)."""
    import neulf_core.members as members

    _time_the_first_steps(monkeypatch)
    monkeypatch.setattr(members, "MEMBERS_PASSES", 0.0 if kept == 2 else 1e12)

    def after_the_decision(events):
        return any(e.get("event") == "members" for e in events) and sum(e.get("event") == "step" for e in events) > 40

    folder = tmp_path / "m"
    result, _ = run(tiny_scene, folder, config(minutes=0.04), stop_when=after_the_decision)
    assert result.status == "cancelled"
    assert json.loads((folder / "model.json").read_text())["members_rule"]["count"] == kept
    if written == 2:
        (folder / STATE_NAME).write_text(json.dumps({"count": 2, "seed": 0, "split": "steps", "finished": []}))
    else:
        (folder / STATE_NAME).unlink()
    result, _ = run(tiny_scene, folder, config(minutes=0.04), resume=True)
    assert result.status == "finished"
    assert finished_members(folder) == ([2] if kept == 2 else []) and (folder / STATE_NAME).exists() == (kept == 2)
    minutes = json.loads((folder / "model.json").read_text())["train_config"]["minutes"]
    assert minutes == pytest.approx(0.04 / kept)  # the first member's share: the whole for one


def test_a_minutes_budget_stopped_after_the_rule_resumes_as_an_ensemble(tiny_scene, tmp_path, monkeypatch):
    import neulf_core.members as members

    _time_the_first_steps(monkeypatch)
    monkeypatch.setattr(members, "MEMBERS_PASSES", 0.0)

    def after_the_decision(events):
        return any(e.get("event") == "members" for e in events) and sum(e.get("event") == "step" for e in events) > 40

    result, _ = run(tiny_scene, tmp_path / "m", config(minutes=0.04), stop_when=after_the_decision)
    assert result.status == "cancelled"
    assert json.loads((tmp_path / "m" / STATE_NAME).read_text())["count"] == 2
    result, _ = run(tiny_scene, tmp_path / "m", config(minutes=0.04), resume=True)
    assert result.status == "finished" and finished_members(tmp_path / "m") == [2]
    first = json.loads((tmp_path / "m" / "model.json").read_text())
    assert first["train_config"]["minutes"] == pytest.approx(0.02)  # its share, not the whole (nor a quarter)


def test_on_a_cpu_the_rules_members_share_the_batch(tiny_scene, tmp_path):
    """The default (members_split None) on a CPU: where the passes call for two members, each
    trains all the steps with half the batch -- the run its seed gives alone so."""
    result, events = run(tiny_scene, tmp_path / "rule", config(steps=89, batch_size=16384, members_split=None))
    assert result.status == "finished" and finished_members(tmp_path / "rule") == [2]  # 120 passes
    assert json.loads((tmp_path / "rule" / STATE_NAME).read_text())["split"] == "batch"
    assert any(e.get("event") == "stage" and "each all the steps with 1/2 of the rays" in e.get("message", "")
               for e in events)
    run(tiny_scene, tmp_path / "alone", config(steps=89, batch_size=8192, seed=0, members=1))
    assert_same_weights(tmp_path / "rule", tmp_path / "alone")
    # Under the rule's passes: one member of the whole batch, as before.
    run(tiny_scene, tmp_path / "under", config(steps=40, members_split=None))
    assert not (tmp_path / "under" / STATE_NAME).exists()
    # Members of the batch pay from 12 passes, members of the steps from 60: 18 steps of 8192
    # rays make 12.2 passes over the tiny scene's pixels, 17 make 11.5.
    run(tiny_scene, tmp_path / "twelve", config(steps=18, batch_size=8192, members_split=None))
    assert finished_members(tmp_path / "twelve") == [2]
    run(tiny_scene, tmp_path / "eleven", config(steps=17, batch_size=8192, members_split=None))
    assert not (tmp_path / "eleven" / STATE_NAME).exists()
    run(tiny_scene, tmp_path / "twelve-steps", config(steps=18, batch_size=8192, members_split="steps"))
    assert not (tmp_path / "twelve-steps" / STATE_NAME).exists()


def _rule_run(**overrides) -> TrainConfig:
    """A minutes budget long enough that the pass limit (5 passes: 119 steps of 512 rays over the
    tiny scene's pixels) ends each member, so that runs repeat to the weight."""
    return config(minutes=10.0, max_passes=5.0, members_split=None, seed=5, **overrides)


def test_a_minutes_budget_whose_rule_splits_the_batch_goes_on_with_half(tiny_scene, tmp_path, monkeypatch):
    """On a minutes budget the rule decides at a step of the first member (here 30): from there it
    trains with half the batch, its pass limit still counting rays; the second member trains with
    half throughout.  Stopped after the decision and resumed, the first member goes on as it began."""
    import neulf_core.members as members

    _time_the_first_steps(monkeypatch)
    monkeypatch.setattr(members, "BATCH_MEMBERS_PASSES", 0.0)
    result, events = run(tiny_scene, tmp_path / "whole", _rule_run())
    assert result.status == "finished" and finished_members(tmp_path / "whole") == [2]
    assert json.loads((tmp_path / "whole" / STATE_NAME).read_text())["split"] == "batch"
    metas = [json.loads((member_dir(tmp_path / "whole", m) / "model.json").read_text()) for m in (1, 2)]
    rule = metas[0]["members_rule"]
    assert (rule["split"], rule["batch_switch"]) == ("batch", {"step": 30, "before": 512})
    # 30 steps of 512 rays, then the rest of 119 x 512 rays in steps of 256: 30 + 178.
    assert metas[0]["progress"]["step"] == 30 + 2 * (119 - 30)
    assert (metas[1]["train_config"]["batch_size"], metas[1]["progress"]["step"]) == (256, 237)
    assert any(e.get("event") == "passes" and e.get("steps") == 208 for e in events)

    def after_the_decision(events):
        return any(e.get("event") == "members" for e in events) and sum(e.get("event") == "step" for e in events) > 60

    result, _ = run(tiny_scene, tmp_path / "cut", _rule_run(), stop_when=after_the_decision)
    assert result.status == "cancelled" and finished_members(tmp_path / "cut") == []
    result, _ = run(tiny_scene, tmp_path / "cut", _rule_run(), resume=True)
    assert result.status == "finished" and finished_members(tmp_path / "cut") == [2]
    assert_same_weights(tmp_path / "cut", tmp_path / "whole")
    assert_same_weights(member_dir(tmp_path / "cut", 2), member_dir(tmp_path / "whole", 2))


def test_a_first_member_stopped_before_its_verdict_was_saved_goes_on_with_its_share(tiny_scene, tmp_path,
                                                                                     monkeypatch):
    """members.json can say "two members of the batch" while the first member's last checkpoint
    predates the verdict (killed between the two, or a second start stopped before its own):
    resumed, that member trains with its share of the batch from where it stood."""
    import neulf_core.members as members

    _time_the_first_steps(monkeypatch)
    monkeypatch.setattr(members, "BATCH_MEMBERS_PASSES", 0.0)

    def before_the_decision(events):
        return sum(e.get("event") == "step" for e in events) >= 15

    result, _ = run(tiny_scene, tmp_path / "m", _rule_run(), stop_when=before_the_decision)
    stopped = json.loads((tmp_path / "m" / "model.json").read_text())
    assert result.status == "cancelled" and "members_rule" not in stopped
    (tmp_path / "m" / STATE_NAME).write_text(json.dumps({"count": 2, "seed": 5, "split": "batch", "finished": []}))
    result, _ = run(tiny_scene, tmp_path / "m", _rule_run(), resume=True)
    assert result.status == "finished" and finished_members(tmp_path / "m") == [2]
    first = json.loads((tmp_path / "m" / "model.json").read_text())
    at = stopped["progress"]["step"]
    assert first["members_rule"]["batch_switch"] == {"step": at, "before": 512}
    assert first["progress"]["step"] == at + 2 * (119 - at)


def test_the_kept_start_decides_the_members(tmp_path):
    """Two starts time their own pace, so their verdicts on the members may differ: members.json
    follows the kept one's (model.json), and a second start's verdict is not passed on."""
    from neulf_core.members import _state_as_decided, read_state
    from neulf_core.starts import _Watch

    heard = []
    watch = _Watch(heard.append, "second", 100, decision=42)
    watch({"event": "members", "count": 2, "split": "batch"})
    assert watch.members == 2 and heard == []
    model = tmp_path / "m"
    model.mkdir()
    (model / "model.json").write_text(json.dumps({"members_rule": {"count": 2, "split": "batch"}}))
    assert _state_as_decided(model, 7) == read_state(model) == {"count": 2, "seed": 7, "split": "batch", "finished": []}
    (model / "model.json").write_text(json.dumps({"members_rule": {"count": 1}}))
    assert _state_as_decided(model, 7) is None and read_state(model) is None
    (model / "model.json").write_text(json.dumps({"progress": {"step": 10}}))  # the budget ended before the rule
    assert _state_as_decided(model, 7) is None


def test_a_switch_of_batch_counts_rays_for_the_pass_limit_and_the_schedule():
    from neulf_core.train import BatchSwitch

    switch = BatchSwitch.of({"count": 2, "batch_switch": {"step": 30, "before": 8192}})
    assert switch.batch == 4096 and switch.steps_for(119, 4096) == 208 and switch.steps_for(20, 4096) == 30
    assert switch.extra_rays(4096) == 30 * 4096  # step x 4096 + this: the rays seen
    assert BatchSwitch.of({"count": 1}) is None and BatchSwitch.of(None) is None


def test_render_speed_times_members_with_the_current_code_only(benchmark_script, tiny_scene, tmp_path):
    bench = benchmark_script("render_speed")
    run(tiny_scene, tmp_path / "two", config(steps=20, members=2))
    run(tiny_scene, tmp_path / "one", config(steps=20))
    two, one = (LightField.load(tmp_path / name, "cpu") for name in ("two", "one"))
    assert len(bench.single_fields(two)) == 2 and not bench.reference_can_render(two)
    assert len(bench.single_fields(one)) == 1 and bench.reference_can_render(one)
    bench.use_code([two, one], current=True)  # reaches into every member's layers


def test_two_starts_count_a_members_share_of_the_minutes():
    """A minutes budget that the rule shares between two members: the first member's two starts
    must fit in its half, not in the whole (they overran it before: 77 s for a 1-minute run)."""
    from neulf_core.starts import _Watch, minutes_budget_allows

    watch = _Watch(None, "first", 2374)
    watch({"event": "members", "count": 2})
    assert watch.members == 2
    # 60 s to the decision step of CanClip's 6 photos projects to 203 s in all: inside 4 minutes,
    # not inside the 2 minutes a member of two gets.
    assert minutes_budget_allows(4.0, 60.0, 2374) and not minutes_budget_allows(4.0 / watch.members, 60.0, 2374)


def test_only_the_first_starts_members_verdict_reaches_the_user():
    """The second of two starts decides its members too, but the kept start's verdict is the
    model's (members.train_members): its event and its message stay inside."""
    from neulf_core.starts import _Watch

    for stage, shown in (("first", True), ("second", False)):
        seen = []
        watch = _Watch(seen.append, stage, 2374)
        watch({"event": "stage", "verdict": "members", "message": "2 members: ..."})
        watch({"event": "members", "count": 2})
        watch({"event": "stage", "message": "sweep depth of view 1"})
        assert watch.members == 2
        assert [e.get("message") for e in seen if e.get("event") == "stage"] == (
            ["2 members: ...", "sweep depth of view 1"] if shown else ["sweep depth of view 1"])


@pytest.mark.parametrize("poses_off", [False, True])
def test_a_later_member_follows_the_first_ones_verdict_on_the_losses(tiny_scene, tmp_path, monkeypatch, poses_off):
    """With 11 to 20 photos (here the rule's limit lowered to the tiny scene's 7) the first
    member stops the multi-view losses where its pose check finds the poses right; a later
    member, which has no check of its own, trains without them from its start (with them
    throughout where the first found the poses off)."""
    import neulf_core.poses as poses_module
    from conftest import losses_as_for_11_to_20_photos

    calls = losses_as_for_11_to_20_photos(monkeypatch, poses_off)
    check = poses_module.POSE_CHECK_STEP
    each = 2 * check + 4
    cfg = config(steps=2 * each, members=2, refine_poses=None, near=1.0, far=6.0, consistency_rays=16, batch_size=64)
    run(tiny_scene, tmp_path / "m", cfg)
    first = json.loads((tmp_path / "m" / "model.json").read_text())
    assert len(calls) == (2 * each if poses_off else check)
    assert first.get("multiview_losses_until_step") == (None if poses_off else check)
    second = json.loads((member_dir(tmp_path / "m", 2) / "model.json").read_text())
    assert second.get("multiview_losses_until_step") == (None if poses_off else 0)


def test_the_rate_is_the_median_steps_so_a_few_slow_steps_do_not_decide():
    """A shared machine's hiccup (here 5 of 100 steps taking 50 times as long) must not read as
    a slow run: the rule times the median step."""
    import neulf_core.poses as poses_module
    import neulf_core.train as train_module

    steady, hiccups = [0.02] * 95, [1.0] * 5
    meta = {}
    budget = config(minutes=1.0)
    train_module._decide_members_at_measured_rate(budget, budget, 8192, 268800, steady + hiccups, meta, None, "cpu", 210,
                                                     elapsed=9.0)
    assert meta["members_rule"]["steps_per_minute"] == pytest.approx(3000.0)
    assert meta["members_rule"]["passes"] == pytest.approx(3000 * 8192 / 268800, abs=0.1)
    assert meta["members_rule"]["count"] == 2  # 91 passes; the mean step would read 36 and one member
    assert train_module.MEMBERS_RATE_FROM_STEP >= poses_module.POSE_CHECK_STEP  # timed after the pose check


def test_members_that_split_the_batch_count_the_budgets_passes_together():
    """A member of half the batch decides what counts passes (the multi-view losses) as one run
    of the whole budget would: each counting its own half dropped the losses where one run keeps
    them, and lost 6 dB under pose noise (rules.budget_rays_per_step)."""
    from neulf_core.rules import budget_rays_per_step

    assert budget_rays_per_step(config(batch_size=4096, members=2, members_split="batch")) == 8192
    assert budget_rays_per_step(config(batch_size=4096, members=2)) == 4096  # members of the steps: their own batch
    assert budget_rays_per_step(config(batch_size=None)) == 8192  # the preset's


def test_the_command_line_asks_for_members_of_the_batch(tiny_scene, tmp_path):
    from neulf_core.cli import main

    model = tmp_path / "m"
    assert main(["train", str(tiny_scene), "--out", str(model), "--steps", "4", "--batch-size", "128",
                 "--members-split", "batch", "--progress", "json"]) == 0
    assert json.loads((model / STATE_NAME).read_text())["split"] == "batch" and finished_members(model) == [2]
    assert json.loads((member_dir(model, 2) / "model.json").read_text())["train_config"]["batch_size"] == 64


def test_members_of_the_batch_stopped_in_the_second_resume_as_they_began(tiny_scene, tmp_path):
    """A resume that does not say --members-split goes on as the model began (members.json):
    the second member with half the batch, and its rules counting the budget's rays together."""
    run(tiny_scene, tmp_path / "whole", config(steps=30, seed=4, members_split="batch"))

    def in_second_member(events):
        return any(e.get("member") == 2 and e.get("event") == "step" and e["step"] >= 5 for e in events)

    result, _ = run(tiny_scene, tmp_path / "cut", config(steps=30, seed=4, members_split="batch"),
                    stop_when=in_second_member)
    assert result.status == "cancelled" and finished_members(tmp_path / "cut") == []
    result, _ = run(tiny_scene, tmp_path / "cut", config(steps=30, seed=4), resume=True)
    assert result.status == "finished" and finished_members(tmp_path / "cut") == [2]
    second = json.loads((member_dir(tmp_path / "cut", 2) / "model.json").read_text())["train_config"]
    assert (second["batch_size"], second["members_split"]) == (256, "batch")
    assert_same_weights(member_dir(tmp_path / "cut", 2), member_dir(tmp_path / "whole", 2))

"""The stability study's machinery (benchmarks/stability.py) end to end on the tiny scene:
scene edits, a few training steps per run, scoring, and the CSV / chart / tables it writes."""

from __future__ import annotations

import csv
from dataclasses import replace
import json
import importlib.util
import math
import sys
from pathlib import Path

import numpy as np
import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "stability.py"


def two_members(stability) -> dict:
    """What a logged run of the default records where it trained two members of half the batch
    (on a CPU, from 12 passes over the training pixels: neulf_core/members.py), for rows whose
    budget calls for them: the later member in the first one's frame."""
    return {"members": 2, "members_split_used": "batch", "member_poses": stability.MEMBER_POSES}


@pytest.fixture(scope="module")
def stability():
    spec = importlib.util.spec_from_file_location("stability_benchmark", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while the class is built
    spec.loader.exec_module(module)
    return module


def rotation_angle_degrees(a: np.ndarray, b: np.ndarray) -> float:
    cosine = (np.trace(a @ b.T) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0))))


def test_pose_noise_has_the_requested_size_and_moves_no_camera_on_average(stability, tiny_scene):
    """Each camera turns by about the level (a random axis) and moves by about 10 % of the
    spacing per degree, less what all of them share: their mean turn and move are zero."""
    scene = stability.load_any(tiny_scene)
    spacing = stability.rig_spacing(scene.views)
    noisy = stability.perturb_poses(scene.views, 2.0, spacing)
    turns, moves = [], []
    for before, after in zip(scene.views, noisy):
        turn = after.R.T @ before.R  # turn @ R^T = R'^T
        angle = rotation_angle_degrees(after.R, before.R)
        axis = np.array([turn[2, 1] - turn[1, 2], turn[0, 2] - turn[2, 0], turn[1, 0] - turn[0, 1]])
        turns.append(axis / max(np.linalg.norm(axis), 1e-12) * angle)
        moves.append(after.center - before.center)
        assert 0.3 * 2.0 < angle < 1.7 * 2.0
        assert 0.3 < np.linalg.norm(moves[-1]) / (2.0 * stability.SHIFT_PER_DEGREE * spacing) < 1.7
    assert np.allclose(np.mean(turns, axis=0), 0.0, atol=1e-6) and np.allclose(np.mean(moves, axis=0), 0.0, atol=1e-9)
    half = stability.perturb_poses(scene.views, 1.0, spacing)  # the same draws, half the size
    assert rotation_angle_degrees(half[0].R, scene.views[0].R) == pytest.approx(rotation_angle_degrees(noisy[0].R, scene.views[0].R) / 2, rel=1e-6)


def test_the_noise_s_depth_like_part_is_what_the_refinement_cannot_correct_extended_to_any_camera(stability, tiny_scene):
    """The part of the drawn noise along the pose refinement's two held directions (the turns'
    fanning, the moves' baseline): what is left of the noise has none of either, and the part
    grows linearly with a camera's place on the uv plane, so a held-out camera between two
    training cameras gets their mean."""
    from neulf_core.slab import slab_frame

    train, held = stability.split_views(stability.load_any(tiny_scene))
    spacing = stability.rig_spacing(train)
    turns, moves = stability.pose_noise(train, 2.0, spacing)
    part = stability.depth_like_part(train, 2.0, spacing)
    rotation, origin = slab_frame(train)
    uv = ((np.array([v.center for v in train]) - origin) @ rotation.T)[:, :2]
    u, v = (uv - uv.mean(0)).T
    fanning, baseline = np.stack([-v, u, 0 * u], 1), np.stack([u, v, 0 * u], 1)
    part_turns, part_moves = (np.array(x) for x in zip(*(part(view) for view in train)))
    assert np.abs(part_turns).max() > 1e-3  # (this draw has some fanning)
    assert ((turns - part_turns) @ rotation.T * fanning).sum() == pytest.approx(0.0, abs=1e-9)
    assert ((moves - part_moves) @ rotation.T * baseline).sum() == pytest.approx(0.0, abs=1e-12)
    assert np.allclose(part_turns @ rotation.T, (part_turns @ rotation.T * fanning).sum(1, keepdims=True)
                       * fanning / np.maximum((fanning ** 2).sum(1, keepdims=True), 1e-24), atol=1e-9)
    between = replace(train[0], R=train[0].R, t=-train[0].R @ ((train[0].center + train[1].center) / 2))
    assert np.allclose(part(between)[0], (part_turns[0] + part_turns[1]) / 2, atol=1e-9)
    assert np.allclose(part(between)[1], (part_moves[0] + part_moves[1]) / 2, atol=1e-12)
    # Scored that way, a held-out camera turns with its part; without pose noise it stays.
    job = stability.Job("tiny", str(tiny_scene), str(tiny_scene), 1.0, "fast", 2, 0, pose_degrees=2.0)
    moved = stability.held_with_noise_part(job, held)
    assert any(not np.allclose(a.R, b.R) for a, b in zip(moved, held))
    still = stability.held_with_noise_part(replace(job, pose_degrees=0.0), held)
    assert all(np.allclose(a.R, b.R) and np.allclose(a.t, b.t) for a, b in zip(still, held))


def test_prepare_edits_only_training_views(stability, tiny_scene):
    job = stability.Job("tiny", str(tiny_scene), str(tiny_scene), 1.0, "fast", 2, 0, fraction=0.5, pose_degrees=1.0)
    scene, train_views, held = stability.prepare(job)
    original = stability.load_any(tiny_scene)
    assert [v.name for v in held] == ["view_00.png", "view_08.png"]  # every 8th, as in training
    assert len(train_views) == 4  # half of the 7 training views, rounded
    for view in held:
        assert np.allclose(view.R, original.view(view.name).R) and np.allclose(view.t, original.view(view.name).t)
    assert len(scene.views) == len(train_views) + len(held)


def test_study_runs_end_to_end(stability, tiny_scene, tmp_path, monkeypatch):
    monkeypatch.setattr(stability, "POSE_SCENES", ("tiny",))  # its runs scored with the held-out poses fitted too
    jobs = [stability.Job("tiny", str(tiny_scene), str(tiny_scene), 1.0, "fast", 3, seed, fraction=fraction)
            for fraction in (1.0, 0.5) for seed in (0, 1)]
    jobs.append(stability.Job("tiny", str(tiny_scene), str(tiny_scene), 1.0, "fast", 3, 0, pose_degrees=1.0))
    jobs.append(stability.Job("tiny", str(tiny_scene), str(tiny_scene), 1.0, "fast", 3, 0, pose_degrees=1.0,
                              refine_poses=True))
    # the losses study: off / on for the same wall-clock budget
    jobs += [stability.Job("tiny", str(tiny_scene), str(tiny_scene), 1.0, "fast", 3, seed, fraction=0.5,
                           consistency=on, minutes=0.05) for on, seed in ((False, 0), (False, 1), (True, 0))]
    # the coarse-to-fine study: the half share (4 training views, on by default) without it
    jobs += [stability.Job("tiny", str(tiny_scene), str(tiny_scene), 1.0, "fast", 3, seed, fraction=0.5,
                           coarse_to_fine=False) for seed in (0, 1)]
    rows = stability.run_jobs(jobs, workers=1, log=tmp_path / "runs.jsonl")

    assert [r["status"] for r in rows] == ["finished"] * len(jobs), [r.get("error") for r in rows]
    assert len((tmp_path / "runs.jsonl").read_text().splitlines()) == len(jobs)
    meta = {"date": "2026-11-21", "machine": "test", "fast_steps": 3, "paper_steps": 0, "seeds": "0,1"}
    tables = stability.write_outputs(rows, tmp_path / "docs", meta)

    with open(tmp_path / "docs" / "stability.csv") as handle:
        written = list(csv.DictReader(handle))
    assert len(written) == len(jobs)
    for row in written:
        assert row["steps_done"] == "3" or row["minutes"] == "0.05"
        # (a 3-second budget ends before 200 steps: its one warning says so, train.barely_trained_warning)
        assert row["warnings"] == ("1" if row["minutes"] == "0.05" else "0"), row
        for column in ("psnr", "ssim", "psnr_matched", "train_seconds"):
            assert math.isfinite(float(row[column])), (column, row)
    assert (tmp_path / "docs" / "stability.png").stat().st_size > 0
    fitted = [r for r in rows if r.get("psnr_pose_fitted") is not None]
    assert len(fitted) == 4 and all(not r["minutes"] and r["coarse_to_fine"] is None and r["fraction"] == 1.0 for r in fitted)
    assert all(math.isfinite(r["psnr_pose_fitted"]) and len(r["pose_fit_degrees"].split(";")) == 2 for r in fitted)
    assert "held-out poses fitted" in tables and "| fast + `--refine-poses`, tiny |" in tables
    # Runs that refine log how the corrections held their depth-like part, so they stand.
    refined = [r for r in rows if r["refine_poses"] is True or r.get("pose_check_refining") is True]
    assert refined and all(r["pose_gauge"] == stability.DEPTH_LIKE_GAUGE for r in refined)
    assert all(r["pose_gauge"] is None for r in rows if r["refine_poses"] is False)
    few = stability.Job("tiny", str(tiny_scene), str(tiny_scene), 1.0, "fast", 3, 0, fraction=stability.POSE_FEW_VIEWS)
    assert stability.in_pose_study(few) and not stability.in_pose_study(stability.replace(few, fraction=0.5))
    # A fresh machine has no run log: it starts from the committed CSV, and every run is found again.
    fresh_log = tmp_path / "fresh" / "runs.jsonl"
    assert {f.name for f in stability.fields(stability.Job)} <= set(stability.CSV_COLUMNS)  # every field a run is keyed by
    assert stability.seed_log_from_csv(fresh_log, tmp_path / "docs" / "stability.csv") == len(jobs)
    assert set(stability.load_log(fresh_log)) == {job.key for job in jobs}
    assert stability.seed_log_from_csv(fresh_log, tmp_path / "docs" / "stability.csv") == 0  # never overwritten
    # ... and the tables made from it are the ones made from the runs, to the digit: the CSV keeps
    # every score they read (the moved views' included) and its floats in full.
    assert "moved by the noise's depth-like part" in tables
    assert stability.write_outputs(list(stability.load_log(fresh_log).values()), tmp_path / "fresh_docs", meta) == tables
    markdown = (tmp_path / "docs" / "STABILITY.md").read_text()
    assert stability.MARKER_BEGIN in markdown and tables in markdown
    # --report-only trains nothing: its header keeps the machine and date the runs came from.
    assert stability.previous_generation(tmp_path / "docs" / "STABILITY.md") == {"date": "2026-11-21", "machine": "test"}
    assert stability.previous_generation(tmp_path / "no_such.md") is None
    report = stability.parse_args(["--report-only", "--docs", str(tmp_path / "docs")])
    assert stability.generation(report) == {"date": "2026-11-21", "machine": "test"}
    named = stability.parse_args(["--report-only", "--docs", str(tmp_path / "docs"), "--machine", "a GPU and a CPU"])
    assert stability.generation(named) == {"date": "2026-11-21", "machine": "a GPU and a CPU"}
    timed = [r for r in rows if r["minutes"]]
    # Each ran for its 3 seconds, or stopped earlier after 100 passes over its 4 small photos --
    # each member at its own, where the minutes rule made two (3 s pass over them far more
    # than 60 times on most machines).
    from conftest import TINY_HEIGHT, TINY_WIDTH
    from neulf_core.train import TrainConfig
    from neulf_core.rules import losses_by_default, pass_step_limit
    limit = pass_step_limit(TrainConfig(), "disparity", 4, 4 * TINY_WIDTH * TINY_HEIGHT, 8192)
    assert all(r["train_seconds"] >= 2.5 or r["steps_done"] == (r.get("members") or 1) * limit for r in timed), \
        [(r["train_seconds"], r["steps_done"], r.get("members"), limit) for r in timed]
    # The members rule's passes are logged where it counted them at a measured pace (a minutes
    # budget that reached its timing), never for a steps budget.
    assert all(r.get("members_passes") is None for r in rows if not r["minutes"])
    assert all(r.get("members_passes") is None or r["members_passes"] > 0 for r in timed)
    losses_line = next(line for line in stability.losses_table(rows) if line.startswith("| tiny |"))
    assert "| 4 |" in losses_line  # the 4 training views of the half share
    # The default's column: what the rule says for 4 photos of a shallow scene at the passes
    # the runs with the losses made (counted from their steps).
    on_steps = np.mean([r["steps_done"] for r in timed if r["consistency"] is True])
    passes = on_steps * 8192 / (4 * TINY_WIDTH * TINY_HEIGHT)
    assert f"| {passes:.0f} | {'on' if losses_by_default(False, 4, passes) else 'off'} |" in losses_line
    coarse_line = next(line for line in stability.coarse_table(rows) if line.startswith("| tiny |"))
    assert "| 4 |" in coarse_line
    used = {(r["fraction"], r["coarse_to_fine"]): r["coarse_to_fine_used"] for r in rows if not r["minutes"] and not r["pose_degrees"]}
    assert used == {(1.0, None): True, (0.5, None): True, (0.5, False): False}  # 8 and 4 training views: on by default
    # wall-clock runs stay out of the seed-spread target: the three step-budget configurations only
    assert "within 0.2 dB" in tables and "of 3 configurations" in tables
    # and by kind of run: the default's own two, the coarse-to-fine rule switched off for one
    assert "the default as a user runs it: " in tables and " of 2 within 0.2 dB" in tables
    assert "switched off or forced on (the rule studies): " in tables and " of 1 within 0.2 dB" in tables
    # pose refinement forced on or off is a rule study too; None is the default's pose check
    assert stability.setting_of({"refine_poses": True, "coarse_to_fine": None}).startswith("with a default rule")
    assert stability.setting_of({"refine_poses": False, "coarse_to_fine": None}).startswith("with a default rule")
    assert stability.setting_of({"refine_poses": None, "coarse_to_fine": None}).startswith("the default")


def test_a_crash_is_recorded_not_raised(stability, tmp_path):
    job = stability.Job("missing", str(tmp_path / "nowhere"), str(tmp_path / "nowhere"), 1.0, "fast", 3, 0)
    row = stability.run_job(job)
    assert row["status"] == "crashed" and "nowhere" in row["error"]


def test_nerf_w_protocol_fits_on_the_left_half_and_scores_the_right(stability):
    rng = np.random.default_rng(0)
    target = rng.uniform(0.2, 0.8, (16, 20, 3)).astype(np.float32)
    darker = (target - 0.05) / 1.2                      # a global exposure and offset change only
    assert stability.psnr_right_half_after_left_fit(darker, target) > 60
    broken = darker.copy()
    broken[:, 10:] = rng.uniform(0.2, 0.8, (16, 10, 3))  # structure wrong where it is scored
    assert stability.psnr_right_half_after_left_fit(broken, target) < 20
    broken_left = darker.copy()
    broken_left[:, :10] = 0.5                            # the fit sees only the left half
    assert stability.psnr_right_half_after_left_fit(broken_left, target) < stability.psnr_right_half_after_left_fit(darker, target)


def test_a_log_written_before_a_job_field_existed_still_counts(stability, tmp_path):
    """Rows logged before `refine_poses` existed, or before the pose check made None the
    default, ran without refinement: they count as refinement forced off, and the default's
    runs are trained again.  A budget too short for the check trains the same either way."""
    def logged(steps, **fields):
        job = stability.Job("tiny", "a", "a", 1.0, "fast", steps, 0, **fields)
        return {**{k: v for k, v in stability.asdict(job).items() if k != "refine_poses"}, **fields,
                "status": "finished", "psnr": 30.0}

    log = tmp_path / "runs.jsonl"
    refined = {**logged(1000, refine_poses=True), "pose_gauge": stability.DEPTH_LIKE_GAUGE}  # (else run again)
    log.write_text("\n".join(json.dumps(row) for row in (logged(1000), refined, logged(3))) + "\n")
    done = stability.load_log(log)
    job = stability.Job("tiny", "a", "a", 1.0, "fast", 1000, 0)
    assert stability.replace(job, refine_poses=False).key in done and job.key not in done
    assert stability.replace(job, refine_poses=True).key in done
    assert stability.Job("tiny", "a", "a", 1.0, "fast", 3, 0).key in done  # 3 steps: no check, no refinement


def test_rows_logged_since_the_pose_check_are_read_as_logged(stability, tmp_path):
    """A short run forced off since the check existed stays forced off (the normalisation of
    older rows must not turn it into the default's)."""
    forced_off = stability.Job("tiny", "a", "a", 1.0, "fast", 3, 0, refine_poses=False)
    log = tmp_path / "runs.jsonl"
    log.write_text(json.dumps({**stability.asdict(forced_off), "status": "finished", "psnr": 30.0,
                               "pose_check_refining": None}) + "\n")
    done = stability.load_log(log)
    assert forced_off.key in done and stability.replace(forced_off, refine_poses=None).key not in done


def test_a_new_default_colour_start_re_runs_the_default_and_old_rows_stand_until_then(stability, tmp_path):
    """The colour decoder's start is part of a run's key: rows logged before the learned start
    (no `colour_start`) read as the random start, the study trains the default again, and until
    it has, the report falls back to the old row and says how many there are.  A job with the
    random start trains with it (the override), the preset's own start needs none."""
    job = stability.Job("tiny", "a", "a", 1.0, "fast", 1000, 0, colour_start=stability.preset_colour_start("fast"))
    assert job.colour_start != "random"
    old = {k: v for k, v in stability.asdict(job).items() if k != "colour_start"}
    log = tmp_path / "runs.jsonl"
    log.write_text(json.dumps({**old, "status": "finished", "psnr": 30.0}) + "\n")
    done = stability.load_log(log)
    assert job.key not in done and stability.replace(job, colour_start="random").key in done
    [row] = stability.report_rows(done, [job])
    assert row["psnr"] == 30.0 and row["colour_start"] == "random"
    # seed 1 re-run with the new start, seed 0 not yet: the configuration reports both old rows
    other = stability.replace(job, seed=1)
    log.write_text("".join(json.dumps({**stability.asdict(j), **extra, "status": "finished", "psnr": psnr}) + "\n"
                           for j, extra, psnr in ((job, {"colour_start": "random"}, 30.0),
                                                  (other, {"colour_start": "random"}, 31.0), (other, {}, 32.0))))
    done = stability.load_log(log)
    assert sorted(r["psnr"] for r in stability.report_rows(done, [job, other])) == [30.0, 31.0]
    log.write_text(log.read_text() + json.dumps({**stability.asdict(job), "status": "finished", "psnr": 33.0}) + "\n")
    assert sorted(r["psnr"] for r in stability.report_rows(stability.load_log(log), [job, other])) == [32.0, 33.0]
    note = " ".join(stability.random_start_note([row]))
    assert "1 of the default's 1 runs" in note
    assert stability.random_start_note([{**row, "colour_start": job.colour_start}]) == []
    held = []
    assert stability.train_config(job, held).field_overrides == {}
    assert stability.train_config(stability.replace(job, colour_start="random"), held).field_overrides == {"colour_start": ""}
    paper = stability.Job("tiny", "a", "a", 1.0, "paper", 100, 0, colour_start=stability.preset_colour_start("paper"))
    assert paper.colour_start == "random" and stability.train_config(paper, held).field_overrides == {}


def test_a_run_whose_sweep_faded_otherwise_than_now_is_run_again(stability, tmp_path):
    """Rows logged before the fade depended on the photo count faded over TEACHER_FADE: a
    run of few photos is trained again, one of more photos and the paper's network (no sweep)
    stand, whether the row came from the log or from the committed CSV (no value: '')."""
    from neulf_core.teacher import TEACHER_FADE, TEACHER_FEW_VIEWS, teacher_fade

    few, more = TEACHER_FEW_VIEWS, TEACHER_FEW_VIEWS + 1
    assert teacher_fade(few) != TEACHER_FADE == teacher_fade(more)
    jobs = {(preset, n): stability.Job(f"tiny{n}", "a", "a", 1.0, preset, 1000, 0) for preset in ("fast", "paper") for n in (few, more)}
    log = tmp_path / "runs.jsonl"
    for fade in ({}, {"sweep_fade": None}):  # logged before the field, or read back from the CSV
        log.write_text("".join(json.dumps({**stability.asdict(job), "train_views": n, "status": "finished", "psnr": 30.0, **fade}) + "\n"
                               for (_, n), job in jobs.items()))
        done = stability.load_log(log)
        assert {key for key, job in jobs.items() if job.key in done} == {("fast", more), ("paper", few), ("paper", more)}
    assert stability.sweep_fade("fast", few) == teacher_fade(few) and stability.sweep_fade("paper", few) is None
    log.write_text(json.dumps({**stability.asdict(jobs["fast", few]), "train_views": few, "status": "finished",
                               "sweep_fade": teacher_fade(few)}) + "\n")  # trained since: stands
    assert jobs["fast", few].key in stability.load_log(log)


def test_a_run_with_another_member_count_than_the_rule_now_gives_is_run_again(stability, tiny_scene, tmp_path):
    """neulf_core/members.py: two members where the budget passes over the training pixels at
    least 60 times (12 where they share the batch, the default on a CPU).  The tiny scene's 7
    training views of 48 x 36 pixels at 8192 rays a step: 89 steps make 60 passes, 18 make 12."""
    def row(steps, members=None, minutes=None, steps_done=None):
        job = stability.Job("tiny", str(tiny_scene), str(tiny_scene), 1.0, "fast", steps, 0, minutes=minutes)
        # (two members of the default share the batch on a CPU: members.default_split)
        extra = {"members": members, "members_split_used": "batch" if members > 1 else None} if members else {}
        return {**stability.asdict(job), "train_views": 7, "status": "finished", "psnr": 30.0,
                "sweep_fade": stability.sweep_fade("fast", 7), "steps_done": steps_done, **extra}

    # Members of the default share the batch on a CPU, two from 12 passes: 18 steps.
    assert not stability.trained_with_other_members(row(17))                  # one member, as then
    assert stability.trained_with_other_members(row(18))                      # logged before members: one
    assert not stability.trained_with_other_members(row(18, members=2))
    assert stability.trained_with_other_members(row(17, members=2))
    steps_rows = {"members_split": "steps"}  # a job asking for the steps split: two from 60 passes, 89 steps
    assert not stability.trained_with_other_members({**row(88), **steps_rows})
    assert stability.trained_with_other_members({**row(89), **steps_rows})
    assert not stability.trained_with_other_members({**row(89, members=2), **steps_rows, "members_split_used": "steps"})
    assert stability.trained_with_other_members(row(1000, minutes=1.0, steps_done=500))  # its pace: 339 passes
    assert not stability.trained_with_other_members(row(1000, minutes=1.0, steps_done=500, members=2))
    # logged with the passes its rule counted at the pace it timed, whatever steps it then made
    timed = {**row(1000, minutes=1.0, steps_done=500, members=1), "members_passes": 11.0}
    assert not stability.trained_with_other_members(timed)
    assert stability.trained_with_other_members({**timed, "members_passes": 13.0})  # two of the batch from 12
    assert stability.trained_with_other_members(row(1000, minutes=1.0, steps_done=500, members=1))  # (not logged)
    assert not stability.trained_with_other_members({**row(89), "truth": str(tmp_path / "gone")})  # stands
    log = tmp_path / "runs.jsonl"
    log.write_text(json.dumps(row(89)) + "\n" + json.dumps({**row(89, members=2), "seed": 1}) + "\n")
    assert len(stability.load_log(log)) == 1


def test_a_run_whose_members_split_the_budget_otherwise_than_its_job_says_is_run_again(stability, tiny_scene):
    """Since the sixty-fourth session the default's members (where the rule gives two) share the
    batch on a CPU, where the study trains: the default's rows whose two members split the steps
    (logged so, or before the column: the default's split then) are run again; a job that asked
    for a split stands with two members of it."""
    def row(members, used=None, split=None):
        job = stability.Job("tiny", str(tiny_scene), str(tiny_scene), 1.0, "fast", 1000, 0, members_split=split)
        return {**stability.asdict(job), "train_views": 7, "status": "finished", "psnr": 30.0,
                "sweep_fade": stability.sweep_fade("fast", 7), "members": members, "members_split_used": used}

    assert not stability.trained_with_other_members(row(2, "batch"))    # 1000 steps: 674 passes, two of the batch
    assert stability.trained_with_other_members(row(2, "steps"))        # ... logged with the steps split
    assert stability.trained_with_other_members(row(2))                 # ... before the column: the steps
    assert not stability.trained_with_other_members(row(2, "steps", "steps"))  # asked for
    assert not stability.trained_with_other_members(row(2, "batch", "batch"))
    assert not stability.trained_with_other_members(row(2, None, "batch"))  # (a forced split before the column)
    assert stability.trained_with_other_members(row(1, None, "batch"))  # the batch split trains two
    assert stability.split_used(row(2, None, "batch")) == "batch" and stability.split_used(row(1)) == "steps"


def test_a_run_that_refined_its_poses_with_the_depth_like_part_held_otherwise_is_run_again(stability, tiny_scene, tmp_path):
    """poses.DEPTH_LIKE_GAUGE: a logged run that refined its poses (by the check's verdict or
    forced) and held the corrections' depth-like part otherwise -- rows logged before it was
    recorded held it by a weak prior -- is run again; one that did not refine stands."""
    job = stability.Job("tiny", str(tiny_scene), str(tiny_scene), 1.0, "fast", 36, 0, pose_degrees=1.0)
    base = {**stability.asdict(job), "train_views": 7, "status": "finished", "psnr": 30.0,
            "sweep_fade": stability.sweep_fade("fast", 7), **two_members(stability)}  # (24 passes: two, as the rule gives)
    held = stability.DEPTH_LIKE_GAUGE
    assert stability.trained_with_another_pose_gauge({**base, "pose_check_refining": True})
    assert stability.trained_with_another_pose_gauge({**base, "pose_check_refining": None, "refine_poses": True})
    assert not stability.trained_with_another_pose_gauge({**base, "pose_check_refining": True, "pose_gauge": held})
    assert not stability.trained_with_another_pose_gauge({**base, "pose_check_refining": False})
    assert not stability.trained_with_another_pose_gauge({**base, "pose_check_refining": None, "refine_poses": False})
    assert_stale_row_reported_until_run_again(stability, tmp_path / "runs.jsonl", {**base, "pose_check_refining": True},
                                              {**base, "seed": 1, "pose_check_refining": True, "pose_gauge": held},
                                              stability.older_pose_gauge_note, "1 runs that refined their poses")


def assert_stale_row_reported_until_run_again(stability, log, stale_row: dict, fresh_row: dict, note, words: str):
    """load_log: of the two logged rows the stale one is not done (the study runs it again),
    and the report shows it from `older` until then, its note saying `words`."""
    log.write_text(json.dumps(stale_row) + "\n" + json.dumps(fresh_row) + "\n")
    assert [row["seed"] for row in stability.load_log(log).values()] == [fresh_row["seed"]]
    older = {}
    stability.load_log(log, older)
    assert [row["seed"] for row in older.values()] == [stale_row["seed"]]
    assert words in " ".join(note(list(older.values())))


def test_a_default_pose_noise_run_scored_before_the_noise_s_depth_like_part_is_run_again(stability, tmp_path):
    """A default pose-noise run logged without the score with the held-out views moved by the
    noise's depth-like part is run again for it (reported as logged until then); forced
    refinement, no noise, or the score present: it stands.  The table then reads the score,
    its 0° cell the plain one."""
    job = stability.Job("lambertian", "x", "x", 1.0, "fast", 80, 0, pose_degrees=1.0)
    row = {**stability.asdict(job), "status": "finished", "psnr": 28.0}
    assert stability.scored_without_noise_part(row)
    assert not stability.scored_without_noise_part({**row, "psnr_noise_part_aligned": 29.0})
    assert not stability.scored_without_noise_part({**row, "refine_poses": True})
    assert not stability.scored_without_noise_part({**row, "pose_degrees": 0.0})
    log = tmp_path / "runs.jsonl"
    log.write_text(json.dumps(row) + "\n" + json.dumps({**row, "seed": 1, "psnr_noise_part_aligned": 29.0}) + "\n")
    older = {}
    assert [r["seed"] for r in stability.load_log(log, older, rescore=True).values()] == [1]
    assert [r["seed"] for r in older.values()] == [0]
    assert len(stability.load_log(log)) == 2  # (other scripts' logs, e.g. seed_scatter's, keep their rows)
    rows = [{**row, "seed": s, "psnr_noise_part_aligned": 29.0 + s / 10} for s in range(3)]
    rows += [{**row, "seed": s, "pose_degrees": 0.0, "psnr": 31.0 + s / 10} for s in range(3)]
    table = stability.pose_score_table(rows, "psnr_noise_part_aligned", "moved", zero_column="psnr")
    line = next(text for text in table if text.startswith(f"| {stability.POSE_SETTING_LABELS[None]}, lambertian |"))
    cells = [c.strip() for c in line.strip("|").split("|")][1:]
    assert cells[0] == "31.10 ± 0.20" and cells[stability.POSE_DEGREES.index(1.0)] == "29.10 ± 0.20"


def test_members_that_refined_their_poses_apart_are_run_again(stability, tiny_scene, tmp_path):
    """Since the later members follow the first one's verdict on the poses (members.py), a
    logged run of several members that refined poses apart, or whose second member checked
    its own, is run again; one trained without refinement, or of one member, stands."""
    job = stability.Job("tiny", str(tiny_scene), str(tiny_scene), 1.0, "fast", 89, 0, pose_degrees=1.0)
    base = {**stability.asdict(job), "train_views": 7, "status": "finished", "psnr": 30.0,
            "sweep_fade": stability.sweep_fade("fast", 7)}
    assert stability.trained_with_members_own_poses({**base, "members": 2, "pose_check_refining": True})
    assert not stability.trained_with_members_own_poses({**base, "members": 2, "pose_check_refining": True,
                                                         "member_poses": stability.MEMBER_POSES})
    assert not stability.trained_with_members_own_poses({**base, "members": 2, "pose_check_refining": True,
                                                         "member_poses": stability.MEMBER_POSES_CORRECTIONS_ONLY})
    # The first member's check dropped the refinement: logged before the second followed its
    # verdict, the second ran its own check -- again; logged since, or forced off, it stands.
    assert stability.trained_with_members_own_poses({**base, "members": 2, "pose_check_refining": False})
    assert stability.trained_with_members_own_poses({**base, "members": 2, "pose_check_refining": False,
                                                     "member_poses": stability.MEMBER_POSES_CORRECTIONS_ONLY})
    assert not stability.trained_with_members_own_poses({**base, "members": 2, "pose_check_refining": False,
                                                         "member_poses": stability.MEMBER_POSES})
    assert not stability.trained_with_members_own_poses({**base, "members": 2, "pose_check_refining": None,
                                                         "refine_poses": False})
    assert not stability.trained_with_members_own_poses({**base, "members": 1, "pose_check_refining": True})
    log = tmp_path / "runs.jsonl"
    log.write_text(json.dumps({**base, "members": 2, "pose_check_refining": True}) + "\n")
    assert stability.load_log(log) == {}


def test_the_default_only_plan_is_the_36_configurations_a_user_runs_in_their_order(stability, tmp_path):
    """--defaults-only keeps the fast preset with no rule forced (the paper's network, forced
    pose refinement and the forced-off colour transforms of the jittered photos go), three
    seeds each; --by-configuration runs each configuration's seeds together; --scenes keeps
    the named scenes only."""
    args = stability.parse_args(["--defaults-only", "--only", "views,variants,exposure,pose"])
    scenes = {name: tmp_path / name for name in ("lambertian", "shiny", "fine", "jitter1", "canclip", "canclip_jitter1", "hci")}
    jobs = stability.plan(args, scenes)
    configurations = {stability.replace(job, seed=0).key for job in jobs}
    assert len(configurations) == 36 and len(jobs) == 108
    assert all(job.preset == "fast" and job.refine_poses is None for job in jobs)
    for jittered in ("jitter1", "canclip_jitter1"):
        assert [job.appearance for job in jobs if job.scene == jittered] == [None] * 3  # the rule's choice only
    everything = stability.plan(stability.parse_args(["--only", "views,variants,exposure,pose"]), scenes)
    assert {job.key for job in jobs} == {job.key for job in everything if stability.is_default_run(job)}

    order = sorted(jobs, key=stability.job_order(jobs, by_configuration=True))
    for start in range(0, len(order), 3):  # one configuration's three seeds, then the next
        group = order[start:start + 3]
        assert [job.seed for job in group] == [0, 1, 2]
        assert len({stability.replace(job, seed=0).key for job in group}) == 1
    seed_first = sorted(jobs, key=stability.job_order(jobs))
    assert {job.seed for job in seed_first[:36]} == {0}  # the study's own order: every configuration once first

    only = stability.plan(stability.parse_args(["--defaults-only", "--only", "pose", "--scenes", "canclip"]), scenes)
    assert {job.scene for job in only} == {"canclip"} and len(only) == 12 * 3


def test_pack_copies_the_real_captures_at_their_training_scale(stability, tiny_scene, tmp_path, monkeypatch):
    """--pack: photos resized as training resizes them, so the copy at scale 1 trains on the
    same pixels and intrinsics as the original at the study's scale."""
    from neulf_core.scene import load_scene

    for name in ("lambertian", "shiny", "fine", "lambertian_jitter1"):  # stand-ins for the renders
        (tmp_path / "synth" / name / "ground_truth").mkdir(parents=True)
        for part in ("images", "sparse_gt"):
            (tmp_path / "synth" / name / part).mkdir()
        (tmp_path / "synth" / name / "ground_truth" / "cameras.json").write_text("{}")
        (tmp_path / "synth" / name / "summary.json").write_text("{}")
    scenes = {name: tmp_path / "synth" / folder for name, folder in
              (("lambertian", "lambertian"), ("shiny", "shiny"), ("fine", "fine"), ("jitter1", "lambertian_jitter1"))}
    scenes["canclip"] = tiny_scene
    args = stability.parse_args(["--canclip-scale", "0.5"])
    printed = stability.pack(args, scenes, tmp_path / "packed")
    assert f"--canclip {tmp_path / 'packed' / 'canclip'} --canclip-scale 1" in printed
    original, packed = load_scene(tiny_scene), load_scene(tmp_path / "packed" / "canclip")
    for a, b in zip(original.views, packed.views):
        assert np.array_equal(a.load_image(0.5), b.load_image(1.0))
        assert np.allclose(a.scaled_camera(0.5).calibration_matrix(), b.scaled_camera(1.0).calibration_matrix())
    assert (tmp_path / "packed" / "scenes" / "lambertian_jitter1" / "ground_truth" / "cameras.json").is_file()


def test_a_real_captures_exposures_jittered_as_a_camera_would(stability, tiny_scene, tmp_path):
    """Each photo of the copy is the original brightened or darkened by its drawn stops on
    linear light (photo_exposures reads them back), with the same model; made once, and made
    again for another source."""
    import torch

    from neulf_core.appearance import photo_exposures
    from neulf_core.scene import load_scene

    out = stability.jitter_capture_exposures(tmp_path, tiny_scene)
    drawn = json.loads((out / "exposures.json").read_text())["exposures"]
    assert max(abs(k) for k in drawn.values()) <= 1.0 and len(set(drawn.values())) == len(drawn)
    original, jittered = load_scene(tiny_scene), load_scene(out)
    assert [v.name for v in original.views] == [v.name for v in jittered.views]
    for a, b in zip(original.views, jittered.views):
        assert np.allclose(a.camera.calibration_matrix(), b.camera.calibration_matrix()) and np.allclose(a.R, b.R)
        both = torch.from_numpy(np.concatenate([a.load_image(1.0), b.load_image(1.0)]).reshape(-1, 3))
        views = torch.arange(2).repeat_interleave(len(both) // 2)
        before, after = photo_exposures(both, views, 2)
        expected = drawn[a.image_path.name]
        assert after - before == pytest.approx(expected, abs=0.15 if expected > 0 else 0.05), a.name  # (brightening clips)
    stamp = (out / "exposures.json").stat().st_mtime_ns
    assert stability.jitter_capture_exposures(tmp_path, tiny_scene) == out and (out / "exposures.json").stat().st_mtime_ns == stamp


def test_the_fewer_views_target_states_its_standard_error(stability):
    """Three seeds' means are each uncertain: the target line says by how much the loss is."""
    def row(fraction, seed, value):
        return {**stability.base("canclip", "fast", fraction=fraction), "seed": seed, "status": "finished", "psnr": value}
    rows = [row(1.0, s, v) for s, v in enumerate((36.2, 36.3, 36.25))]
    rows += [row(0.25, s, v) for s, v in enumerate((34.9, 34.5, 34.7))]
    line = next(line for line in stability.targets(rows) if "views on canclip" in line)
    error = math.sqrt(0.05 ** 2 / 3 + 0.2 ** 2 / 3)  # sample standard deviations 0.05 and 0.2 dB
    assert f"1.55 ± {error:.2f} (standard error, 3 / 3 seeds) dB lost" in line and line.endswith("MISSED")
    single = [r for r in rows if r["seed"] == 0]  # one seed each: no scatter to state
    assert "standard error" not in next(line for line in stability.targets(single) if "views on canclip" in line)


def test_a_deep_scene_trained_with_other_surfaces_is_run_again(stability, tiny_scene, tmp_path):
    """Since deep scenes train with a back surface (rules.default_back_surface) whose features
    the fast preset blends (DisparityConfig.back_surface_blend), a fast run of one logged
    without `back_surface` (or with an empty CSV cell), or with a back surface but no blend or
    the colour blend, is trained again; one logged since, a shallow scene's, the paper
    network's and one that never recorded its depth stand."""
    # (36 steps, 24 passes: two members by the members rule, as logged, so only the surface decides)
    fast = {**stability.asdict(stability.Job("tiny", str(tiny_scene), str(tiny_scene), 1.0, "fast", 36, 0)),
            "train_views": 7, "status": "finished", "psnr": 30.0, "sweep_fade": stability.sweep_fade("fast", 7),
            **two_members(stability)}
    current = {"back_surface": True, "back_surface_blend": "features"}
    for deep in (True, False):
        run = {**fast, "deep_scene": deep}
        paper = {**run, "preset": "paper", "sweep_fade": None}
        assert stability.trained_with_another_surface_mix(run) is deep
        assert stability.trained_with_another_surface_mix({**run, "back_surface": None}) is deep  # from the CSV
        assert not stability.trained_with_another_surface_mix({**run, **current})
        assert stability.trained_with_another_surface_mix({**run, "back_surface": True})  # logged before the blend
        assert stability.trained_with_another_surface_mix({**run, **current, "back_surface_blend": "colour"})
        assert not stability.trained_with_another_surface_mix({**run, "back_surface": False})  # forced off
        assert not stability.trained_with_another_surface_mix(paper)
    assert not stability.trained_with_another_surface_mix(fast)  # no depth recorded: it stands
    log = tmp_path / "runs.jsonl"
    deep = {**fast, "deep_scene": True}
    log.write_text("".join(json.dumps(row) + "\n" for row in
                           (deep, {**deep, "seed": 1, **current}, {**deep, "seed": 2, "back_surface": True})))
    assert [row["seed"] for row in stability.load_log(log).values()] == [1]
    older = {}
    stability.load_log(log, older)
    assert sorted(row["seed"] for row in older.values()) == [0, 2]  # kept for the report until re-run


def test_a_run_whose_losses_the_rule_now_decides_otherwise_is_run_again(stability, tiny_scene, tmp_path):
    """A fast run of 14 photos of a deep scene logged with the multi-view losses on to its end
    is trained again where the pose check found its poses right and its colours were not learned
    (the losses now stop there), and stands where the check kept refining, where none ran, or
    where the colours were learned; runs whose losses were asked for, and minutes runs, stand."""
    from neulf_core.rules import CONSISTENCY_ALWAYS_MAX_VIEWS

    # (66 steps, 22 passes: enough for the losses, and two members by the members rule, as logged;
    # the surfaces and the fade as the default's now)
    run = {**stability.asdict(stability.Job("tiny", str(tiny_scene), str(tiny_scene), 1.0, "fast", 66, 0)),
           "train_views": 14, "deep_scene": True, "multiview_losses": True, "status": "finished",
           "pose_check_refining": False, "appearance_used": False, "sweep_fade": stability.sweep_fade("fast", 14),
           "back_surface": True, "back_surface_blend": "features", **two_members(stability)}
    assert stability.trained_with_another_losses_rule(run)
    assert not stability.trained_with_another_losses_rule({**run, "losses_until_step": 100})      # stopped at the check
    assert stability.trained_with_another_losses_rule({**run, "multiview_losses": False})          # off from the start
    assert not stability.trained_with_another_losses_rule({**run, "pose_check_refining": True})   # the check kept refining
    assert not stability.trained_with_another_losses_rule({**run, "pose_check_refining": None, "refine_poses": True})
    assert not stability.trained_with_another_losses_rule({**run, "pose_check_refining": None, "refine_poses": False})
    assert not stability.trained_with_another_losses_rule({**run, "appearance_used": True})       # colours learned
    assert not stability.trained_with_another_losses_rule({**run, "train_views": CONSISTENCY_ALWAYS_MAX_VIEWS})
    assert not stability.trained_with_another_losses_rule({**run, "consistency": True})           # asked for
    assert not stability.trained_with_another_losses_rule({**run, "minutes": 1.0})                # counted at its rate
    assert stability.trained_with_another_losses_rule({**run, "deep_scene": False, "losses_until_step": 100})  # shallow
    assert not stability.trained_with_another_losses_rule({**run, "deep_scene": False, "multiview_losses": False})
    refining = {**run, "pose_check_refining": True}
    assert stability.trained_with_another_losses_rule({**refining, "steps": 1})                   # too few passes: off
    assert not stability.trained_with_another_losses_rule({**refining, "steps": 1, "multiview_losses": False})
    log = tmp_path / "runs.jsonl"
    log.write_text("".join(json.dumps(row) + "\n" for row in (run, {**run, "seed": 1, "losses_until_step": 100})))
    assert [row["seed"] for row in stability.load_log(log).values()] == [1]


def test_the_losses_table_says_how_long_the_defaults_losses_ran(stability):
    runs = [{"seed": 1, "psnr": 31.0, "multiview_losses": True, "losses_until_step": 100},
            {"seed": 0, "psnr": 31.2, "multiview_losses": True, "losses_until_step": None},
            {"seed": 2, "psnr": 31.1, "multiview_losses": False}]
    runs = [{**run, "status": "finished"} for run in runs]
    assert stability.losses_default_cell(runs).endswith("(on, to step 100, off)")
    assert stability.losses_default_cell(runs).startswith(stability.cell(runs))
    assert stability.losses_default_cell([]) == "-"


def test_a_run_that_started_its_field_again_otherwise_than_the_rule_now_decides_is_run_again(stability, tiny_scene,
                                                                                             tmp_path):
    """pose_check.poses_far_off: a logged run of a shallow scene that refined its poses and started
    its field again (or not) otherwise than the rule now decides from what it logged is run
    again.  Rows logged before the far-off check was: the default's judged by its pose check's
    statistic (the preset's points held its first steps), forced ones stand (no points: the
    old rule's bar)."""
    from neulf_core.pose_check import FAR_OFF_POSE_DEGREES, MANY_PHOTOS_FAR_OFF_POSE_DEGREES

    job = stability.Job("tiny", str(tiny_scene), str(tiny_scene), 1.0, "fast", 80, 0, pose_degrees=0.5)
    between = (FAR_OFF_POSE_DEGREES + MANY_PHOTOS_FAR_OFF_POSE_DEGREES) / 2
    base = {**stability.asdict(job), "train_views": 26, "status": "finished", "psnr": 30.0, "deep_scene": False,
            "sweep_fade": stability.sweep_fade("fast", 26), "pose_gauge": stability.DEPTH_LIKE_GAUGE,
            "pose_check_refining": True, **two_members(stability)}  # (15 passes: two members, as the rule gives)
    stale = stability.trained_with_another_restart_rule
    assert stale({**base, "field_restarted": True, "pose_check_degrees": between})  # many photos, points: no longer
    assert not stale({**base, "field_restarted": False, "pose_check_degrees": between})
    assert not stale({**base, "field_restarted": True, "pose_check_degrees": between, "train_views": 13})  # few: still
    assert stale({**base, "field_restarted": False, "far_off_degrees": between, "train_views": 13})
    assert not stale({**base, "field_restarted": False, "far_off_degrees": between, "far_off_points_held": True})
    assert stale({**base, "field_restarted": False, "far_off_degrees": between, "far_off_points_held": False})
    far = {**base, "field_restarted": True, "far_off_degrees": MANY_PHOTOS_FAR_OFF_POSE_DEGREES}
    assert not stale({**far, "restart_geometry_only": True, "restart_depth_layers": True})
    assert stale({**far, "restart_geometry_only": True})  # before the fifty-seventh: the depth layers kept
    assert stale(far)  # restarted before the fifty-sixth session: everything started again, not the geometry alone
    assert stale({**far, "restart_geometry_only": True, "train_views": 13, "far_off_degrees": 1.0})  # few: everything
    assert not stale({**base, "field_restarted": True, "pose_check_degrees": between, "deep_scene": True})
    forced = {**base, "pose_check_refining": None, "refine_poses": True, "pose_check_degrees": None}
    assert not stale({**forced, "field_restarted": True, "restart_depth_layers": True})  # the old bar, which forced runs keep
    assert stale({**forced, "field_restarted": True})  # ... but its depth layers were not made smoother then
    assert stale({**forced, "field_restarted": False, "far_off_degrees": between})  # no points: restarts
    assert not stale({**base, "pose_check_refining": False, "field_restarted": False, "pose_check_degrees": 0.02})
    assert_stale_row_reported_until_run_again(
        stability, tmp_path / "runs.jsonl", {**base, "field_restarted": True, "pose_check_degrees": between},
        {**base, "seed": 1, "field_restarted": False, "far_off_degrees": between},
        stability.older_restart_rule_note, "1 runs started their field again")


def test_a_missing_capture_does_not_drop_its_rows_from_docs(stability, tmp_path, capsys):
    """The study writes docs/ from the runs it planned: with CanClip not where --canclip says (a
    checkout without ../shared/data) it had rewritten docs/stability.csv with 143 of its 289 rows,
    exit 0.  It now says which capture is missing and writes nothing; into another --docs folder
    it writes the part it can."""
    table = stability.DOCS / "stability.csv"
    before = table.stat().st_mtime_ns
    stability.main(["--report-only", "--canclip", str(tmp_path / "none"), "--cache", str(tmp_path / "cache")])
    said = capsys.readouterr().out
    assert "skip: the captures canclip" in said and "Nothing was written" in said, said
    assert table.stat().st_mtime_ns == before and not (tmp_path / "cache").exists()
    args = stability.parse_args(["--canclip", str(tmp_path / "none"), "--docs", str(tmp_path / "part")])
    assert stability.missing_captures_would_be_dropped(args) is False

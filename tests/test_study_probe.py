"""benchmarks/study_probe.py: a probe runs the stability study's job with a patch executed
first and the pose noise drawn from the seed asked for, and summarises the seeds."""

import json
import math

import pytest


@pytest.fixture(scope="module")
def probe(benchmark_script):
    return benchmark_script("study_probe")


def test_a_probe_runs_the_patch_then_the_job_under_its_noise_draw(probe, tiny_scene, tmp_path, monkeypatch):
    import stability  # (the module run_one imports: benchmarks/ is on sys.path)

    monkeypatch.setattr(stability, "POSE_NOISE_SEED", stability.POSE_NOISE_SEED)  # run_one sets it; restored after
    marker = tmp_path / "patched"
    patch = tmp_path / "patch.py"
    patch.write_text(f"import pathlib\npathlib.Path({str(marker)!r}).write_text('ran')\n")
    job = stability.Job("tiny", str(tiny_scene), str(tiny_scene), 1.0, "fast", 3, 0, pose_degrees=1.0)
    from dataclasses import asdict

    original_train = stability.train
    monkeypatch.setattr(stability, "train", original_train)  # run_one wraps it to keep the model; restored after
    row = probe.run_one((asdict(job), str(patch), 101, str(probe.HERE.parent), str(tmp_path / "kept")))
    assert marker.read_text() == "ran"
    # --keep: the trained model survives the study's temporary folder, and it renders the row's score
    kept = probe.kept_model_dir(tmp_path / "kept", asdict(job), 101)
    assert kept.name == "tiny-views1-pose1deg-draw101-seed0" and (kept / "model.pt").is_file()
    held = stability.split_views(stability.load_any(tiny_scene))[1]
    assert stability.score_views(kept, held, 1.0)["psnr"] == pytest.approx(row["psnr"], abs=1e-9)
    assert row["status"] == "finished" and row["draw"] == 101 and row["steps_done"] == 3
    # A pose-noise job is also scored with the held-out views moved by the noise's depth-like part.
    assert math.isfinite(row["psnr_noise_part_aligned"]) and row["psnr_per_view_noise_part_aligned"].count("=") == 2
    # The draw is the study's noise seed while the job runs: another draw turns the cameras otherwise.
    train = stability.split_views(stability.load_any(tiny_scene))[0]
    spacing = stability.rig_spacing(train)
    turned = {}
    for draw in (101, 202):
        monkeypatch.setattr(stability, "POSE_NOISE_SEED", draw)
        turned[draw] = stability.perturb_poses(train, 1.0, spacing)[0].R
    assert abs(turned[101] - turned[202]).max() > 1e-4


def test_the_summary_gives_each_noise_and_draw_its_seeds_mean_and_spread(probe):
    rows = [{"pose_degrees": 0.5, "draw": 1234, "seed": s, "status": "finished", "psnr": p}
            for s, p in ((1, 30.2), (0, 30.0))]
    rows.append({"pose_degrees": 0.5, "draw": 101, "seed": 0, "status": "crashed", "psnr": float("nan"),
                 "error": "RuntimeError: boom"})
    lines = probe.summary_lines(rows, "try")
    assert lines[0] == "try: pose noise 0.5°, noise draw 101, seeds 0:  (1 did not finish: RuntimeError: boom)"
    assert lines[1] == "try: pose noise 0.5°, noise draw 1234, seeds 0,1: 30.00 / 30.20: 30.10 ± 0.141 sd, range 0.20"
    assert len(lines) == 2  # (no other scores in these rows)
    for row, aligned in zip(rows, (31.0, 31.4)):
        row["psnr_noise_part_aligned"] = aligned
    lines = probe.summary_lines(rows, "try")
    assert lines[2] == "    held-out views moved by the noise's depth-like part: 31.40 / 31.00: 31.20 ± 0.283 sd"


def test_the_command_line_refuses_a_missing_patch_or_checkout(probe, tmp_path):
    with pytest.raises(SystemExit, match="no file"):
        probe.main(["--patch", str(tmp_path / "missing.py")])
    with pytest.raises(SystemExit, match="holds no neulf_core"):
        probe.main(["--root", str(tmp_path)])
    assert json.dumps(probe.parse_list("0-3", int)) == "[0, 1, 2, 3]"
    assert probe.parse_list("0.25,0.5") == [0.25, 0.5]


def test_a_minutes_budget_and_fern_plan_the_study_s_jobs(probe, tmp_path):
    import stability

    fern = tmp_path / "fern"
    fern.mkdir()
    args = probe.parse_args(["--scene", "fern", "--fraction", "0.25", "--minutes", "1", "--seeds", "0-1",
                             "--fern", str(fern)])
    tasks = probe.plan(args, stability)
    jobs = [stability.Job(**task[0]) for task in tasks]
    assert [job.seed for job in jobs] == [0, 1]
    # as the study's losses jobs: a minutes budget and no step count, at the study's scale of fern
    assert all(job.minutes == 1.0 and job.steps == 0 and job.scale == 0.5 and job.path == str(fern) for job in jobs)
    held = []
    assert stability.train_config(jobs[0], held).minutes == 1.0 and stability.train_config(jobs[0], held).steps is None
    # without --minutes the steps budget stands
    steps_job = stability.Job(**probe.plan(probe.parse_args(["--scene", "fern", "--fern", str(fern), "--seeds", "0"]),
                                           stability)[0][0])
    assert steps_job.steps == 1000 and not steps_job.minutes
    with pytest.raises(SystemExit, match="no scene 'fern'"):
        probe.plan(probe.parse_args(["--scene", "fern", "--fern", str(tmp_path / "missing")]), stability)

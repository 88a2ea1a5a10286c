"""benchmarks/seed_scatter.py: the seed scatter's jobs are the stability study's, and its summary."""

from pathlib import Path

import numpy as np
import pytest


@pytest.fixture(scope="module")
def scatter(benchmark_script):
    return benchmark_script("seed_scatter")


def test_seeds_parse_as_ranges_and_lists(scatter):
    assert scatter.parse_seeds("0-7") == list(range(8))
    assert scatter.parse_seeds("0,1,2") == [0, 1, 2]
    assert scatter.parse_seeds("0-2,5") == [0, 1, 2, 5]


def test_summary_counts_the_triples_inside_the_target(scatter):
    s = scatter.summary([30.0, 30.1, 30.15, 30.5])
    assert s["n"] == 4 and s["triples"] == 4
    assert s["triples_inside"] == 1  # only (30.0, 30.1, 30.15): every other triple holds 30.5
    assert s["range"] == pytest.approx(0.5) and s["mean"] == pytest.approx(30.1875)
    assert s["sd"] == pytest.approx(np.std([30.0, 30.1, 30.15, 30.5], ddof=1))


def test_chance_inside_matches_draws_of_a_normal_scatter(scatter):
    rng = np.random.default_rng(0)
    for sd in (0.05, 0.1, 0.2):
        draws = rng.normal(0.0, sd, size=(200_000, 3))
        simulated = float(np.mean(draws.max(1) - draws.min(1) <= scatter.TARGET_DB))
        assert scatter.chance_inside(sd) == pytest.approx(simulated, abs=0.005)
    assert scatter.chance_inside(0.0) == 1.0


def test_jobs_are_the_stability_studys_and_the_table_reads_their_rows(scatter):
    stability = scatter.stability
    scenes = {"lambertian": Path("/scenes/lambertian"), "canclip": Path("/data/canclip")}
    scales = {"lambertian": 0.5, "canclip": 0.25}
    jobs = scatter.plan(["synthetic-0.1deg", "canclip-6-photos"], [0, 1, 2, 3], 1000, scenes, scales)
    study_job = stability.Job("lambertian", "/scenes/lambertian", "/scenes/lambertian", 0.5, "fast", 1000, 2,
                              pose_degrees=0.1, colour_start=stability.preset_colour_start("fast"))
    assert jobs["synthetic-0.1deg"][2].key == study_job.key  # the very run the study logs
    assert [job.fraction for job in jobs["canclip-6-photos"]] == [0.25] * 4
    done = {job.key: {"status": "finished", "psnr": 30.0 + 0.05 * job.seed} for job in jobs["synthetic-0.1deg"]}
    lines = scatter.table(done, jobs).splitlines()  # in CONFIGURATIONS' order, not the run's
    assert lines[3].startswith("| synthetic-0.1deg | 30.00 30.05 30.10 30.15 | 30.07 |")
    assert "| 4 of 4 |" in lines[3]
    assert lines[2] == "| canclip-6-photos | 0 of 4 finished | | | | | |"


def logged_runs(scatter, tmp_path, psnr_of) -> tuple[Path, Path, Path]:
    """A CanClip stand-in folder, a run log whose rows `psnr_of(label, steps)` lists as
    (label, steps, base PSNR) -- seeds 0-2 each, base + 0.01 * seed -- and an empty docs
    folder: what --report-only reads and writes."""
    import json
    from dataclasses import asdict

    capture, cache, docs = tmp_path / "canclip", tmp_path / "cache", tmp_path / "docs"
    for folder in (capture, cache, docs):
        folder.mkdir()
    with open(cache / "runs.jsonl", "w") as log:
        for label, steps, base in psnr_of:
            for job in scatter.plan([label], [0, 1, 2], steps, {"canclip": capture}, {"canclip": 0.25})[label]:
                log.write(json.dumps({**asdict(job), "status": "finished", "psnr": base + 0.01 * job.seed}) + "\n")
    return capture, cache, docs


def report_arguments(capture: Path, cache: Path, docs: Path) -> list[str]:
    return ["--seeds", "0-2", "--canclip", str(capture), "--cache", str(cache), "--docs", str(docs), "--report-only"]


def test_report_only_rewrites_the_generated_block_and_keeps_the_text_around_it(scatter, tmp_path):
    capture, cache, docs = logged_runs(scatter, tmp_path, [("canclip", 1000, 36.2)])
    (docs / "SEED_SCATTER.md").write_text(f"# By hand\n\n{scatter.MARKER_BEGIN}\nold\n{scatter.MARKER_END}\n\nAfter.\n")
    scatter.main(["--configurations", "canclip"] + report_arguments(capture, cache, docs))
    text = (docs / "SEED_SCATTER.md").read_text()
    assert text.startswith("# By hand\n") and text.endswith("\nAfter.\n") and "old" not in text
    assert "| canclip | 36.20 36.21 36.22 | 36.21 | 0.010 | 0.02 | 1 of 1 | 100 % |" in text
    assert len((docs / "seed_scatter.csv").read_text().splitlines()) == 1 + 3


def test_another_budget_writes_its_own_block_and_csv_beside_the_studys(scatter, tmp_path):
    capture, cache, docs = logged_runs(scatter, tmp_path, [("canclip", 1000, 10.0), ("canclip", 3000, 30.0)])
    (docs / "SEED_SCATTER.md").write_text("# By hand\n")
    common = ["--configurations", "canclip"] + report_arguments(capture, cache, docs)
    scatter.main(common)
    scatter.main(common + ["--steps", "3000", "--machine", "an H100 and a CPU"])
    scatter.main(common)  # the study's block again: the other budget's stays
    text = (docs / "SEED_SCATTER.md").read_text()
    assert text.count("| canclip | 10.00 10.01 10.02 |") == 1 and text.count("| canclip | 30.00 30.01 30.02 |") == 1
    assert "on an H100 and a CPU; fast: 3000 steps" in text
    assert (docs / "seed_scatter.csv").is_file() and (docs / "seed_scatter_3000.csv").is_file()
    assert scatter.outputs_for(1000)[1] == scatter.MARKER_BEGIN
    # runs whose members split the batch get a CSV and a block of their own, beside the default's
    import json
    from dataclasses import asdict

    with open(cache / "runs.jsonl", "a") as log:
        for job in scatter.plan(["canclip"], [0, 1, 2], 1000, {"canclip": capture}, {"canclip": 0.25},
                                members_split="batch")["canclip"]:
            log.write(json.dumps({**asdict(job), "status": "finished", "psnr": 50.0 + 0.01 * job.seed}) + "\n")
    scatter.main(common + ["--members-split", "batch"])
    text = (docs / "SEED_SCATTER.md").read_text()
    assert scatter.outputs_for(1000, "batch") == (
        "seed_scatter_members_batch.csv", "<!-- seed scatter with members splitting the batch begins (generated by "
        "benchmarks/seed_scatter.py) -->", "<!-- seed scatter with members splitting the batch ends -->")
    assert scatter.outputs_for(3000, "batch")[0] == "seed_scatter_3000_members_batch.csv"
    assert scatter.outputs_for(1000, "batch")[1] in text and text.count("| canclip | 10.00 10.01 10.02 |") == 1
    assert text.count("| canclip | 50.00 50.01 50.02 |") == 1
    assert "| canclip | 10.01 ± 0.010 | 1 of 1 | 50.01 ± 0.010 | 1 of 1 | +40.00 | 3 of 3 | - / - |" in text  # paired
    assert "fast: 1000 steps; members split the batch (`--members-split batch`); seeds 0-2" in text
    assert (docs / "seed_scatter_members_batch.csv").is_file()


def test_a_run_of_some_configurations_keeps_the_others_rows_and_lines(scatter, tmp_path):
    capture, cache, docs = logged_runs(scatter, tmp_path, [("canclip", 1000, 36.2), ("canclip-6-photos", 1000, 34.8)])
    common = report_arguments(capture, cache, docs)
    scatter.main(["--configurations", "canclip-6-photos"] + common)
    scatter.main(["--configurations", "canclip"] + common)  # the 6-photo rows stay, in CONFIGURATIONS' order
    text = (docs / "SEED_SCATTER.md").read_text()
    assert text.index("| canclip | 36.20 36.21 36.22 |") < text.index("| canclip-6-photos | 34.80 34.81 34.82 |")
    rows = (docs / "seed_scatter.csv").read_text().splitlines()
    assert len(rows) == 1 + 6 and rows[1].startswith("canclip,fast,1.0,") and rows[4].startswith("canclip,fast,0.25,")
    kept = scatter.earlier_rows(docs / "seed_scatter.csv", ["canclip"])
    assert list(kept) == ["canclip-6-photos"] and [row["seed"] for row in kept["canclip-6-photos"]] == ["0", "1", "2"]


def test_two_starts_can_be_forced_off_or_on_for_a_comparison(scatter):
    """--two-starts off / on reaches the trainer (the default's rule otherwise), and the
    few-photo pose-noise lines are asked for by name, not trained by default."""
    stability = scatter.stability
    scenes, scales = {"canclip": Path("/data/canclip")}, {"canclip": 0.25}
    label = "canclip-6-photos-0.25deg"
    for flag, forced in (("rule", None), ("on", True), ("off", False)):
        args = scatter.parse_args(["--configurations", label, "--two-starts", flag])
        job = scatter.plan([label], [0], 3000, scenes, scales, scatter.TWO_STARTS[args.two_starts])[label][0]
        assert (job.fraction, job.pose_degrees, job.two_starts) == (0.25, 0.25, forced)
        assert stability.train_config(job, []).two_starts is forced
    ruled = scatter.plan([label], [0], 3000, scenes, scales)[label][0]
    assert ruled.key != stability.replace(ruled, two_starts=False).key  # logged apart
    jittered = scatter.plan([label], [0], 3000, scenes, scales, None, 0.5)[label][0]
    assert stability.train_config(jittered, []).pixel_jitter == 0.5 and jittered.key != ruled.key
    assert scatter.parse_args(["--pixel-jitter", "0.25"]).pixel_jitter == 0.25
    assert label not in scatter.parse_args([]).configurations.split(",")
    assert scatter.parse_args([]).configurations.split(",") == scatter.DEFAULT_CONFIGURATIONS


def test_one_start_against_two_reads_both_logs_seed_by_seed(scatter, tmp_path):
    """--against-one-start: the two starts' log (--cache) beside the one-start log, each score
    (the pose-fitted one where the runs have it) with its scatter, and the start each seed kept."""
    import json
    from dataclasses import asdict

    label = "canclip-6-photos-0.25deg"
    capture, docs = tmp_path / "canclip", tmp_path / "docs"
    capture.mkdir(), docs.mkdir()
    logs = {}
    for name, two_starts, base, kept in (("one", False, 34.6, ""), ("two", None, 34.5, "second")):
        logs[name] = tmp_path / name
        logs[name].mkdir()
        jobs = scatter.plan([label], [0, 1, 2], 3000, {"canclip": capture}, {"canclip": 0.25}, two_starts)[label]
        (logs[name] / "runs.jsonl").write_text("".join(
            json.dumps({**asdict(job), "status": "finished", "psnr": base + 0.1 * job.seed,
                        "psnr_pose_fitted": base + 1 + 0.01 * job.seed, "start_kept": kept or None}) + "\n" for job in jobs))
    scatter.main(["--configurations", label, "--seeds", "0-2", "--steps", "3000", "--canclip", str(capture),
                  "--cache", str(logs["two"]), "--against-one-start", str(logs["one"]), "--docs", str(docs)])
    text = (docs / "SEED_SCATTER.md").read_text()
    assert (f"| {label} | PSNR | 34.60 34.70 34.80 | 34.70 ± 0.100 | 1 of 1 | 34.50 34.60 34.70 | 34.60 ± 0.100 | 1 of 1 "
            f"| 2 2 2 |") in text
    assert f"| {label} | PSNR, held-out poses fitted | 35.60 35.61 35.62 | 35.61 ± 0.010 |" in text
    assert scatter.comparison_outputs(3000)[1] in text
    rows = (docs / "seed_scatter_starts_3000.csv").read_text().splitlines()
    assert len(rows) == 1 + 6 and sum(",second," in row for row in rows) == 3

    # A fresh machine has neither log: the block comes again from the CSV, dated as it was
    table = (docs / "seed_scatter_starts_3000.csv").read_text()
    (docs / "SEED_SCATTER.md").write_text(text.replace("Generated ", "Generated 2026-01-02 on a GPU; fast: 1 steps. Was "))
    scatter.main(["--configurations", label, "--seeds", "0-2", "--steps", "3000", "--canclip", str(capture),
                  "--cache", str(tmp_path / "no_log"), "--against-one-start", str(tmp_path / "no_log_either"),
                  "--docs", str(docs)])
    again = (docs / "SEED_SCATTER.md").read_text()
    assert "Generated 2026-01-02 on a GPU; fast: 3000 steps; seeds 0-2; one start" in again
    assert again.split("Rows of both")[1] == text.split("Rows of both")[1]  # the table, line for line
    assert (docs / "seed_scatter_starts_3000.csv").read_text() == table


def test_a_fresh_machine_reports_the_committed_rows_again(scatter, tmp_path):
    """--report-only without the run log (a fresh clone) starts it from the committed CSV, so the
    page and the CSV come out as they were; runs the plan keys otherwise (made on another
    machine, its scenes elsewhere) keep their lines instead of emptying them."""
    capture, cache, docs = logged_runs(scatter, tmp_path, [("canclip", 1000, 36.2), ("canclip-6-photos", 1000, 34.8)])
    (docs / "SEED_SCATTER.md").write_text("# By hand\n")
    labels = ["--configurations", "canclip,canclip-6-photos"]
    scatter.main(labels + report_arguments(capture, cache, docs))
    page, table = (docs / "SEED_SCATTER.md").read_text(), (docs / "seed_scatter.csv").read_text()
    assert "| canclip | 36.20 36.21 36.22 |" in page and "| canclip-6-photos | 34.80 34.81 34.82 |" in page

    (cache / "runs.jsonl").unlink()
    scatter.main(labels + report_arguments(capture, cache, docs))
    assert (docs / "SEED_SCATTER.md").read_text() == page and (docs / "seed_scatter.csv").read_text() == table
    assert len((cache / "runs.jsonl").read_text().splitlines()) == 6

    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    scatter.main(labels + report_arguments(elsewhere, tmp_path / "another_cache", docs))
    assert (docs / "SEED_SCATTER.md").read_text() == page and (docs / "seed_scatter.csv").read_text() == table
    # ... and a report trains nothing, so its header keeps the date and machine the block had
    (docs / "SEED_SCATTER.md").write_text(page.replace("Generated ", "Generated 2026-01-02 on a GPU; fast: 1 steps. Was "))
    scatter.main(labels + report_arguments(capture, cache, docs))
    assert "Generated 2026-01-02 on a GPU; fast: 1000 steps; seeds 0-2;" in (docs / "SEED_SCATTER.md").read_text()

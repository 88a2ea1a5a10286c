"""The speed benchmarks end to end on the tiny scene: benchmarks/train_step_time.py (both Adam
variants train, a CSV row per run, --append adds to it) and benchmarks/sweep_time.py (the
depth teacher's sweep timed, its targets' checksum the same on every repeat)."""

from __future__ import annotations

import csv
import importlib.util
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def load(name: str):
    spec = importlib.util.spec_from_file_location(name, REPO / "benchmarks" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_train_step_time_both_variants_and_append(tiny_scene, tmp_path, capsys):
    bench = load("train_step_time")
    out = tmp_path / "times.csv"
    common = ["--scene", str(tiny_scene), "--scale", "1", "--steps", "3", "--repeats", "1", "--out", str(out)]
    bench.main(common)
    bench.main([*common, "--threads", "2", "--append"])
    rows = list(csv.DictReader(open(out)))
    assert [r["variant"] for r in rows] == ["fused", "loop", "fused", "loop"]
    assert all(r["steps"] == "3" and float(r["ms_per_step"]) > 0 for r in rows)
    assert [r["machine"].endswith(f"cpu ({n} threads)") for r, n in zip(rows, (1, 1, 2, 2))] == [True] * 4
    assert "fused / loop" in capsys.readouterr().out


def test_sweep_time_appends_labelled_runs_with_one_checksum(tiny_scene, tmp_path, capsys):
    bench = load("sweep_time")
    out = tmp_path / "sweep.csv"
    bench.main(["--scene", str(tiny_scene), "--scale", "1", "--repeats", "2", "--label", "a", "--out", str(out)])
    bench.main(["--scene", str(tiny_scene), "--scale", "1", "--repeats", "1", "--label", "b", "--out", str(out)])
    rows = list(csv.DictReader(open(out)))
    assert [r["label"] for r in rows] == ["a", "a", "b"] and all(float(r["seconds"]) > 0 for r in rows)
    assert len({r["checksum"] for r in rows}) == 1  # the same targets every time
    assert "median" in capsys.readouterr().out

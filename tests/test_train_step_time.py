"""benchmarks/train_step_time.py end to end on the tiny scene: both Adam variants train, the
CSV gets a row per run, and --append adds to it."""

from __future__ import annotations

import csv
import importlib.util
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_both_variants_time_and_append(tiny_scene, tmp_path, capsys):
    spec = importlib.util.spec_from_file_location("train_step_time", REPO / "benchmarks" / "train_step_time.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    out = tmp_path / "times.csv"
    common = ["--scene", str(tiny_scene), "--scale", "1", "--steps", "3", "--repeats", "1", "--out", str(out)]
    bench.main(common)
    bench.main([*common, "--threads", "2", "--append"])
    rows = list(csv.DictReader(open(out)))
    assert [r["variant"] for r in rows] == ["fused", "loop", "fused", "loop"]
    assert all(r["steps"] == "3" and float(r["ms_per_step"]) > 0 for r in rows)
    assert [r["machine"].endswith(f"cpu ({n} threads)") for r, n in zip(rows, (1, 1, 2, 2))] == [True] * 4
    assert "fused / loop" in capsys.readouterr().out

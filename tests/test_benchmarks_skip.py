"""The benchmarks skip cleanly where the reference scenes are absent (a user's fresh checkout has
no ../shared/data): each script, pointed at a folder that is not there, says `skip:` and exits 0
before any work, with no traceback and nothing under docs/ written (benchmarks/reference_data.py)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
MISSING = "{missing}"  # stands for a folder under the test's tmp_path that is not there
TMP = "{tmp}"          # an existing scratch folder (caches, outputs that are not docs/)

# script -> its arguments: the scene (or the folder of scenes) at MISSING, the smallest budget.
SCRIPTS = {
    "speed_accuracy": ["--scene", MISSING, "--minutes", "0.01", "--methods", "classic-plane"],
    "model_size": ["--scene", MISSING, "--steps", "1"],
    "render_fps": ["--scene", MISSING, "--model", f"m={TMP}/model", "--repeats", "1"],
    "gpu_profile": ["--scene", MISSING, "--steps", "1", "--frames", "1", "--out", f"{TMP}/profile"],
    "point_depth": ["--data", MISSING, "--steps", "1", "--seeds", "0"],
    "side_by_side": ["--data", MISSING, "--baseline", "a={}", "--steps", "1", "--seeds", "0"],
    "auto_search": ["--data", MISSING, "--steps", "10", "--curve", "1", "--seeds", "0"],
    "slab_placement": ["--data", MISSING, "--steps", "1"],
    "depth": ["--data", MISSING, "--parts", "hci,canclip", "--steps", "1", "--hci-steps", "1", "--jobs", "1"],
    "sweep_time": ["--scene", MISSING, "--repeats", "1"],
    "train_step_time": ["--scene", MISSING, "--steps", "1", "--repeats", "1"],
    "train_scale": ["--scene", MISSING, "--scales", "0.25", "--eval-scales", "0.25", "--minutes", "0.01", "--seeds", "0"],
    "setup_time": ["--scene", MISSING, "--repeats", "1"],
    "seed_scatter": ["--canclip", MISSING, "--configurations", "canclip", "--seeds", "0", "--steps", "1",
                     "--cache", f"{TMP}/cache"],
    "pixel_samples": ["--canclip", MISSING, "--configurations", "canclip", "--seeds", "0", "--steps", "1",
                      "--cache", f"{TMP}/cache"],
    "sample_contrast": ["--canclip", MISSING, "--configurations", "canclip", "--seeds", "0",
                        "--cache", f"{TMP}/cache"],
    "members": ["--canclip", MISSING, "--configurations", "canclip", "--seeds", "0", "--budgets", "1",
                "--cache", f"{TMP}/cache"],
    "seed_disagreement": ["--canclip", MISSING, "--configurations", "canclip-6-photos", "--seeds", "0", "--steps", "1",
                          "--models", f"{TMP}/models"],
    "wide_photo": ["--scene", MISSING, "--steps", "1", "--seeds", "0", "--work", f"{TMP}/work"],
    "frames_time": ["--scene", MISSING, "--count", "2", "--work", f"{TMP}/work"],
}


def docs_state() -> tuple[str, dict]:
    """git's view of docs/ and every file's modification time and size there."""
    status = subprocess.run(["git", "status", "--porcelain", "--", "docs"], cwd=REPO, capture_output=True, text=True).stdout
    files = {str(p): (p.stat().st_mtime_ns, p.stat().st_size) for p in (REPO / "docs").rglob("*") if p.is_file()}
    return status, files


def run_script(name: str, args: list[str], tmp_path: Path) -> subprocess.CompletedProcess:
    scratch = tmp_path / "scratch"
    scratch.mkdir(exist_ok=True)
    args = [a.replace(MISSING, str(tmp_path / "missing")).replace(TMP, str(scratch)) for a in args]
    return subprocess.run([sys.executable, f"benchmarks/{name}.py", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=120, env={**os.environ, "OMP_NUM_THREADS": "1"})


def assert_skipped(result: subprocess.CompletedProcess, before: tuple[str, dict]) -> str:
    output = result.stdout + result.stderr
    assert result.returncode == 0, output
    assert "skip:" in output and "Traceback" not in output, output
    assert docs_state() == before, "docs/ changed"
    return output


@pytest.mark.parametrize("name", list(SCRIPTS), ids=list(SCRIPTS))
def test_a_benchmark_skips_where_its_scenes_are_missing(name, tmp_path):
    before = docs_state()
    output = assert_skipped(run_script(name, SCRIPTS[name], tmp_path), before)
    assert f"{tmp_path / 'missing'}" in output  # the line names the folder it looked for


@pytest.mark.parametrize("name, args", [
    # canclip is here (an empty stand-in), statue is not: the committed CSV would lose statue's rows
    ("slab_placement", ["--data", TMP, "--scenes", "canclip,statue", "--steps", "1"]),
    # the default's synthetic configurations need no capture, but docs/seed_disagreement.csv is
    # written whole and holds canclip-6-photos
    ("seed_disagreement", ["--canclip", MISSING, "--seeds", "0", "--steps", "1", "--models", f"{TMP}/models"]),
], ids=["slab_placement", "seed_disagreement"])
def test_a_partial_run_does_not_rewrite_a_committed_table(name, args, tmp_path):
    (tmp_path / "scratch" / "canclip").mkdir(parents=True)
    before = docs_state()
    output = assert_skipped(run_script(name, args, tmp_path), before)
    assert "would drop their rows" in output and "Nothing was written" in output

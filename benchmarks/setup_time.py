"""Wall time of short training runs, where what a run does before and between its steps shows:
loading the photos, building the rays, the depth teacher's sweep, the fill of unseen texels.

    python benchmarks/setup_time.py [--scene ../shared/data/canclip] [--scale 0.5 (default: train's)] \
        [--run 'members=--steps 50 --members 2'] [--run 'auto=--steps 150 --preset auto'] \
        [--checkout before=/tmp/old] [--checkout after=.] [--repeats 3] [--out docs/setup_time.csv]

Each `--run LABEL=ARGS` is `python -m neulf_core train SCENE --out TEMP [--scale S] ARGS`, run
in a process of its own with one torch thread (OMP_NUM_THREADS=1) in each `--checkout
LABEL=FOLDER` (a git worktree of another commit, `git worktree add /tmp/old HEAD`, so two
versions of the code are timed on one machine), the checkouts taking turns run after run so
that a drift in the machine's speed falls on both.  Prints each run's seconds and the medians;
appends one row per run to the CSV.  A few steps are the point: the rest of a run is the same
in both versions, and the steps' own time is in benchmarks/train_step_time.py.
"""

from __future__ import annotations

import argparse
import os
import shlex
import statistics
import subprocess
import sys
import tempfile
import time
from datetime import date
from pathlib import Path


REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))

from reference_data import skip_unless_present  # noqa: E402
from speed_accuracy import append_rows, machine  # noqa: E402

COLUMNS = ["date", "machine", "torch_threads", "scene", "scale", "run", "args", "checkout", "repeat", "seconds"]


def labelled(text: str) -> tuple[str, str]:
    label, sep, value = text.partition("=")
    if not sep or not label:
        raise SystemExit(f"expected LABEL=VALUE, not {text!r}")
    return label, value


def timed_run(checkout: Path, scene: Path, scale: float | None, args: str) -> float:
    with tempfile.TemporaryDirectory(prefix="neulf-setup-") as folder:
        command = [sys.executable, "-m", "neulf_core", "train", str(scene), "--out", str(Path(folder) / "model"),
                   *(["--scale", str(scale)] if scale is not None else []), *shlex.split(args)]
        started = time.perf_counter()
        done = subprocess.run(command, cwd=checkout, env={**os.environ, "OMP_NUM_THREADS": "1"},
                              stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        seconds = time.perf_counter() - started
    if done.returncode:
        raise SystemExit(f"{checkout}: {' '.join(command)} failed:\n{done.stderr[-2000:]}")
    return seconds


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", type=Path, default=REPO.parent / "shared" / "data" / "canclip")
    parser.add_argument("--scale", type=float, help="(default: train's own rule)")
    parser.add_argument("--run", action="append", help="LABEL=train options (repeatable)")
    parser.add_argument("--checkout", action="append", help="LABEL=folder of a checkout (repeatable; default: this one)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", type=Path, default=REPO / "docs" / "setup_time.csv")
    args = parser.parse_args(argv)
    skip_unless_present(args.scene)
    runs = [labelled(r) for r in (args.run or ["members=--steps 50 --members 2"])]
    checkouts = [(label, Path(folder).resolve()) for label, folder in map(labelled, args.checkout or [f"this={REPO}"])]
    scene = args.scene.resolve()
    rows = []
    for run, options in runs:
        for repeat in range(args.repeats):
            for checkout, folder in checkouts:
                seconds = timed_run(folder, scene, args.scale, options)
                rows.append({"date": date.today().isoformat(), "machine": machine(), "torch_threads": 1,
                             "scene": scene.name, "scale": args.scale or "default", "run": run, "args": options,
                             "checkout": checkout, "repeat": repeat, "seconds": round(seconds, 2)})
                print(f"{run} ({options}), {checkout}, repeat {repeat}: {seconds:.2f} s", flush=True)
        for checkout, _ in checkouts:
            times = [r["seconds"] for r in rows if r["run"] == run and r["checkout"] == checkout]
            print(f"{run}: {checkout} median {statistics.median(times):.2f} s over {len(times)}")
    append_rows(args.out, rows, COLUMNS)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()

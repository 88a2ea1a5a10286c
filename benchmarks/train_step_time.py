"""Time per training step of the default, with Adam's fused kernel against its per-tensor loop.

    python benchmarks/train_step_time.py [--scene ../shared/data/canclip] [--scale 0.5] \
        [--steps 500] [--repeats 3] [--threads 1] [--out docs/train_step_time.csv] [--append]

Trains the default (`fast`) for a fixed number of steps, once per variant and repeat, the
variants alternating so a change in the machine's load falls on both; each run in a fresh
process (one torch thread by default, as the 20x benchmark runs). The time per step is the
trainer's own elapsed time (which counts the plane sweep it computes first) over its steps.
Prints each run and the medians; writes one CSV row per run (`--append`: after the file's
rows, e.g. a second thread count).
"""

from __future__ import annotations

import argparse
import csv
import json
import statistics
import subprocess
import sys
import tempfile
from datetime import date
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))

from reference_data import skip_unless_present  # noqa: E402
from speed_accuracy import hardware  # noqa: E402

VARIANTS = ("fused", "loop")

# One run, in its own process: the trainer's Adam, or the same Adam forced to its per-tensor loop.
RUN = """
import json, sys, torch
sys.path.insert(0, {repo!r})
from neulf_core.train import TrainConfig, train
if {variant!r} == "loop":
    fused_adam = torch.optim.Adam
    class LoopAdam(fused_adam):
        def __init__(self, *args, **kwargs):
            kwargs.update(fused=None, foreach=False)
            super().__init__(*args, **kwargs)
    torch.optim.Adam = LoopAdam
torch.set_num_threads({threads})
result = train({scene!r}, {out!r}, TrainConfig(steps={steps}, scale={scale}, validate_seconds=1e9, checkpoint_seconds=1e9))
print(json.dumps({{"steps": result.step, "elapsed": result.elapsed, "val_psnr": result.val_psnr}}))
"""


def run_once(variant: str, args, work: Path) -> dict:
    code = RUN.format(repo=str(REPO), variant=variant, threads=args.threads, scene=str(args.scene),
                      out=str(work / f"{variant}_{len(list(work.iterdir()))}"), steps=args.steps, scale=args.scale)
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    result = json.loads(done.stdout.strip().splitlines()[-1])
    return {"variant": variant, **result, "ms_per_step": 1000 * result["elapsed"] / result["steps"]}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", type=Path, default=REPO.parent / "shared" / "data" / "canclip")
    parser.add_argument("--scale", type=float, default=0.5)
    parser.add_argument("--steps", type=int, default=500)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", type=Path, default=REPO / "docs" / "train_step_time.csv")
    parser.add_argument("--append", action="store_true", help="add the rows to --out instead of replacing it")
    args = parser.parse_args(argv)
    skip_unless_present(args.scene)
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        for repeat in range(args.repeats):
            for variant in VARIANTS if repeat % 2 == 0 else VARIANTS[::-1]:
                row = {"repeat": repeat, **run_once(variant, args, Path(folder))}
                rows.append(row)
                print(f"{variant:6s} repeat {repeat}: {row['ms_per_step']:.1f} ms per step, "
                      f"held-out {row['val_psnr']:.2f} dB", flush=True)
    medians = {v: statistics.median(r["ms_per_step"] for r in rows if r["variant"] == v) for v in VARIANTS}
    print(f"median ms per step: fused {medians['fused']:.1f}, loop {medians['loop']:.1f} "
          f"(fused / loop {medians['fused'] / medians['loop']:.3f})")
    torch.set_num_threads(args.threads)  # what each run had, for the description
    machine = hardware(torch.device("cpu"))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    append = args.append and args.out.is_file()
    with open(args.out, "a" if append else "w", newline="") as handle:
        writer = csv.DictWriter(handle, ["date", "machine", "scene", "scale", "steps", "repeat", "variant",
                                         "ms_per_step", "elapsed", "val_psnr"])
        if not append:
            writer.writeheader()
        for row in rows:
            writer.writerow({"date": date.today().isoformat(), "machine": machine, "scene": args.scene.name,
                             "scale": args.scale, "steps": row["steps"], "repeat": row["repeat"],
                             "variant": row["variant"], "ms_per_step": round(row["ms_per_step"], 2),
                             "elapsed": round(row["elapsed"], 2), "val_psnr": round(row["val_psnr"], 3)})
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()

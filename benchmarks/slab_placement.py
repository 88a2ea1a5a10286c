"""Where to put the light slab's planes: held-out PSNR for several placements, same budget.

    python benchmarks/slab_placement.py [--steps 600] [--scenes canclip,statue,fern] [--data ../shared/data]

Trains the default field for a fixed number of steps per placement on each scene (every
8th view held out) and writes docs/slab_placement.csv and a markdown table on stdout.
Fixed steps, not time, so a busy machine does not bias the comparison.
"""

from __future__ import annotations

import argparse
import csv
import os
import platform
import sys
import tempfile
import time
from datetime import date
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from neulf_core.evaluate import evaluate_model  # noqa: E402
from neulf_core.scene import load_scene, split_views  # noqa: E402
from neulf_core.slab import scene_depths, slab_frame  # noqa: E402
from neulf_core.train import TrainConfig, train  # noqa: E402
from reference_data import present  # noqa: E402

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
# name -> (its photo folder inside the scene folder, None: the model's own; training scale)
SCENES = {"canclip": (None, 0.5), "statue": (None, 0.5), "fern": ("images_8", 1.0)}


def placements(scene, views):
    rotation, origin = slab_frame(views)
    z = scene_depths(scene, rotation, origin)
    near, far = float(z.min()), float(z.max())
    return {
        "harmonic mean depth (default)": 1.0 / np.mean(1.0 / z),
        "median depth": float(np.median(z)),
        "nearest content": near,
        "farthest content": far,
        "NeRF spiral focus": 1.0 / (0.25 / (0.9 * near) + 0.75 / (5 * far)),
    }


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--steps", type=int, default=600)
    parser.add_argument("--scenes", default="canclip,statue,fern")
    parser.add_argument("--out", default=str(Path(__file__).resolve().parents[1] / "docs" / "slab_placement.csv"))
    parser.add_argument("--threads", type=int, default=1, help="torch threads (1 lets two runs share 2 cores fairly)")
    parser.add_argument("--data", type=Path, default=SHARED, help="the folder holding the scenes")
    args = parser.parse_args()
    # --out holds this run's rows only: a committed one is not rewritten without a missing scene's
    scenes = present({name: args.data / name for name in args.scenes.split(",")}, "--data", rewrites=args.out)
    torch.set_num_threads(args.threads)
    rows = []
    for name in scenes:
        images, scale = SCENES[name]
        path = args.data / name
        images = path / images if images else None
        scene = load_scene(path, images)
        train_views, _ = split_views(scene)
        for label, st in placements(scene, train_views).items():
            with tempfile.TemporaryDirectory() as tmp:
                started = time.perf_counter()
                train(scene, tmp, TrainConfig(steps=args.steps, scale=scale, st_depth=st, validate_seconds=1e9))
                report = evaluate_model(tmp, path, images_dir=images, save_images=False,
                                        pixel_samples=1)  # as its earlier CSV was scored
                rows.append({"scene": name, "placement": label, "st_depth": round(st, 4), "psnr": round(report["mean_psnr"], 3),
                             "ssim": round(report["mean_ssim"], 4), "steps": args.steps, "scale": scale,
                             "seconds": round(time.perf_counter() - started, 1), "machine": f"{platform.machine()} {os.cpu_count()} cores, {args.threads} torch thread(s)",
                             "date": date.today().isoformat()})
                print(rows[-1], flush=True)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    with open(args.out, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    print("\n| scene | placement | st depth | PSNR | SSIM |\n|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['scene']} | {r['placement']} | {r['st_depth']} | {r['psnr']} | {r['ssim']} |")


if __name__ == "__main__":
    main()

"""The SfM points' depth at the product's budget: the default with and without it, side by side.

    python benchmarks/point_depth.py                         # CanClip and Statue, 1.5 minutes, seeds 0 / 1
    python benchmarks/point_depth.py --scenes statue --minutes 3 --seeds 0

For each scene and seed the default (`fast`) trains twice at once for the same minutes, one
torch thread each, pinned to a core each (the cores swapped from one seed to the next, so
neither setting always gets the same core): once as it is (`--point-depth`: the rays through
the training photos' keypoints pulled toward their points' depth, neulf_core/point_depth.py)
and once with `--no-point-depth`.  Both are scored on the held-out views (every 8th) as
`eval` scores them (4 points a pixel).  Only scenes whose COLMAP model keeps tracks change
(CanClip and Statue here; fern's and HCI's models have none).  Writes docs/point_depth.csv
(one row per run) and prints a markdown table of the pairs.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import platform
import subprocess
import sys
import tempfile
from datetime import date
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DOCS = REPO / "docs"
SCENES = {"canclip": (REPO.parent / "shared" / "data" / "canclip", 0.5),
          "statue": (REPO.parent / "shared" / "data" / "statue", 0.5)}
SETTINGS = {"on": True, "off": False}


def one_run(scene: str, scale: float, minutes: float, seed: int, point_depth: bool, out: Path) -> dict:
    """Train and score one model in this process (the pinned child's work)."""
    import torch

    from neulf_core.evaluate import evaluate_model
    from neulf_core.train import TrainConfig, train

    torch.set_num_threads(1)
    result = train(scene, out, TrainConfig(minutes=minutes, scale=scale, seed=seed, point_depth=point_depth,
                                           validate_seconds=1e9))
    scores = evaluate_model(out, scene, save_images=False)
    meta = json.loads((out / "model.json").read_text())
    return {"steps": result.step, "train_seconds": round(result.elapsed, 1), "psnr": round(scores["mean_psnr"], 3),
            "ssim": round(scores["mean_ssim"], 4), "point_rays": (meta.get("point_depth") or {}).get("rays", 0)}


def pair(name: str, minutes: float, seed: int) -> list[dict]:
    """Both settings of one scene and seed at once, each pinned to its own core."""
    path, scale = SCENES[name]
    cores = sorted(os.sched_getaffinity(0))
    children = []
    with tempfile.TemporaryDirectory(prefix="neulf_point_depth_") as folder:
        for i, (setting, on) in enumerate(SETTINGS.items()):
            core = cores[(i + seed) % len(cores)]
            args = [sys.executable, __file__, "--child", json.dumps([str(path), scale, minutes, seed, on,
                                                                     str(Path(folder) / setting)])]
            children.append((setting, core, subprocess.Popen(["taskset", "-c", str(core), *args],
                                                             stdout=subprocess.PIPE, text=True)))
        rows = []
        for setting, core, child in children:
            output, _ = child.communicate()
            if child.returncode:
                raise SystemExit(f"the {setting} run of {name}, seed {seed} failed (exit {child.returncode})")
            rows.append({"scene": name, "seed": seed, "point_depth": setting, "minutes": minutes, "core": core,
                         **json.loads(output.strip().splitlines()[-1])})
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", default="canclip,statue")
    parser.add_argument("--minutes", type=float, default=1.5)
    parser.add_argument("--seeds", default="0,1")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        scene, scale, minutes, seed, on, out = json.loads(args.child)
        print(json.dumps(one_run(scene, scale, minutes, seed, on, Path(out))))
        return
    rows = []
    for name in args.scenes.split(","):
        for seed in (int(s) for s in args.seeds.split(",")):
            rows += pair(name, args.minutes, seed)
            print(f"{name} seed {seed}: " + ", ".join(f"{r['point_depth']} {r['psnr']:.2f} dB ({r['steps']} steps)"
                                                       for r in rows[-2:]), flush=True)
    machine = f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores"
    for row in rows:
        row.update(date=date.today().isoformat(), machine=machine)
    DOCS.mkdir(exist_ok=True)
    with open(DOCS / "point_depth.csv", "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    print("\n| scene | seed | without the points | with them (the default) | change | steps without / with | keypoint rays |")
    print("|---|---|---|---|---|---|---|")
    for i in range(0, len(rows), 2):
        on, off = rows[i], rows[i + 1]
        print(f"| {on['scene']} | {on['seed']} | {off['psnr']:.2f} | {on['psnr']:.2f} | {on['psnr'] - off['psnr']:+.2f} dB "
              f"| {off['steps']} / {on['steps']} | {on['point_rays']} |")


if __name__ == "__main__":
    main()

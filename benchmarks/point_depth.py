"""The SfM points' depth at the product's budget: the default with and without it, side by side.

    python benchmarks/point_depth.py                         # CanClip and Statue, 1.5 minutes, seeds 0 / 1
    python benchmarks/point_depth.py --scenes statue --minutes 3 --seeds 0
    python benchmarks/point_depth.py --scenes statue --steps 3400 --seeds 0-7 --device cuda --jobs 8 \
        --out docs/point_depth_statue_h200.csv                  # a GPU: many pairs at once, a fixed step count

For each scene and seed the default (`fast`) trains twice at once for the same minutes, one
torch thread each, pinned to a core each (the cores swapped from one seed to the next, so
neither setting always gets the same core): once as it is (`--point-depth`: the rays through
the training photos' keypoints pulled toward their points' depth, neulf_core/point_depth.py)
and once with `--no-point-depth`.  Both are scored on the held-out views (every 8th) as
`eval` scores them (4 points a pixel).  On a GPU (`--device cuda`) nothing is pinned, `--jobs`
pairs train at once (a step is bound by Python and kernel launches, so the GPU has room), and
`--steps` fixes the budget in steps, so runs side by side do not change each other's.  Only
scenes whose COLMAP model keeps tracks change (CanClip and Statue here; fern's and HCI's models
have none).  Writes docs/point_depth.csv
(or `--out`; one row per run) and prints a markdown table of the pairs and the mean change with
its standard error over the seeds.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from datetime import date
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # neulf_core from this checkout, installed or not
sys.path.insert(0, str(REPO / "benchmarks"))
from seed_scatter import parse_seeds as seed_list  # noqa: E402  ("0-7", "0,1" or a mix)
DOCS = REPO / "docs"
SCENES = {"canclip": 0.5, "statue": 0.5}  # the scenes (folders under --data) and the scale each trains at
SETTINGS = {"on": True, "off": False}


def one_run(scene: str, scale: float, budget: dict, seed: int, point_depth: bool, device: str | None, out: Path) -> dict:
    """Train and score one model in this process (the child's work); `budget` is {"minutes": m} or {"steps": n}."""
    import torch

    from neulf_core.evaluate import evaluate_model
    from neulf_core.train import TrainConfig, train

    torch.set_num_threads(1)
    result = train(scene, out, TrainConfig(**budget, scale=scale, seed=seed, point_depth=point_depth, device=device,
                                           validate_seconds=1e9))
    scores = evaluate_model(out, scene, save_images=False, device=device)
    meta = json.loads((out / "model.json").read_text())
    return {"steps": result.step, "train_seconds": round(result.elapsed, 1), "psnr": round(scores["mean_psnr"], 3),
            "ssim": round(scores["mean_ssim"], 4), "point_rays": (meta.get("point_depth") or {}).get("rays", 0)}


def pair(name: str, budget: dict, seed: int, device: str | None, data: Path) -> list[dict]:
    """Both settings of one scene and seed at once, each pinned to its own core (on the CPU)."""
    path, scale = data / name, SCENES[name]
    cores = sorted(os.sched_getaffinity(0))
    children = []
    with tempfile.TemporaryDirectory(prefix="neulf_point_depth_") as folder:
        for i, (setting, on) in enumerate(SETTINGS.items()):
            pinned = device is None or device == "cpu"
            core = cores[(i + seed) % len(cores)] if pinned else ""
            args = [sys.executable, __file__, "--child", json.dumps([str(path), scale, budget, seed, on, device,
                                                                     str(Path(folder) / setting)])]
            command = ["taskset", "-c", str(core), *args] if pinned else args
            children.append((setting, core, subprocess.Popen(command, stdout=subprocess.PIPE, text=True)))
        rows = []
        for setting, core, child in children:
            output, _ = child.communicate()
            if child.returncode:
                raise SystemExit(f"the {setting} run of {name}, seed {seed} failed (exit {child.returncode})")
            rows.append({"scene": name, "seed": seed, "point_depth": setting, "minutes": budget.get("minutes", ""),
                         "core": core,
                         **json.loads(output.strip().splitlines()[-1])})
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", default="canclip,statue")
    parser.add_argument("--minutes", type=float, default=1.5)
    parser.add_argument("--steps", type=int, help="a fixed step count instead of --minutes")
    parser.add_argument("--seeds", default="0,1", help="comma-separated, or a range such as 0-7")
    parser.add_argument("--device", help="cpu (default: pinned cores) or cuda")
    parser.add_argument("--jobs", type=int, default=1, help="pairs trained at once (on a GPU)")
    parser.add_argument("--out", default=str(DOCS / "point_depth.csv"))
    parser.add_argument("--data", default=str(REPO.parent / "shared" / "data"), help="the folder holding the scenes")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        scene, scale, budget, seed, on, device, out = json.loads(args.child)
        print(json.dumps(one_run(scene, scale, budget, seed, on, device, Path(out))))
        return
    budget = {"steps": args.steps} if args.steps else {"minutes": args.minutes}
    pairs = [(name, seed) for name in args.scenes.split(",") for seed in seed_list(args.seeds)]
    rows = []
    machine = machine_name(args.device)
    with ThreadPoolExecutor(max(1, args.jobs)) as pool:
        for pair_rows in pool.map(lambda job: pair(job[0], budget, job[1], args.device, Path(args.data)), pairs):
            rows += [{**row, "date": date.today().isoformat(), "machine": machine} for row in pair_rows]
            write_rows(Path(args.out), rows)  # after every pair, so a run cut short keeps what it finished
            print(f"{pair_rows[0]['scene']} seed {pair_rows[0]['seed']}: "
                  + ", ".join(f"{r['point_depth']} {r['psnr']:.2f} dB ({r['steps']} steps)" for r in pair_rows), flush=True)
    print("\n| scene | seed | without the points | with them (the default) | change | steps without / with | keypoint rays |")
    print("|---|---|---|---|---|---|---|")
    for i in range(0, len(rows), 2):
        on, off = rows[i], rows[i + 1]
        print(f"| {on['scene']} | {on['seed']} | {off['psnr']:.2f} | {on['psnr']:.2f} | {on['psnr'] - off['psnr']:+.2f} dB "
              f"| {off['steps']} / {on['steps']} | {on['point_rays']} |")
    for name in dict.fromkeys(row["scene"] for row in rows):
        changes = [rows[i]["psnr"] - rows[i + 1]["psnr"] for i in range(0, len(rows), 2) if rows[i]["scene"] == name]
        error = statistics.stdev(changes) / len(changes) ** 0.5 if len(changes) > 1 else float("nan")
        print(f"\n{name}: mean change {statistics.mean(changes):+.3f} dB, standard error {error:.3f} ({len(changes)} seeds)")


def write_rows(path: Path, rows: list[dict]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


def machine_name(device: str | None) -> str:
    """The CPU (and GPU, where one trained) the rows came from."""
    machine = f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores"
    if device and device.startswith("cuda"):
        import torch

        machine += f", {torch.cuda.get_device_name(0)}"
    return machine


if __name__ == "__main__":
    main()

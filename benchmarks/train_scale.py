"""Which image scale to train at: the same minutes at several training scales, each model scored
at several render scales.

    python benchmarks/train_scale.py --scene ../shared/data/canclip --scales 0.25,0.5,1 \
        --eval-scales 0.5,1 --minutes 1.5 --seeds 0,1 [--out docs/train_scale.csv]

Every (training scale, seed) trains with `python -m neulf_core train SCENE --scale S --minutes
M --seed N`, two at a time, one torch thread each, each pinned to a core of its own (taskset;
the pairs are the list in order, so a scale's seeds fall on both cores).  Each model is then
scored on its held-out views (every 8th view, the same at every scale) at every `--eval-scales`
against the photo read at that scale, four points a pixel as `eval` renders.  A model trained
at a smaller scale is rendered larger than it trained: the light field is continuous, so this
asks what its training resolution bought.  Prints a table of mean PSNR per (training scale,
render scale) and writes one row per (model, render scale) to the CSV.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from datetime import date
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

from neulf_core.metrics import psnr  # noqa: E402
from neulf_core.render import LightField  # noqa: E402
from neulf_core.scene import load_scene  # noqa: E402
from reference_data import skip_unless_present  # noqa: E402
from seed_scatter import parse_seeds  # noqa: E402
from speed_accuracy import append_rows, machine  # noqa: E402

COLUMNS = ["date", "machine", "scene", "train_scale", "train_size", "seed", "minutes", "steps", "members",
           "eval_scale", "eval_size", "psnr"]


def train_one(scene: Path, folder: Path, scale: float, minutes: float, seed: int, core: int | None) -> dict:
    command = [sys.executable, "-m", "neulf_core", "train", str(scene), "--out", str(folder), "--scale", str(scale),
               "--minutes", str(minutes), "--seed", str(seed)]
    if core is not None:
        command = ["taskset", "-c", str(core), *command]
    done = subprocess.run(command, cwd=REPO, env={**os.environ, "OMP_NUM_THREADS": "1"}, capture_output=True, text=True)
    if done.returncode:
        raise SystemExit(f"training failed: {' '.join(command)}\n{done.stderr[-2000:]}")
    return json.loads((folder / "model.json").read_text())


def scores(folder: Path, scene, eval_scales) -> list[tuple[float, str, float]]:
    light_field = LightField.load(folder, "cpu", precision="full")
    out = []
    for scale in eval_scales:
        values = []
        for name in light_field.meta["scene"]["held_out"]:
            view = scene.view(name)
            photo = view.load_image(scale).astype(np.float32) / 255.0
            values.append(psnr(light_field.render_view(view, scale, depth=False).rgb, photo))
        out.append((scale, f"{photo.shape[1]}x{photo.shape[0]}", float(np.mean(values))))
    return out


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", type=Path, default=REPO.parent / "shared" / "data" / "canclip")
    parser.add_argument("--scales", default="0.25,0.5,1")
    parser.add_argument("--eval-scales", default="0.5,1")
    parser.add_argument("--minutes", type=float, default=1.5)
    parser.add_argument("--seeds", default="0,1")
    parser.add_argument("--no-pin", action="store_true", help="do not pin the runs to cores (no taskset)")
    parser.add_argument("--out", type=Path, default=REPO / "docs" / "train_scale.csv")
    args = parser.parse_args(argv)
    skip_unless_present(args.scene)
    scales = [float(s) for s in args.scales.split(",")]
    eval_scales = [float(s) for s in args.eval_scales.split(",")]
    jobs = [(scale, seed) for scale in scales for seed in parse_seeds(args.seeds)]
    scene = load_scene(args.scene)
    rows = []
    with tempfile.TemporaryDirectory(prefix="neulf-scale-") as temp:
        folders = {job: Path(temp) / f"s{job[0]}_seed{job[1]}" for job in jobs}
        with ThreadPoolExecutor(2) as pool:
            metas = list(pool.map(lambda ij: train_one(args.scene, folders[ij[1]], ij[1][0], args.minutes, ij[1][1],
                                                       None if args.no_pin else ij[0] % 2), enumerate(jobs)))
        for job, meta in zip(jobs, metas):
            steps, rig = meta["progress"]["step"], meta["rig"]
            members = 1 + len(list((folders[job] / "members").glob("*/model.pt")))
            for eval_scale, eval_size, value in scores(folders[job], scene, eval_scales):
                rows.append({"date": date.today().isoformat(), "machine": machine(), "scene": args.scene.name,
                             "train_scale": job[0], "train_size": f"{rig['width']}x{rig['height']}", "seed": job[1],
                             "minutes": args.minutes, "steps": steps, "members": members,
                             "eval_scale": eval_scale, "eval_size": eval_size, "psnr": round(value, 3)})
                print(f"train x{job[0]} seed {job[1]} ({steps} steps, {members} member(s)) -> render x{eval_scale} "
                      f"{eval_size}: {value:.2f} dB", flush=True)
    print("\n| training scale | steps | " + " | ".join(f"rendered x{s}" for s in eval_scales) + " |")
    print("|---|---|" + "---|" * len(eval_scales))
    for scale in scales:
        mine = [r for r in rows if r["train_scale"] == scale]
        steps = statistics.mean(r["steps"] for r in mine)
        cells = [f"{statistics.mean(r['psnr'] for r in mine if r['eval_scale'] == s):.2f}" for s in eval_scales]
        print(f"| x{scale:g} | {steps:.0f} | " + " | ".join(cells) + " |")
    append_rows(args.out, rows, COLUMNS)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()

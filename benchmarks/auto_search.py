"""Does the `auto` preset's size search pick the texture its model needs?  Learning curves of
the search's candidates against the final models' held-out PSNR.

    python benchmarks/auto_search.py --scenes statue,canclip,fern --seeds 0 --steps 4000 \\
        --curve 533,1066,2132 --out docs/auto_search.csv
    python benchmarks/auto_search.py ... --curve 533 --no-finals --variant '{"teacher": true}'   # a change to the search
    python benchmarks/auto_search.py --report-only --out docs/auto_search_halfway_533.csv      # the table again

For each scene and seed it trains, as `autosize.train_auto` would at `--steps`:
- each candidate texture (x1, x0.7, x0.5) as the search trains it (validation views carved out,
  no sweep teacher), at each step budget of `--curve`, scored on the validation views (full
  renders of model.pt) -- the search itself spends the first of them;
- each texture as the final model (all training views, the preset's teacher) for the steps the
  search leaves at `--steps`, scored on the held-out views as `eval` scores them.
So the table says which texture the search would choose at each candidate budget, and which the
final model wanted.  A candidate's row also holds, for the diagnosis only, its PSNR on the
held-out views and each view's (`held_out_psnr`, `view_psnr`): the search never sees them.
Two runs at a time, one torch thread and one core each (AMD EPYC here).
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from datetime import date
from functools import partial
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))
from reference_data import present  # noqa: E402
from seed_scatter import parse_seeds  # noqa: E402
from side_by_side import SCENES, machine_name  # noqa: E402

FIELDS = ["scene", "seed", "factor", "kind", "variant", "steps", "train_seconds", "psnr", "held_out_psnr", "model_bytes",
          "texture_size", "view_psnr"]


def one_run(path: str, images: str | None, scale: float, seed: int, factor: float, kind: str, steps: int,
            total_steps: int, variant: dict) -> dict:
    """One candidate (kind "candidate": validation PSNR, and for the diagnosis the held-out views'
    PSNR, which the search never sees) or one final model (kind "final": held-out PSNR).
    `variant`: TrainConfig fields set over the candidate's (a change to the search tried), and
    `"validation": "halfway"` to validate on the training views half-way between the held-out
    ones instead of every 8th training view."""
    from dataclasses import replace

    import numpy as np
    import torch

    from neulf_core import autosize
    from neulf_core.evaluate import evaluate_model
    from neulf_core.scene import load_scene
    from neulf_core.train import TrainConfig, train

    torch.set_num_threads(1)
    variant = dict(variant)
    scene = load_scene(path, images)
    if variant.pop("validation", None) == "halfway":  # tried in the sixty-seventh session, not kept
        autosize.validation_split = partial(halfway_validation_split, autosize.validation_split)
    config = TrainConfig(preset=autosize.PRESET, steps=total_steps, scale=scale, seed=seed, validate_seconds=1e9)
    config = autosize.final_model_defaults(scene, config, None)
    fit, validation, held = autosize.validation_split(scene, config)
    candidate = autosize.Candidate(factor, {**config.field_overrides, **autosize.texture_overrides(fit, scale, factor)})
    with tempfile.TemporaryDirectory(prefix="neulf_auto_search_") as folder:
        if kind == "candidate":
            run = autosize.candidate_config(config, candidate, {"steps": steps, "minutes": None}, held + validation)
            run = replace(run, **variant)
            trained = train(scene, folder, run)
            views = dict(zip((v.name for v in validation + held), autosize.view_psnrs(Path(folder), validation + held, scale)))
            result = {"steps": trained.step, "psnr": round(float(np.mean([views[v.name] for v in validation])), 3),
                      "held_out_psnr": round(float(np.mean([views[v.name] for v in held])), 3),
                      "model_bytes": (Path(folder) / autosize.MODEL_NAME).stat().st_size,
                      "view_psnr": json.dumps({name: round(value, 3) for name, value in views.items()})}
        else:
            final = replace(config, field_overrides=candidate.overrides, steps=steps)
            trained = train(scene, folder, final)
            scores = evaluate_model(folder, path, images_dir=images, save_images=False)
            result = {"steps": trained.step, "psnr": round(scores["mean_psnr"], 3),
                      "model_bytes": (Path(folder) / autosize.MODEL_NAME).stat().st_size}
    return {**result, "train_seconds": round(trained.elapsed, 1), "texture_size": "x".join(map(str, candidate.overrides["texture_size"]))}


def halfway_validation_split(split, scene, config):
    """autosize.validation_split with the validation views half-way between the held-out views
    (every 8th view held out: views 4, 12, 20, ...), each with training views on both sides as a
    held-out view has; the candidates train on the rest."""
    fit, validation, held = split(scene, config)
    position = {v.name: i for i, v in enumerate(scene.views)}
    train_views = sorted(fit + validation, key=lambda v: position[v.name])
    every = config.holdout_every
    halfway = [v for v in train_views if position[v.name] % every == every // 2]
    return [v for v in train_views if v not in halfway], halfway, held


def jobs(scenes, seeds, factors, curve, total_steps):
    """Every run, the longest first (two cores stay busy to the end)."""
    from neulf_core.autosize import _candidate_steps
    from neulf_core.train import TrainConfig

    final_steps = max(1, total_steps - len(factors) * _candidate_steps(TrainConfig(steps=total_steps), len(factors)))
    listed = [(name, seed, f, "candidate", s) for name in scenes for seed in seeds for f in factors for s in curve]
    listed += [(name, seed, f, "final", final_steps) for name in scenes for seed in seeds for f in factors]
    return sorted(listed, key=lambda job: -job[4])


def run_pinned(job, total_steps: int, data: Path, core: int, variant: dict) -> dict:
    name, seed, factor, kind, steps = job
    scale, images = SCENES[name]
    path = data / name
    payload = json.dumps([str(path), str(path / images) if images else None, scale, seed, factor, kind, steps, total_steps,
                          variant if kind == "candidate" else {}])
    output = subprocess.run(["taskset", "-c", str(core), sys.executable, __file__, "--child", payload],
                            check=True, stdout=subprocess.PIPE, text=True).stdout
    return {"scene": name, "seed": seed, "factor": factor, "kind": kind,
            "variant": json.dumps(variant, sort_keys=True) if kind == "candidate" and variant else "",
            **json.loads(output.strip().splitlines()[-1])}


def table(rows: list[dict], tolerance: float) -> list[str]:
    """Per scene and seed: the candidates' validation PSNR at each budget and the texture chosen,
    then the final models' held-out PSNR and the texture that scored best."""
    from neulf_core.autosize import Candidate, choose

    lines = ["| scene | seed | run | x1 | x0.7 | x0.5 | chosen / best |", "|---|---|---|---|---|---|---|"]
    for scene, seed in sorted({(r["scene"], r["seed"]) for r in rows}):
        mine = [r for r in rows if r["scene"] == scene and r["seed"] == seed]
        for kind in ("candidate", "final"):
            for steps in sorted({r["steps"] for r in mine if r["kind"] == kind}):
                runs = {r["factor"]: r for r in mine if r["kind"] == kind and r["steps"] == steps}
                if kind == "candidate":
                    picked = choose([Candidate(f, {}, r["steps"], r["psnr"], r["model_bytes"]) for f, r in runs.items()],
                                    tolerance).factor
                else:
                    picked = max(runs.values(), key=lambda r: r["psnr"])["factor"]
                cells = [f"{runs[f]['psnr']:.2f}" if f in runs else "" for f in (1.0, 0.7, 0.5)]
                label = f"search, {steps} steps (validation)" if kind == "candidate" else f"model, {steps} steps (held-out)"
                lines.append(f"| {scene} | {seed} | {label} | {' | '.join(cells)} | x{picked:g} |")
    return lines


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", default="statue,canclip,fern")
    parser.add_argument("--seeds", default="0")
    parser.add_argument("--steps", type=int, default=4000, help="the auto run's whole budget")
    parser.add_argument("--curve", default="533,1066,2132", help="candidate step budgets")
    parser.add_argument("--factors", default="1,0.7,0.5")
    parser.add_argument("--variant", default="{}", help="JSON: TrainConfig fields set over the candidates' (a change tried)")
    parser.add_argument("--no-finals", action="store_true", help="train the candidates only")
    parser.add_argument("--data", default=str(REPO.parent / "shared" / "data"))
    parser.add_argument("--out", default=str(REPO / "docs" / "auto_search.csv"))
    parser.add_argument("--report-only", action="store_true", help="print the table from --out")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    from neulf_core.autosize import TOLERANCE_DB
    if args.child:
        print(json.dumps(one_run(*json.loads(args.child))))
        return
    out = Path(args.out)
    if args.report_only:
        with open(out) as handle:
            rows = [{**r, "seed": int(r["seed"]), "factor": float(r["factor"]), "steps": int(r["steps"]),
                     "psnr": float(r["psnr"]), "model_bytes": int(r["model_bytes"])} for r in csv.DictReader(handle)]
        print("\n".join(table(rows, TOLERANCE_DB)))
        return
    # --out holds this run's rows only: a committed one is not rewritten without a missing scene's
    scenes = present({name: Path(args.data) / name for name in args.scenes.split(",")}, "--data", rewrites=out)
    factors = [float(f) for f in args.factors.split(",")]
    listed = jobs(scenes, parse_seeds(args.seeds), factors, [int(s) for s in args.curve.split(",")],
                  args.steps)
    listed = [job for job in listed if not (args.no_finals and job[3] == "final")]
    cores = sorted(os.sched_getaffinity(0))[:2]
    machine = machine_name(None)
    rows: list[dict] = []
    free = list(cores)

    def work(job):
        core = free.pop()
        try:
            return run_pinned(job, args.steps, Path(args.data), core, json.loads(args.variant))
        finally:
            free.append(core)

    with ThreadPoolExecutor(len(cores)) as pool:
        for row in pool.map(work, listed):
            rows.append({**row, "date": date.today().isoformat(), "machine": machine})
            out.parent.mkdir(parents=True, exist_ok=True)
            with open(out, "w", newline="") as handle:
                writer = csv.DictWriter(handle, fieldnames=FIELDS + ["date", "machine"])
                writer.writeheader()
                writer.writerows(rows)
            print(f"{row['scene']} seed {row['seed']} x{row['factor']:g} {row['kind']} {row['steps']} steps: "
                  f"{row['psnr']:.2f} dB", flush=True)
    print("\n" + "\n".join(table(rows, TOLERANCE_DB)))


if __name__ == "__main__":
    main()

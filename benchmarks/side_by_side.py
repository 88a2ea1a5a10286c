"""Two training settings at the product's budget, side by side: the change a default makes.

    python benchmarks/side_by_side.py --scenes fern,canclip,statue --seeds 0-4 \\
        --baseline 'geometry 32/64/128={"field_overrides": {"geometry_spatial_res": [32, 64, 128]}}' \\
        --candidate 'default={}' --out docs/geometry_scales.csv
    python benchmarks/side_by_side.py ... --steps 3400 --device cuda --jobs 8   # a GPU: many pairs at once

A setting is `LABEL=JSON`: the `TrainConfig` fields it sets over the default (`fast`), e.g.
`{"point_depth": false}` or `{"field_overrides": {...}}`; its key `"checkout"`, a folder holding
another version of this repository (`git worktree add /tmp/old HEAD`), trains that setting with
that version's code (its own copy of this script runs the run), so a change that moves no
option, only the code, is measured side by side: `--baseline 'before={"checkout": "/tmp/old"}'
--candidate 'after={}'`.  For each scene and seed both
settings train at once for the same minutes, one torch thread each, pinned to a core each (the
cores swapped from one seed to the next, so neither setting always gets the same core), and are
scored on the held-out views (every 8th) as `eval` scores them (4 points a pixel).  On a GPU
(`--device cuda`) nothing is pinned, `--jobs` pairs train at once (a step is bound by Python and
kernel launches, so the GPU has room), and `--steps` fixes the budget in steps, so runs side by
side do not change each other's.  Writes one row per run to `--out` after every pair (a run cut
short keeps what it finished) and prints a markdown table of the pairs and each scene's mean
change (candidate - baseline) with its standard error over the seeds.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
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
from reference_data import present  # noqa: E402
from seed_scatter import parse_seeds as seed_list  # noqa: E402  ("0-7", "0,1" or a mix)
DOCS = REPO / "docs"
# The scenes (folders under --data): the scale each trains at and its photo folder (None: the
# model's own), as the README's per-scene figures train them; HCI's dense 9 x 9 grid (81 views of
# 512 x 512) at the stability study's half scale.
SCENES = {"canclip": (0.5, None), "statue": (0.5, None), "fern": (1.0, "images_8"), "hci_antinous": (0.5, None)}


def parse_setting(text: str) -> tuple[str, dict]:
    """'LABEL=JSON' -> (label, TrainConfig fields)."""
    label, sep, options = text.partition("=")
    if not sep or not label:
        raise SystemExit(f"a setting is LABEL=JSON (e.g. 'off={{\"point_depth\": false}}'), not {text!r}")
    try:
        fields = json.loads(options or "{}")
    except json.JSONDecodeError as error:
        raise SystemExit(f"setting {label!r}: its options are not JSON ({error})")
    if not isinstance(fields, dict):
        raise SystemExit(f"setting {label!r}: its options must be a JSON object of TrainConfig fields")
    return label, fields


def one_run(scene: str, images: str | None, scale: float, budget: dict, seed: int, options: dict,
            device: str | None, out: Path) -> dict:
    """Train and score one model in this process (the child's work); `budget` is {"minutes": m} or {"steps": n}."""
    import torch

    from neulf_core.autosize import PRESET as AUTO_PRESET, train_auto
    from neulf_core.evaluate import evaluate_model
    from neulf_core.members import finished_members
    from neulf_core.train import TrainConfig, train

    torch.set_num_threads(1)
    config = TrainConfig(**budget, scale=scale, seed=seed, device=device, validate_seconds=1e9, **options)
    run = train_auto if config.preset == AUTO_PRESET else train  # as the CLI: auto searches the size first
    result = run(scene, out, config, images_dir=images)
    scores = evaluate_model(out, scene, images_dir=images, save_images=False, device=device)
    meta = json.loads((out / "model.json").read_text())
    rule = meta.get("members_rule") or {}
    return {"steps": result.step, "train_seconds": round(result.elapsed, 1), "psnr": round(scores["mean_psnr"], 3),
            "ssim": round(scores["mean_ssim"], 4), "point_rays": (meta.get("point_depth") or {}).get("rays", 0),
            # the members trained, and the passes the members rule counted ("" where it did not run)
            "members": 1 + len(finished_members(out)), "members_passes": rule.get("passes", ""),
            # the auto preset's chosen texture size, as a factor of the default's ("" for the other presets)
            "texture_factor": ((meta.get("autosize") or {}).get("chosen") or {}).get("factor", ""),
            # what the rules chose for the field
            "back_surface": bool(meta["field_config"].get("back_surface")),
            "depth_layers": meta["field_config"].get("geometry_layers", 0)}


def pair(name: str, budget: dict, seed: int, settings: list[tuple[str, dict]], device: str | None,
         data: Path, where: tuple | None = None) -> list[dict]:
    """Both settings of one scene and seed at once, each pinned to its own core (on the CPU).
    `where`: (folder, scale, photo folder) of a scene not in SCENES (benchmarks/untuned_scene.py)."""
    scale, images = SCENES[name] if where is None else where[1:]
    path = data / name if where is None else Path(where[0])
    cores = sorted(os.sched_getaffinity(0))
    pinned = device is None or device == "cpu"
    children = []
    with tempfile.TemporaryDirectory(prefix="neulf_side_by_side_") as folder:
        for i, (label, options) in enumerate(settings):
            core = cores[(i + seed) % len(cores)] if pinned else ""
            options = dict(options)
            checkout = options.pop("checkout", None)
            script = Path(checkout) / "benchmarks" / Path(__file__).name if checkout else __file__
            args = [sys.executable, str(script), "--child",
                    json.dumps([str(path), str(path / images) if images else None, scale, budget, seed, options, device,
                                str(Path(folder) / str(i))])]
            command = ["taskset", "-c", str(core), *args] if pinned else args
            children.append((label, core, subprocess.Popen(command, stdout=subprocess.PIPE, text=True)))
        rows = []
        for label, core, child in children:
            output, _ = child.communicate()
            if child.returncode:
                raise SystemExit(f"the {label} run of {name}, seed {seed} failed (exit {child.returncode})")
            rows.append({"scene": name, "seed": seed, "setting": label, "minutes": budget.get("minutes", ""),
                         "core": core, **json.loads(output.strip().splitlines()[-1])})
    return rows


def summary(rows: list[dict], baseline: str, candidate: str) -> list[str]:
    """The pairs as a markdown table, then each scene's mean change and its standard error."""
    by_pair: dict[tuple, dict] = {}
    for row in rows:
        by_pair.setdefault((row["scene"], row["seed"]), {})[row["setting"]] = row
    lines = [f"| scene | seed | {baseline} | {candidate} | change | steps | members | keypoint rays |",
             "|---|---|---|---|---|---|---|---|"]
    changes: dict[str, list[float]] = {}
    for (scene, seed), runs in by_pair.items():
        if baseline not in runs or candidate not in runs:
            continue
        base, new = runs[baseline], runs[candidate]
        changes.setdefault(scene, []).append(new["psnr"] - base["psnr"])
        lines.append(f"| {scene} | {seed} | {base['psnr']:.2f} | {new['psnr']:.2f} | {new['psnr'] - base['psnr']:+.2f} dB "
                     f"| {base['steps']} / {new['steps']} | {base.get('members', '?')} / {new.get('members', '?')} "
                     f"| {base['point_rays']} / {new['point_rays']} |")
    for scene, values in changes.items():
        error = statistics.stdev(values) / len(values) ** 0.5 if len(values) > 1 else float("nan")
        lines.append(f"\n{scene}: mean change {statistics.mean(values):+.3f} dB, standard error {error:.3f} "
                     f"({len(values)} seeds; {sum(v > 0 for v in values)} up)")
    return lines


def main(argv: list[str] | None = None, description: str = __doc__, baseline: str = "", candidate: str = "default={}",
         scenes: str = "canclip,statue,fern", out: Path = DOCS / "side_by_side.csv") -> None:
    parser = argparse.ArgumentParser(description=description.split("\n\n")[0])
    parser.add_argument("--baseline", default=baseline or None,
                        help="LABEL=JSON: the TrainConfig fields the setting compared against sets")
    parser.add_argument("--candidate", default=candidate, help="LABEL=JSON (default: the default, 'default={}')")
    parser.add_argument("--scenes", default=scenes, help=f"comma-separated, of {', '.join(SCENES)}")
    parser.add_argument("--minutes", type=float, default=1.5)
    parser.add_argument("--steps", type=int, help="a fixed step count instead of --minutes")
    parser.add_argument("--seeds", default="0,1", help="comma-separated, or a range such as 0-7")
    parser.add_argument("--device", help="cpu (default: pinned cores) or cuda")
    parser.add_argument("--jobs", type=int, default=1, help="pairs trained at once (on a GPU)")
    parser.add_argument("--out", default=str(out))
    parser.add_argument("--data", default=str(REPO.parent / "shared" / "data"), help="the folder holding the scenes")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        scene, images, scale, budget, seed, options, device, folder = json.loads(args.child)
        print(json.dumps(one_run(scene, images, scale, budget, seed, options, device, Path(folder))))
        return
    if not args.baseline:
        parser.error("--baseline LABEL=JSON is required: the setting the candidate is compared against")
    settings = [parse_setting(args.baseline), parse_setting(args.candidate)]
    unknown = [name for name in args.scenes.split(",") if name not in SCENES]
    if unknown:
        raise SystemExit(f"unknown scene(s) {', '.join(unknown)}; choose from {', '.join(SCENES)}")
    # --out holds this run's rows only: a committed one is not rewritten without a missing scene's
    scenes = present({name: Path(args.data) / name for name in args.scenes.split(",")}, "--data", rewrites=args.out)
    budget = {"steps": args.steps} if args.steps else {"minutes": args.minutes}
    pairs = [(name, seed) for name in scenes for seed in seed_list(args.seeds)]
    rows = []
    machine = machine_name(args.device)
    with ThreadPoolExecutor(max(1, args.jobs)) as pool:
        for pair_rows in pool.map(lambda job: pair(job[0], budget, job[1], settings, args.device, Path(args.data)), pairs):
            rows += [{**row, "date": date.today().isoformat(), "machine": machine} for row in pair_rows]
            write_rows(Path(args.out), rows)
            print(f"{pair_rows[0]['scene']} seed {pair_rows[0]['seed']}: "
                  + ", ".join(f"{r['setting']} {r['psnr']:.2f} dB ({r['steps']} steps)" for r in pair_rows), flush=True)
    print("\n" + "\n".join(summary(rows, settings[0][0], settings[1][0])))


def write_rows(path: Path, rows: list[dict]) -> None:
    """Every row, under the columns any of them has (a run with another checkout's code may
    report fewer: its cells stay empty)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    columns = list(dict.fromkeys(key for row in rows for key in row))
    with open(path, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=columns, restval="")
        writer.writeheader()
        writer.writerows(rows)


def machine_name(device: str | None) -> str:
    """The CPU's model name (and the GPU, where one trained), as the speed benchmark names them;
    each run trains with one torch thread."""
    import torch

    from speed_accuracy import hardware

    described = hardware(torch.device(device or "cpu"))
    on_cpu = torch.device(device or "cpu").type == "cpu"
    return described.rsplit(", ", 1)[0] + ", one torch thread a run" if on_cpu else described


if __name__ == "__main__":
    main()

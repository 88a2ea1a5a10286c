"""Try a change on the stability study's jobs without editing the package.

    python benchmarks/study_probe.py --scene canclip --pose-degrees 1 --seeds 0-3 --tag default
    python benchmarks/study_probe.py --scene canclip --pose-degrees 1 --seeds 0-3 --tag keep-points --patch PATCH.py
    python benchmarks/study_probe.py --scene lambertian --fraction 0.25 --pose-degrees 0.25,0.5 --seeds 0,1 \
        --noise-draws 1234,101,202,303 --tag held
    python benchmarks/study_probe.py ... --root /tmp/old --tag prior      # a git worktree of an older commit
    python benchmarks/study_probe.py --scene lambertian --fraction 0.75 --seeds 0,4 --keep /tmp/models  # keep the models
    python benchmarks/study_probe.py --scene fern --fraction 0.25 --minutes 1 --seeds 0-3 --tag one-minute  # equal time

Each run is a stability-study job (benchmarks/stability.py: its scenes, held-out views, pose
noise, training config and scores, `fast` preset, one torch thread) in a process of its own,
two side by side.  Before the job that process executes `--patch` (a Python file that sets a
module constant or replaces a function of neulf_core: the change being tried), draws the pose
noise from `--noise-draws` instead of the study's one fixed draw (stability.POSE_NOISE_SEED),
and imports neulf_core and the study from `--root` (another checkout) when given.  The
unpatched default reproduced the study's rows to the digit up to commit 48662af; since the
sweep's projection changed its float rounding (sixty-eighth session), its runs land within that
rounding's noise of them (docs/BENCHMARKS.md, "The sweep's projection").

Prints each (pose noise, noise draw)'s PSNRs by seed, their mean, sd and range (and, where the runs
have them, the held-out scores with poses fitted and with the views moved by the noise's
depth-like part, stability.depth_like_part); appends every
run to `--log` (JSON lines: the study's row plus tag, patch, draw and root).  It writes no docs:
a probe's numbers go into docs/STABILITY.md's lab notebook with the command that made them.
"""

from __future__ import annotations

import argparse
import json
import runpy
import shutil
import statistics
import sys
import tempfile
from dataclasses import asdict
from multiprocessing import get_context
from pathlib import Path

HERE = Path(__file__).resolve().parent
DEFAULT_LOG = Path(tempfile.gettempdir()) / "neulf_probe" / "runs.jsonl"


def use_checkout(root: Path) -> None:
    """Import neulf_core and the study's scripts from `root` (ahead of the installed package)."""
    for path in (root, root / "benchmarks"):
        if str(path) not in sys.path:
            sys.path.insert(0, str(path))


def kept_model_dir(keep: Path, job_fields: dict, draw: int | None) -> Path:
    """Where --keep puts a job's model: one folder per scene, share of the views, pose noise,
    noise draw and seed."""
    name = f"{job_fields['scene']}-views{job_fields['fraction']:g}-pose{job_fields['pose_degrees']:g}deg"
    return keep / (name + (f"-draw{draw}" if draw is not None else "") + f"-seed{job_fields['seed']}")


def keep_trained_models(stability, folder: Path) -> None:
    """Make the study's run copy the model it trains into `folder` before its temporary folder
    goes (to render, diff or probe it afterwards)."""
    train = stability.train

    def train_and_keep(scene, model_dir, config, **kwargs):
        result = train(scene, model_dir, config, **kwargs)
        shutil.rmtree(folder, ignore_errors=True)
        shutil.copytree(model_dir, folder)
        return result

    stability.train = train_and_keep


def run_one(task: tuple[dict, str, int | None, str, str]) -> dict:
    """One job in this (fresh) process: the checkout, the patch, the noise draw, then the study's
    run (its model copied out where `keep` names a folder)."""
    job_fields, patch, draw, root, keep = task
    use_checkout(Path(root))
    import neulf_core
    import stability

    if not Path(neulf_core.__file__).resolve().is_relative_to(Path(root).resolve()):
        raise RuntimeError(f"neulf_core came from {neulf_core.__file__}, not from {root}")
    if patch:
        runpy.run_path(patch)
    if draw is not None:
        stability.POSE_NOISE_SEED = draw
    if keep:
        keep_trained_models(stability, kept_model_dir(Path(keep), job_fields, draw))
    row = stability.run_job(stability.Job(**job_fields))
    return {**row, "draw": draw if draw is not None else stability.POSE_NOISE_SEED}


def parse_list(text: str, kind=float) -> list:
    """'0-3' or '0,1,2' for integers; '0.25,0.5' otherwise.  (Not seed_scatter.parse_seeds: importing
    it would import the study from this checkout before --root's.)"""
    values = []
    for part in filter(None, text.split(",")):
        first, _, last = part.partition("-")
        values += list(range(int(first), int(last) + 1)) if kind is int and last else [kind(part)]
    return values


def plan(args, study) -> list[tuple[dict, str, int | None, str, str]]:
    """The tasks: every pose noise x noise draw x seed of the asked configuration."""
    scenes = {"canclip": (args.canclip, args.canclip_scale), "hci": (args.hci, args.hci_scale),
              "fern": (args.fern, args.fern_scale)}
    for variant in ("lambertian", "shiny", "fine"):
        if args.scene == variant:
            scenes[variant] = (study.render_synthetic(args.scenes_cache, variant), args.synth_scale)
    if args.scene not in scenes or not Path(scenes[args.scene][0]).is_dir():
        raise SystemExit(f"no scene '{args.scene}' here; choose canclip, hci, fern, lambertian, shiny or fine "
                         "(the real captures from ../shared/data, or --canclip / --hci / --fern)")
    path, scale = scenes[args.scene]
    draws = parse_list(args.noise_draws, int) if args.noise_draws else [None]
    tasks = []
    for degrees in parse_list(args.pose_degrees):
        for draw in draws:
            for seed in parse_list(args.seeds, int):
                # (a minutes budget as the study's losses jobs set it: no step count)
                job = study.Job(args.scene, str(path), str(path), scale, "fast", 0 if args.minutes else args.steps, seed,
                                fraction=args.fraction, pose_degrees=degrees, minutes=args.minutes or 0.0,
                                colour_start=study.preset_colour_start("fast"), appearance=False)
                tasks.append((asdict(job), str(Path(args.patch).resolve()) if args.patch else "", draw, str(args.root),
                              str(args.keep.resolve()) if args.keep else ""))
    return tasks


def summary_lines(rows: list[dict], tag: str) -> list[str]:
    """Per (pose noise, draw): PSNRs by seed, mean, sd, range."""
    lines = []
    for key in sorted({(row["pose_degrees"], row["draw"]) for row in rows}):
        group = sorted((row for row in rows if (row["pose_degrees"], row["draw"]) == key), key=lambda row: row["seed"])
        psnrs = [row["psnr"] for row in group if row.get("status") == "finished"]
        failed = len(group) - len(psnrs)
        text = " / ".join(f"{p:.2f}" for p in psnrs)
        if len(psnrs) >= 2:
            text += (f": {statistics.mean(psnrs):.2f} ± {statistics.stdev(psnrs):.3f} sd, "
                     f"range {max(psnrs) - min(psnrs):.2f}")
        lines.append(f"{tag}: pose noise {key[0]:g}°, noise draw {key[1]}, seeds "
                     f"{','.join(str(row['seed']) for row in group)}: {text}"
                     + (f" ({failed} did not finish: {group[0].get('error', '')})" if failed else ""))
        for column, what in (("psnr_pose_fitted", "held-out poses fitted"),
                             ("psnr_noise_part_aligned", "held-out views moved by the noise's depth-like part")):
            values = [row[column] for row in group if row.get("status") == "finished" and row.get(column) is not None]
            if len(values) >= 2:
                lines.append(f"    {what}: " + " / ".join(f"{v:.2f}" for v in values)
                             + f": {statistics.mean(values):.2f} ± {statistics.stdev(values):.3f} sd")
    return lines


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scene", default="canclip", help="canclip, hci, fern, lambertian, shiny or fine")
    parser.add_argument("--fraction", type=float, default=1.0, help="share of the training views kept")
    parser.add_argument("--pose-degrees", default="0", help="comma-separated pose noises (degrees)")
    parser.add_argument("--seeds", default="0-2")
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--minutes", type=float, default=None,
                        help="a minutes budget instead of --steps (as the study's losses jobs train)")
    parser.add_argument("--noise-draws", default="", help="comma-separated seeds of the pose noise (default: the study's)")
    parser.add_argument("--patch", help="a Python file run in each worker before its job")
    parser.add_argument("--root", type=Path, default=HERE.parent, help="the checkout whose code runs")
    parser.add_argument("--keep", type=Path, help="copy each trained model into a folder of its own here "
                                                   "(<scene>-views<share>-pose<noise>deg[-draw<draw>]-seed<seed>)")
    parser.add_argument("--tag", default="probe", help="names the runs in the output and the log")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--log", type=Path, default=DEFAULT_LOG)
    parser.add_argument("--scenes-cache", type=Path, default=None,
                        help="where the synthetic scenes are rendered (default: the stability study's cache)")
    parser.add_argument("--canclip", type=Path, default=None)
    parser.add_argument("--canclip-scale", type=float, default=0.25)
    parser.add_argument("--hci", type=Path, default=None)
    parser.add_argument("--hci-scale", type=float, default=0.5)
    parser.add_argument("--fern", type=Path, default=None)
    parser.add_argument("--fern-scale", type=float, default=0.5, help="of fern's 504x378 images_8 (the study's)")
    parser.add_argument("--synth-scale", type=float, default=0.5)
    return parser.parse_args(argv)


def main(argv=None) -> None:
    args = parse_args(argv)
    if args.patch and not Path(args.patch).is_file():
        raise SystemExit(f"--patch: no file {args.patch}")
    if not (args.root / "neulf_core").is_dir():
        raise SystemExit(f"--root: {args.root} holds no neulf_core")
    use_checkout(args.root)
    import stability

    args.scenes_cache = args.scenes_cache or stability.DEFAULT_CACHE
    args.canclip, args.hci = args.canclip or stability.CANCLIP, args.hci or stability.HCI
    args.fern = args.fern or stability.FERN
    tasks = plan(args, stability)
    # One job per process (spawned, so a patch or another checkout never leaks into the next).
    pool = get_context("spawn").Pool(args.workers, maxtasksperchild=1)
    try:
        rows = pool.map(run_one, tasks)
    except BaseException:
        pool.terminate()
        raise
    # The workers exit by themselves (terminated, pycolmap's signal handler prints a stack trace).
    pool.close()
    pool.join()
    args.log.parent.mkdir(parents=True, exist_ok=True)
    with open(args.log, "a") as handle:
        for row in rows:
            handle.write(json.dumps({**row, "tag": args.tag, "patch": args.patch or "", "root": str(args.root)},
                                    default=float) + "\n")
    print("\n".join(summary_lines(rows, args.tag)))


if __name__ == "__main__":
    main()

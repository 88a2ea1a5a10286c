"""Does a change leave training as it was, to the bit?  Trains a set of configurations with one
checkout's code and writes a fingerprint of everything each model saved; two fingerprints are
then compared entry by entry.

    python benchmarks/same_weights.py --root /tmp/old --out /tmp/old.json     # a worktree of the commit before
    python benchmarks/same_weights.py --out /tmp/new.json                     # this checkout
    python benchmarks/same_weights.py --compare /tmp/old.json /tmp/new.json

    python benchmarks/same_weights.py --scene SCENE_DIR --steps 30 --out F.json   # one plain run of any scene

The configurations are the stability study's jobs (benchmarks/stability.py: its scenes, which it
renders into its cache when missing, and CanClip from ../shared/data) at a few hundred steps,
chosen to pass through the trainer's decisions: the pose check and the far-off restart (CanClip
at 1°, its 6 photos at 2°), two members by the rule (the synthetic scene's 7 photos) and asked
for (CanClip), the per-photo exposure compensation, few photos (4), and a run cancelled at step
120 and resumed.  One torch thread, steps budgets: the runs are deterministic on a CPU.

A fingerprint holds, for every checkpoint a model folder holds (members too), a SHA-256 of each
tensor (weights, optimizer state, pose corrections, exposure transforms) and every number and
string of its metadata and progress, timings left out, and a hash of the progress events the
run reported.  Used in the seventieth session for the trainer's rewrite and in the seventy-first for
moving its rules into rules.py and pose_check.py (docs/STABILITY.md).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

HERE = Path(__file__).resolve().parent
TIMINGS = ("elapsed", "seconds", "sweep_seconds", "wall_seconds", "path", "root", "model_dir", "poses_from", "model")


def fingerprint(value, out: dict, key: str = "") -> dict:
    """Flatten a saved payload into {path: hash or repr}; tensors by their bytes' SHA-256."""
    import torch

    if isinstance(value, torch.Tensor):
        out[key] = hashlib.sha256(value.detach().cpu().contiguous().numpy().tobytes()).hexdigest()[:16]
    elif isinstance(value, dict):
        for name, item in value.items():
            if name not in TIMINGS:
                fingerprint(item, out, f"{key}.{name}")
    elif isinstance(value, (list, tuple)):
        for index, item in enumerate(value):
            fingerprint(item, out, f"{key}[{index}]")
    elif isinstance(value, (int, float, str, bool)) or value is None:
        out[key] = repr(value)
    return out


def model_fingerprint(folder: Path) -> dict:
    """Every checkpoint under `folder` (the model and its members), the RNG states aside."""
    from neulf_core.checkpoint import load_checkpoint  # (the checkout's own, imported from --root)

    out = {}
    for checkpoint in sorted(folder.rglob("checkpoint.pt")):
        payload = load_checkpoint(checkpoint.parent)
        payload.pop("rng", None)
        fingerprint(payload, out, str(checkpoint.parent.relative_to(folder)))
    return out


def events_hash(events: list[dict]) -> str:
    kept = [{k: v for k, v in e.items() if k not in TIMINGS + ("fraction",)} for e in events
            if e.get("event") not in ("step", "loading", "checkpoint")]
    return hashlib.sha256(json.dumps(kept, sort_keys=True, default=str).encode()).hexdigest()[:16]


def study_jobs(stability, cache: Path, canclip: Path) -> dict:
    """name -> (stability.Job, TrainConfig overrides)."""
    lambertian = str(stability.render_synthetic(cache, "lambertian"))
    jittered = str(stability.render_synthetic(cache, "lambertian", jitter=1.0))

    def job(scene, path, scale, steps, truth=None, **options):
        return stability.Job(scene=scene, path=path, truth=truth or path, scale=scale, preset="fast", steps=steps,
                             seed=0, **options)
    return {
        "lambertian": (job("lambertian", lambertian, 0.5, 300), {}),
        "lambertian-4-photos": (job("lambertian", lambertian, 0.5, 1400, fraction=0.25), {}),
        "lambertian-7-photos": (job("lambertian", lambertian, 0.5, 400, fraction=0.5), {}),
        "lambertian-1deg": (job("lambertian", lambertian, 0.5, 300, pose_degrees=1.0), {}),
        "exposure-jitter": (job("jitter1", jittered, 0.5, 200, truth=lambertian, appearance=None), {}),
        "canclip-1deg": (job("canclip", str(canclip), 0.25, 300, pose_degrees=1.0), {}),
        "canclip-two-members": (job("canclip", str(canclip), 0.25, 200), {"members": 2, "members_split": "batch"}),
        "canclip-6-photos-2deg": (job("canclip", str(canclip), 0.25, 400, fraction=0.25, pose_degrees=2.0), {}),
    }


def train_and_fingerprint(train, scene, config, should_stop=None, resume_after_stop: bool = False) -> dict:
    events = []
    with tempfile.TemporaryDirectory(prefix="neulf_same_weights_") as folder:
        train(scene, folder, config, progress=events.append, should_stop=should_stop)
        if resume_after_stop:
            train(scene, folder, config, resume=True)
        result = model_fingerprint(Path(folder))
    if not resume_after_stop:
        result["events"] = events_hash(events)
    return result


def stop_after(calls: int):
    count = {"n": 0}

    def should_stop() -> bool:
        count["n"] += 1
        return count["n"] > calls
    return should_stop


def run(args) -> dict:
    root = args.root.resolve()
    sys.path[:0] = [str(root), str(root / "benchmarks")]
    import torch

    torch.set_num_threads(1)
    import neulf_core
    from neulf_core.train import TrainConfig, train

    if not Path(neulf_core.__file__).resolve().is_relative_to(root):
        raise SystemExit(f"neulf_core came from {neulf_core.__file__}, not {root}")
    if args.scene:
        config = TrainConfig(steps=args.steps, seed=args.seed, validate_seconds=1e9, checkpoint_seconds=1e9)
        return {"scene": train_and_fingerprint(train, str(args.scene), config)}
    import stability

    results = {}
    for name, (job, overrides) in study_jobs(stability, args.cache, args.canclip).items():
        if args.jobs and name not in args.jobs.split(","):
            continue
        scene, _train_views, held = stability.prepare(job)
        config = replace(stability.train_config(job, held), **overrides)
        results[name] = train_and_fingerprint(train, scene, config)
        if name == "lambertian":  # cancelled at step 120, then resumed: as the run never stopped
            results["lambertian-cancelled-and-resumed"] = train_and_fingerprint(
                train, scene, config, should_stop=stop_after(120), resume_after_stop=True)
        print(f"{name}: {len(results[name])} entries", flush=True)
    return results


def compare(first: dict, second: dict) -> list[str]:
    """One line per configuration: the same, or which entries differ."""
    lines = []
    for name in sorted(set(first) | set(second)):
        a, b = first.get(name), second.get(name)
        if a is None or b is None:
            lines.append(f"{name}: only in {'the second' if a is None else 'the first'}")
            continue
        differ = sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))
        lines.append(f"{name}: the same ({len(a)} entries)" if not differ else
                     f"{name}: {len(differ)} of {len(a)} entries differ, e.g. {', '.join(differ[:5])}")
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--root", type=Path, default=HERE.parent, help="the checkout whose code trains")
    parser.add_argument("--out", type=Path, help="where the fingerprints go (JSON)")
    parser.add_argument("--jobs", default="", help="a comma-separated subset of the configurations")
    parser.add_argument("--scene", type=Path, help="train one plain run of this scene instead")
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "neulf_stability",
                        help="the stability study's cache (its rendered scenes)")
    parser.add_argument("--canclip", type=Path, default=HERE.parent.parent / "shared" / "data" / "canclip")
    parser.add_argument("--compare", nargs=2, type=Path, metavar=("FIRST", "SECOND"))
    args = parser.parse_args(argv)
    if args.compare:
        lines = compare(*(json.loads(path.read_text()) for path in args.compare))
        print("\n".join(lines))
        return 0 if all(": the same" in line for line in lines) else 1
    results = run(args)
    if args.out:
        args.out.write_text(json.dumps(results, indent=0, sort_keys=True))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Time of the plane sweep the default trains against (the depth teacher), which the trainer
computes before its first step and counts in the training budget.

    python benchmarks/sweep_time.py [--scene ../shared/data/canclip] [--scale 0.5] \
        [--repeats 3] [--threads 1] [--label NAME] [--out docs/sweep_time.csv]

Sweeps the scene's training views (every 8th view held out, as training does) at the scale
the trainer would (`teacher.compute_sweep_depth_targets`, which the trainer reaches through
`sweep_depth_targets`, which keeps the last result), given each view's mask of representable
pixels as the trainer's rays hand it over (computed before the clock starts; rows labelled
before the sixty-eighth session timed code that traced every view's rays again for it, as the
trainer then did), `--repeats` times in this process, and
prints the median; appends one row per run to the CSV with `--label` (e.g. the commit), so
two versions of the code can be compared on one machine. Also prints a checksum of the
targets: two versions that agree to the bit print the same one.
"""

from __future__ import annotations

import argparse
import hashlib
import statistics
import sys
import time
from datetime import date
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

from neulf_core.dataset import view_uvst  # noqa: E402
from neulf_core.scene import load_scene, split_views  # noqa: E402
from neulf_core.slab import fit_slab  # noqa: E402
from neulf_core.teacher import compute_sweep_depth_targets  # noqa: E402
from reference_data import skip_unless_present  # noqa: E402
from speed_accuracy import append_rows, hardware  # noqa: E402

COLUMNS = ["date", "machine", "label", "scene", "scale", "train_views", "repeat", "seconds", "checksum"]


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", type=Path, default=REPO.parent / "shared" / "data" / "canclip")
    parser.add_argument("--scale", type=float, default=0.5)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--label", default="")
    parser.add_argument("--out", type=Path, default=REPO / "docs" / "sweep_time.csv")
    args = parser.parse_args(argv)
    skip_unless_present(args.scene)
    torch.set_num_threads(args.threads)
    scene = load_scene(args.scene)
    train_views, _ = split_views(scene)
    slab = fit_slab(scene, train_views, scale=args.scale)
    representable = [view_uvst(view, slab, args.scale)[1] for view in train_views]  # (the trainer's rays build them)
    rows = []
    for repeat in range(args.repeats):
        started = time.perf_counter()
        units, confidences = compute_sweep_depth_targets(train_views, slab, args.scale, representable=representable)
        seconds = time.perf_counter() - started
        checksum = hashlib.sha1(units.numpy().tobytes() + confidences.numpy().tobytes()).hexdigest()[:12]
        rows.append({"date": date.today().isoformat(), "machine": hardware(torch.device("cpu")), "label": args.label,
                     "scene": args.scene.name, "scale": args.scale, "train_views": len(train_views),
                     "repeat": repeat, "seconds": round(seconds, 3), "checksum": checksum})
        print(f"repeat {repeat}: {seconds:.2f} s, targets {checksum}", flush=True)
    print(f"median {statistics.median(r['seconds'] for r in rows):.2f} s over {args.repeats} sweeps of "
          f"{len(train_views)} views ({args.label or 'no label'})")
    append_rows(args.out, rows, COLUMNS)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()

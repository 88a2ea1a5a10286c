"""Where a training step and a rendered frame spend their time, on any device (written for a
lent GPU, where both were found to be bound by something other than arithmetic).

    python benchmarks/gpu_profile.py --scene ../shared/data/canclip --scale 1 --device cuda \
        --out PROFILE_DIR [--model-out MODEL_DIR]

Trains the default preset for `--steps` steps; the steps from a third to five sixths of them are
timed (ms per step, synchronised) and profiled with torch.profiler.  Then renders frames of the
first held-out view at --width x --height, times them and profiles a few.  Writes
PROFILE_DIR/profile_train.txt and profile_render.txt (operators by self CPU time and by device
time) and prints the two timings.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch
from torch.profiler import ProfilerActivity, profile

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from render_fps import stretched_intrinsics, synchronise, time_variants  # noqa: E402
from neulf_core.device import pick_device  # noqa: E402
from neulf_core.render import LightField  # noqa: E402
from neulf_core.scene import load_scene, split_views  # noqa: E402
from neulf_core.train import TrainConfig, train  # noqa: E402
from reference_data import skip_unless_present  # noqa: E402

TOP = 30


def activities(device: torch.device) -> list:
    return [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])


def tables(prof, device: torch.device) -> str:
    by_cpu = prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=TOP)
    text = f"== by self CPU time\n{by_cpu}\n"
    if device.type == "cuda":
        text += f"== by device time\n{prof.key_averages().table(sort_by='self_cuda_time_total', row_limit=TOP)}\n"
    return text


class StepWindow:
    """A progress callback that profiles and times the training steps in [first, last)."""

    def __init__(self, first: int, last: int, device: torch.device):
        self.first, self.last, self.device = first, last, device
        self.profiler = profile(activities=activities(device))
        self.started = self.seconds = None

    def __call__(self, event: dict) -> None:
        step = event.get("step")
        if event.get("event") not in ("step", "validate") or step is None:
            return
        if step == self.first:
            synchronise(self.device)
            self.profiler.start()
            self.started = time.perf_counter()
        elif step == self.last and self.started is not None:
            synchronise(self.device)
            self.seconds = time.perf_counter() - self.started
            self.profiler.stop()


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--scene", required=True)
    parser.add_argument("--images")
    parser.add_argument("--scale", type=float, default=1.0)
    parser.add_argument("--steps", type=int, default=600)
    parser.add_argument("--device")
    parser.add_argument("--width", type=int, default=1008)
    parser.add_argument("--height", type=int, default=567)
    parser.add_argument("--frames", type=int, default=20)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--model-out", type=Path, help="where to keep the trained model (default: OUT/model)")
    args = parser.parse_args(argv)
    skip_unless_present(args.scene)
    skip_unless_present(args.images, option="--images")
    device = pick_device(args.device)
    args.out.mkdir(parents=True, exist_ok=True)
    model_dir = args.model_out or args.out / "model"
    scene = load_scene(args.scene, args.images)
    window = StepWindow(args.steps // 3, args.steps * 5 // 6, device)
    train(scene, model_dir, TrainConfig(steps=args.steps, scale=args.scale, device=str(device), validate_seconds=1e9),
          progress=window)
    steps = window.last - window.first
    train_ms = window.seconds * 1000 / steps
    (args.out / "profile_train.txt").write_text(f"{steps} steps, {train_ms:.2f} ms per step (profiled)\n\n" + tables(window.profiler, device))

    light_field = LightField.load(model_dir, str(device))
    view = split_views(scene)[1][0]
    camera = (stretched_intrinsics(view.scaled_camera(1.0), args.width, args.height), args.width, args.height, view.R, view.t)
    seconds = time_variants({"frame": (light_field, False, None, 1)}, camera, args.frames, device)["frame"]
    frame_ms = float(np.median(seconds)) * 1000
    with profile(activities=activities(device)) as prof:
        for _ in range(5):
            light_field.render(*camera, depth=False)
    (args.out / "profile_render.txt").write_text(
        f"{args.width}x{args.height}, precision {'half' if light_field.half else 'full'}, median {frame_ms:.2f} ms per frame "
        f"(unprofiled); 5 frames profiled\n\n" + tables(prof, device))
    print(f"training: {train_ms:.2f} ms per step (steps {window.first}-{window.last}, profiled); "
          f"render {args.width}x{args.height}: {frame_ms:.2f} ms per frame, median of {args.frames}")


if __name__ == "__main__":
    main()

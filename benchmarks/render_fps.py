"""Frames per second of trained light fields at a chosen resolution, on any device.

    python benchmarks/render_fps.py --scene ../shared/data/canclip --model fast=MODEL_DIR \
        [--model other=DIR] [--width 1008 --height 567] [--device cuda] [--precision auto,full] \
        [--repeats 30] [--pixel-samples 1,4] [--out docs/render_fps.csv]

The camera is the first held-out view's, its intrinsics stretched to the asked size.  Each
variant (model x precision x with/without depth) renders through `LightField.render`, the
call the Blender layer makes, so a frame ends as RGB (and depth) arrays in host memory.  Three
warm-up frames, then `--repeats` timed ones, variants interleaved so a slow spell of the
machine hits them alike; the median is reported.  `--pixel-samples` renders each pixel as the
mean of that many points (the CLI's and Blender's default is 4; `LightField.render`'s own is 1).
Appends to docs/render_fps.csv (or --out) and prints a markdown table.
"""

from __future__ import annotations

import argparse
import sys
import time
from datetime import date
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from speed_accuracy import append_rows, hardware  # noqa: E402
from neulf_core.device import pick_device  # noqa: E402
from neulf_core.render import LightField  # noqa: E402
from neulf_core.scene import load_scene, split_views  # noqa: E402
from reference_data import skip_unless_present  # noqa: E402

DOCS = Path(__file__).resolve().parents[1] / "docs"
WARM_UP = 3


def stretched_intrinsics(camera, width: int, height: int) -> np.ndarray:
    """The camera's K for an image of width x height (each axis scaled on its own)."""
    K = np.array(camera.calibration_matrix(), dtype=np.float64)
    K[0] *= width / camera.width
    K[1] *= height / camera.height
    return K


def synchronise(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def time_variants(variants: dict, camera_args: tuple, repeats: int, device: torch.device) -> dict[str, list[float]]:
    """Seconds per frame of each variant (light field, with depth, rays per chunk or None, points a pixel); every repeat renders each variant once, in turn."""
    K, width, height, R, t = camera_args
    times = {label: [] for label in variants}
    for repeat in range(WARM_UP + repeats):
        for label, (light_field, depth, chunk, samples) in variants.items():
            synchronise(device)
            started = time.perf_counter()
            light_field.render(K, width, height, R, t, depth=depth, chunk=chunk, pixel_samples=samples)
            synchronise(device)
            if repeat >= WARM_UP:
                times[label].append(time.perf_counter() - started)
    return times


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--scene", required=True)
    parser.add_argument("--images")
    parser.add_argument("--model", action="append", required=True, help="NAME=MODEL_DIR")
    parser.add_argument("--width", type=int, default=1008)
    parser.add_argument("--height", type=int, default=567)
    parser.add_argument("--device")
    parser.add_argument("--precision", default="auto,full", help="comma-separated: auto, half, full")
    parser.add_argument("--chunks", default="", help="comma-separated rays per chunk to compare (default: the renderer's)")
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: torch's default)")
    parser.add_argument("--pixel-samples", default="1", help="comma-separated points a pixel to compare (1, 4, ...)")
    parser.add_argument("--out", help="CSV to append to (default: docs/render_fps.csv)")
    args = parser.parse_args(argv)
    skip_unless_present(args.scene)
    skip_unless_present(args.images, option="--images")
    if args.threads:
        torch.set_num_threads(args.threads)
    device = pick_device(args.device)
    view = split_views(load_scene(args.scene, args.images))[1][0]
    camera_args = (stretched_intrinsics(view.scaled_camera(1.0), args.width, args.height), args.width, args.height, view.R, view.t)
    variants = {}
    for name, folder in (m.split("=", 1) for m in args.model):
        for precision in args.precision.split(","):
            light_field = LightField.load(folder, str(device), precision=precision)
            shown = "half" if light_field.half else "full"
            for chunk in [int(c) for c in args.chunks.split(",") if c] or [None]:
                for samples in [int(n) for n in args.pixel_samples.split(",")]:
                    for depth in (False, True):
                        label = (f"{name}, {precision} ({shown}), {'rgb+depth' if depth else 'rgb'}"
                                 + (f", chunk {chunk}" if chunk else "") + (f", {samples} points a pixel" if samples != 1 else ""))
                        variants[label] = (light_field, depth, chunk, samples)
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    times = time_variants(variants, camera_args, args.repeats, device)
    peak = torch.cuda.max_memory_allocated(device) / 2**20 if device.type == "cuda" else None
    machine = hardware(device)
    rows = [{"date": date.today().isoformat(), "hardware": machine, "variant": label,
             "resolution": f"{args.width}x{args.height}", "repeats": args.repeats,
             "median_ms": round(float(np.median(seconds)) * 1000, 2), "min_ms": round(min(seconds) * 1000, 2),
             "fps": round(1.0 / float(np.median(seconds)), 1),
             "peak_gpu_mib": round(peak, 1) if peak is not None else ""} for label, seconds in times.items()]
    append_rows(Path(args.out) if args.out else DOCS / "render_fps.csv", rows)
    print(f"\n{args.width}x{args.height}, {machine}, {args.repeats} frames each after {WARM_UP} warm-up"
          + (f", peak GPU memory {peak:.0f} MiB" if peak is not None else "") + "\n")
    print("| variant | median (ms/frame) | min (ms) | frames per second |\n|---|---|---|---|")
    for row in rows:
        print(f"| {row['variant']} | {row['median_ms']:.1f} | {row['min_ms']:.1f} | {row['fps']:.0f} |")


if __name__ == "__main__":
    main()

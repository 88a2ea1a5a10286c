"""Render time per frame of trained fast fields: the current code against the code before the
render speed-up (its DisparityField.forward, kept here as `reference_forward`, with 64k-ray
chunks and ReLUs not in place), interleaved in one process, median of repeats.

    python benchmarks/render_speed.py --scene ../shared/data/canclip --scale 0.5 \
        --model c8=MODEL_DIR --model c4=MODEL_DIR [--threads 2] [--repeats 7] [--no-depth] [--pixel-samples 1,4] \
        [--sample-contrasts 0,0.02]

The camera is the first held-out view's, at the models' training scale.  Models with depth
layers (which the reference code cannot evaluate) are timed with the current code only.
`--blends colour,features` times models with a back surface with each way of blending their
two surfaces (DisparityConfig.back_surface_blend: two decodes or one), current code.
`--sample-contrasts` times the points per pixel above 1 given only to the pixels of more contrast
than each (render.SAMPLE_CONTRAST; 0: every pixel).  `--default-allocator` times the same with glibc's default malloc thresholds (a process-wide
setting, so that comparison takes two runs).  Timings on a shared machine are noisy: compare
the ratios (each repeat renders every variant once, in turn).
"""

from __future__ import annotations

import argparse
import csv
import resource
import sys
import time
from datetime import date
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from neulf_core.fields.disparity import DisparityField  # noqa: E402
from neulf_core.render import SAMPLE_CONTRAST, LightField  # noqa: E402
from neulf_core.scene import load_scene, split_views  # noqa: E402

CURRENT_FORWARD = DisparityField.forward


def reference_forward(self, uvst):
    """DisparityField.forward before the speed-up (commit d63c3d7)."""
    features = self.geometry.features(uvst)
    if self.config.geometry_coarse_to_fine > 0:  # a model saved inside its coarse-to-fine ramp
        weights = self.geometry_scale_weights
        features = features * weights.repeat_interleave(features.shape[1] // weights.numel())
    geometry = self.geometry.decoder(features)
    unit = torch.sigmoid(geometry[:, 3:4])
    delta = self.disparity(unit)
    uv = uvst[:, :2] * self.uv_half + self.uv_centre
    st = uvst[:, 2:] * self.st_half + self.st_centre
    sheared = (st + uv * delta - self.st_centre) / self.st_half
    grid = (sheared / (1.0 + self.config.texture_margin)).view(1, -1, 1, 2)
    features = [F.grid_sample(texture, grid, mode="bilinear", padding_mode="border", align_corners=True)
                .view(texture.shape[1], -1) for texture in self.textures]
    decoder_in = torch.cat(features, 0).t()
    if self.uv_input:
        decoder_in = torch.cat([decoder_in, uvst[:, :2]], 1)
    return self._decode(decoder_in, uvst[:, :2]), unit  # (the sigmoid, and the linear (u, v) slope where on)


def single_fields(light_field) -> list:
    """The fields a model renders: its one, or its members' (neulf_core/members.py)."""
    return list(getattr(light_field.field, "members", [light_field.field]))


def reference_can_render(light_field) -> bool:
    """The reference code predates the depth layers and members: those are timed with the current code only."""
    return len(single_fields(light_field)) == 1 and not light_field.field.config.geometry_layers


def has_back_surface(light_field) -> bool:
    return any(field_module.config.back_surface for field_module in single_fields(light_field))


def use_code(light_fields, current: bool) -> int | None:
    """Switch every model to the current or the reference code; returns the chunk to use."""
    DisparityField.forward = CURRENT_FORWARD if current else reference_forward
    for light_field in light_fields:
        for field_module in single_fields(light_field):
            for layer in (*field_module.geometry.decoder, *field_module.decoder):
                if isinstance(layer, torch.nn.ReLU):
                    layer.inplace = current
    return None if current else 1 << 16


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--scene", required=True)
    parser.add_argument("--images")
    parser.add_argument("--scale", type=float, default=0.5)
    parser.add_argument("--model", action="append", required=True, help="NAME=MODEL_DIR (a fast-field model)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--no-depth", action="store_true")
    parser.add_argument("--pixel-samples", default="1",
                        help="comma-separated points per pixel to time with the current code (render.PIXEL_SAMPLES)")
    parser.add_argument("--sample-contrasts", default=str(SAMPLE_CONTRAST),
                        help="comma-separated sample contrasts to time the points per pixel above 1 with "
                             f"(render.SAMPLE_CONTRAST: the default {SAMPLE_CONTRAST}; 0: the points in every pixel)")
    parser.add_argument("--blends", help="comma-separated back-surface blends to time (colour, features) for models "
                                         "with a back surface (default: each model's own)")
    parser.add_argument("--out", type=Path, help="also write the timings to this CSV (one row a variant: the date, "
                        "machine, size, threads, depth, repeats, median, min and the ratio)")
    parser.add_argument("--default-allocator", action="store_true",
                        help="leave glibc's malloc thresholds as they are (the render path otherwise keeps freed "
                             "buffers, device.keep_freed_cpu_memory); run once with and once without to compare")
    args = parser.parse_args()
    if args.default_allocator:
        import neulf_core.render as render_module
        render_module.keep_freed_cpu_memory = lambda: False
    models = {name: LightField.load(folder, "cpu") for name, folder in (m.split("=", 1) for m in args.model)}
    view = split_views(load_scene(args.scene, args.images))[1][0]
    camera = view.scaled_camera(args.scale)
    K, width, height = camera.calibration_matrix(), int(camera.width), int(camera.height)
    # Layered models, members and more points per pixel: the current code only.
    samples = [int(n) for n in args.pixel_samples.split(",")]
    contrasts = [float(c) for c in args.sample_contrasts.split(",")]
    variants = [(f"{code}, {name}" + (f", {n} points a pixel{where(c)}" if n != 1 else ""), name, code == "current",
                 (n, c), None)
                for name in models for code in ("reference", "current") for n in samples
                for c in (contrasts if n != 1 else [0.0])
                if code == "current" or (n == 1 and reference_can_render(models[name]))]
    if args.blends:
        variants = [variant for variant in variants if not variant[2] or not has_back_surface(models[variant[1]])] + [
            (f"{label}, {blend} blend", name, True, points, blend) for label, name, current, points, _ in variants
            if current and has_back_surface(models[name]) for blend in args.blends.split(",")]
    torch.set_num_threads(args.threads)  # for the timing only
    times = {label: [] for label, *_ in variants}
    own_blend = {id(f): f.config.back_surface_blend for m in models.values() for f in single_fields(m)}
    faults_before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(args.repeats):
        for label, name, current, points, blend in variants:
            chunk = use_code(models.values(), current)
            for field_module in single_fields(models[name]):
                field_module.config.back_surface_blend = blend or own_blend[id(field_module)]
            started = time.perf_counter()
            models[name].render(K, width, height, view.R, view.t, depth=not args.no_depth, chunk=chunk,
                                pixel_samples=points[0], sample_contrast=points[1])
            times[label].append(time.perf_counter() - started)
    use_code(models.values(), True)
    first = variants[0][0]
    print(f"{width}x{height}, {args.threads} threads, depth {not args.no_depth}, {args.repeats} repeats, "
          f"allocator {'default' if args.default_allocator else 'keeping freed buffers'}, "
          f"page faults {resource.getrusage(resource.RUSAGE_SELF).ru_minflt - faults_before} in all")
    rows = []
    for label in times:
        ratio = np.median([a / b for a, b in zip(times[label], times[first])])
        print(f"{label}: median {np.median(times[label]) * 1000:.0f} ms/frame, min {min(times[label]) * 1000:.0f}, "
              f"median ratio to '{first}' {ratio:.3f}")
        rows.append({"date": date.today().isoformat(), "machine": machine(), "variant": label, "width": width,
                     "height": height, "threads": args.threads, "depth": not args.no_depth, "repeats": args.repeats,
                     "median_ms": round(float(np.median(times[label])) * 1000, 1),
                     "min_ms": round(min(times[label]) * 1000, 1), "ratio_to_first": round(float(ratio), 3)})
    if args.out:  # (the README's render times come from such a file, not from a console)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        with open(args.out, "w", newline="") as handle:
            writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)
        print(f"written {args.out}")


def where(contrast: float) -> str:
    """Which pixels take the points, for a variant's label."""
    return " in every pixel" if contrast == 0 else f" where the contrast is above {contrast:g}"


def machine() -> str:
    """The CPU's model name and core count (the timings are this machine's)."""
    import os
    import platform

    try:
        cpu = next(line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name"))
    except (OSError, StopIteration):
        cpu = platform.processor() or platform.machine()
    return f"{cpu}, {os.cpu_count()} cores, torch {torch.__version__}"


if __name__ == "__main__":
    main()

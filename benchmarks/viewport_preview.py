"""How quickly Blender's viewport shows the light field (neulf_blender/viewport.py), measured
through the PreviewRenderer and core the engine uses, on a camera path through the capture.

    python benchmarks/viewport_preview.py --model MODEL_DIR [--regions 960x540,1920x1080] \
        [--preview-pixels 20000,40000,80000] [--routes in-process,worker] [--frames 12] \
        [--moving-seconds 4] [--focus D --aperture A] [--out docs/viewport_preview.csv]

Two ways of looking, per route (Blender's own Python, or the worker process a stock Blender
uses), viewport size and coarse-pass size:
- **stopped**: each view of a spiral through the capture's rig is asked for once the one
  before is shown at full size (a user who moves, then looks): the time from asking to the
  coarse preview and to the full-size image, medians over the views;
- **moving**: a new view of the spiral every 1/30 s for `--moving-seconds` (a user orbiting
  without a pause): how many images a second the viewport gets to show, and how old the view
  of each is when it arrives.
The views are the model's own rig (`Service.spiral`), its intrinsics stretched to each region;
with `--focus` and `--aperture` (model units) each view has that depth of field, as a viewport
looking through a camera whose depth of field is on (at most viewport.COARSE_LENS_SAMPLES lens
samples in the coarse pass, FULL_LENS_SAMPLES at full size; the CSV gives the largest blur at
full size in pixels).
Appends to docs/viewport_preview.csv (or --out) and prints a markdown table.
"""

from __future__ import annotations

import argparse
import importlib
import statistics
import sys
import tempfile
import time
from datetime import date
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from speed_accuracy import append_rows, machine  # noqa: E402
from neulf_core.worker import Service  # noqa: E402

DOCS = REPO / "docs"
MOVING_FPS = 30.0


def extension_modules():
    """neulf_blender's viewport and core modules, imported as the extension package (they use
    relative imports into neulf_core), without Blender."""
    parent = Path(tempfile.mkdtemp(prefix="neulf_ext_"))
    (parent / "neulf_ext").symlink_to(REPO, target_is_directory=True)
    sys.path.insert(0, str(parent))
    return (importlib.import_module("neulf_ext.neulf_blender.viewport"),
            importlib.import_module("neulf_ext.neulf_blender.core"))


def path_requests(model: Path, width: int, height: int, frames: int, lens: dict) -> list[dict]:
    """The spiral's views at width x height (the rig's K stretched to the region)."""
    path = Service().spiral(str(model), frames=frames)
    K = np.array(path["K"], dtype=np.float64)
    K[0] *= width / path["width"]
    K[1] *= height / path["height"]
    return [{"model_dir": str(model), "K": K.tolist(), "width": width, "height": height, "R": R, "t": t, **lens}
            for R, t in zip(path["R"], path["t"])]


def largest_blur_px(model: Path, request: dict) -> float:
    """The largest circle of confusion (pixels) of the request's depth of field over the slab's
    depth range (refocus.max_blur_radius_px), 0 for a pinhole."""
    from neulf_core.refocus import max_blur_radius_px

    if not request.get("aperture"):
        return 0.0
    slab = Service().model_info(str(model))["slab"]
    return max_blur_radius_px(request["K"][0][0], request["aperture"], request["focus_distance"], slab["z_near"],
                              slab["z_far"])


def stopped(viewport, renderer, requests: list[dict]) -> tuple[list[float], list[float], list[float]]:
    """Seconds from asking for each view to its coarse image, to the pass of four times its
    pixels (where the region has one) and to its full-size image."""
    coarse, middle, full = [], [], []
    for request in requests:
        key = viewport.view_key(request, request["model_dir"], 0.0)
        asked = time.perf_counter()
        renderer.want(key, request)
        arrivals, last = [], None
        while renderer.busy:
            shown = renderer.image()
            if shown is not None and shown.key == key and shown is not last:
                last = shown
                arrivals.append(time.perf_counter() - asked)
            time.sleep(0.001)
        full.append(time.perf_counter() - asked)
        coarse.append(arrivals[0] if arrivals else full[-1])  # (a region within the coarse size: one pass)
        if len(renderer.passes(request["width"], request["height"])) == 3 and len(arrivals) >= 2:
            middle.append(arrivals[1])
    return coarse, middle, full


def moving(viewport, renderer, requests: list[dict], seconds: float) -> tuple[float, float]:
    """Images a second the viewport gets while the view changes MOVING_FPS times a second, and
    the median age (s) of the view in each image when it arrives."""
    asked_at, arrivals = {}, []
    started = time.perf_counter()
    last_image, index = renderer.image(), 0  # (the stopped views' last image is not an arrival)
    next_view = started
    while time.perf_counter() - started < seconds:
        now = time.perf_counter()
        if now >= next_view:
            request = requests[index % len(requests)]
            key = viewport.view_key(request, request["model_dir"], float(index))  # (each ask a new view)
            asked_at[key] = now
            renderer.want(key, request)
            index += 1
            next_view += 1.0 / MOVING_FPS
        shown = renderer.image()
        if shown is not None and shown is not last_image:
            last_image = shown
            arrivals.append(time.perf_counter() - asked_at[shown.key])
        time.sleep(0.001)
    elapsed = time.perf_counter() - started
    return len(arrivals) / elapsed, statistics.median(arrivals) if arrivals else float("nan")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", type=Path, required=True)
    parser.add_argument("--regions", default="960x540,1920x1080")
    parser.add_argument("--preview-pixels", default="20000,40000,80000")
    parser.add_argument("--routes", default="in-process,worker")
    parser.add_argument("--frames", type=int, default=12)
    parser.add_argument("--moving-seconds", type=float, default=4.0)
    parser.add_argument("--out", type=Path, default=DOCS / "viewport_preview.csv")
    parser.add_argument("--label", default="")
    parser.add_argument("--focus", type=float, help="a depth of field's focus distance (model units)")
    parser.add_argument("--aperture", type=float, help="its lens radius (model units)")
    args = parser.parse_args(argv)

    viewport, core_module = extension_modules()
    regions = [tuple(int(v) for v in size.split("x")) for size in args.regions.split(",")]
    pixel_options = [int(v) for v in args.preview_pixels.split(",")]
    lens = {"focus_distance": args.focus, "aperture": args.aperture} if args.aperture else {}
    rows = []
    for route in args.routes.split(","):
        core = core_module.Core(sys.executable, mode="WORKER" if route == "worker" else "AUTO")
        assert core.in_process == (route == "in-process"), route
        render = viewport.render_function(core)
        for width, height in regions:
            requests = path_requests(args.model, width, height, args.frames, lens)
            render(requests[0], lambda: False)  # warm up: the model loaded, the worker started
            for pixels in pixel_options:
                renderer = viewport.PreviewRenderer(render, preview_pixels=pixels)
                coarse, middle, full = stopped(viewport, renderer, requests)
                rate, age = moving(viewport, renderer, requests, args.moving_seconds)
                renderer.close()
                row = {"date": date.today().isoformat(), "machine": machine(), "torch_threads": torch.get_num_threads(),
                       "label": args.label, "model": args.model.name, "route": route, "region": f"{width}x{height}",
                       "preview_pixels": pixels, "views": len(requests),
                       "focus_distance": args.focus if lens else "", "aperture": args.aperture if lens else "",
                       "largest_blur_px": round(largest_blur_px(args.model, requests[0]), 1),
                       "coarse_ms_median": round(1000 * statistics.median(coarse), 1),
                       "four_times_ms_median": round(1000 * statistics.median(middle), 1) if middle else "",
                       "full_ms_median": round(1000 * statistics.median(full), 1),
                       "moving_images_per_s": round(rate, 2), "moving_age_ms_median": round(1000 * age, 1)}
                rows.append(row)
                print(f"{route:10s} {width}x{height} coarse<= {pixels:6d} px: coarse {row['coarse_ms_median']:7.1f} ms, "
                      f"full {row['full_ms_median']:7.1f} ms; moving {rate:5.2f} images/s, {1000 * age:6.1f} ms old",
                      flush=True)
        core_module.shutdown()
    append_rows(args.out, rows)
    print("\n| route | region | coarse pass at most | stopped: to the coarse image | to 4 x its pixels | to full size "
          "| moving: images a second | their age |")
    print("|---|---|---|---|---|---|---|---|")
    for row in rows:
        middle = f"{row['four_times_ms_median']:.0f} ms" if row["four_times_ms_median"] != "" else "-"
        print(f"| {row['route']} | {row['region']} | {row['preview_pixels']:,} px | {row['coarse_ms_median']:.0f} ms | "
              f"{middle} | {row['full_ms_median']:.0f} ms | {row['moving_images_per_s']:.1f} | "
              f"{row['moving_age_ms_median']:.0f} ms |")


if __name__ == "__main__":
    main()

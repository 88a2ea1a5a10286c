"""Speed against accuracy: several methods on one scene, same wall-clock budget, one run.

    python benchmarks/speed_accuracy.py --scene ../shared/data/canclip --scale 0.5 --minutes 5 \
        [--methods fast,authors,paper,classic-plane,classic-sweep] [--threads 2] [--device cpu] \
        [--budget-factor authors=20] [--cache DIR [--retrain fast]]

A method written `fast@65536` is that preset with that many rays per training step instead of
its default batch (on a GPU a step of the fast field costs about the same for far more rays).

Learned methods train for the same budget; held-out PSNR is logged every `--every` seconds on
a fixed sample of 65,536 held-out rays (pooled MSE), and at the end every held-out view is
rendered in full and scored (PSNR, SSIM per view, averaged; LPIPS too once its weights were
fetched with `python -m neulf_core fetch-lpips`).  The classic light field
renderings use the training photos directly (no training).  `--budget-factor authors=20` gives
a method that many times the budget (the issue's "8 x 256 network given 20 times more training
time").  With `--cache DIR` each method's rows are kept in DIR and reused by a later run with the
same scene, resolution, budget, seed and threads (`--retrain M` trains M again), so a long
MLP run survives a change to the default; every row records the load average when its method
started, because methods run at different times are then not side by side.  Writes
docs/bench_<scene>.csv (one row per method and time), docs/bench_<scene>.png (PSNR against
training time, render time per frame, and model size) and prints a markdown table.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import platform
import sys
import tempfile
import time
from datetime import date
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from neulf_core.checkpoint import MODEL_NAME  # noqa: E402
from neulf_core.classic import ClassicLightField  # noqa: E402
from neulf_core.device import describe_device, pick_device  # noqa: E402
from neulf_core.fields import count_parameters  # noqa: E402
from neulf_core.lpips import load_lpips, lpips_distance  # noqa: E402
from neulf_core.metrics import psnr, ssim  # noqa: E402
from neulf_core.render import LightField  # noqa: E402
from neulf_core.scene import load_scene, split_views  # noqa: E402
from neulf_core.slab import fit_slab  # noqa: E402
from neulf_core.train import TrainConfig, train  # noqa: E402
from reference_data import skip_unless_present  # noqa: E402

DOCS = Path(__file__).resolve().parents[1] / "docs"


def hardware(device) -> str:
    return f"{machine()}, {describe_device(device)}"


def machine() -> str:
    """The CPU, its cores and torch's version (hardware() adds the device and its threads)."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{cpu}, {os.cpu_count()} cores, torch {torch.__version__}"


def append_rows(path: Path, rows: list[dict], columns: list[str] | None = None) -> None:
    """Add rows to a CSV, with a header when the file is new (the benchmarks that keep adding
    runs to one file share this)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    new_file = not path.is_file()
    with open(path, "a", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=columns or list(rows[0]))
        if new_file:
            writer.writeheader()
        writer.writerows(rows)


def score(render_fn, views, scale) -> dict:
    """Held-out PSNR, SSIM and -- once its weights were fetched (`python -m neulf_core
    fetch-lpips`) -- LPIPS (AlexNet); median render time per frame."""
    perceptual = load_lpips()
    psnrs, ssims, lpipses, seconds = [], [], [], []
    for view in views:
        target = view.load_image(scale).astype(np.float32) / 255.0
        started = time.perf_counter()
        image = render_fn(view)
        seconds.append(time.perf_counter() - started)
        psnrs.append(psnr(image, target))
        ssims.append(ssim(image, target))
        if perceptual is not None:
            lpipses.append(lpips_distance(perceptual, image, target))
    return {"psnr": float(np.mean(psnrs)), "ssim": float(np.mean(ssims)), "lpips": float(np.mean(lpipses)) if lpipses else "",
            "render_s": float(np.median(seconds)), "per_view": [round(p, 2) for p in psnrs]}


def parse_factors(text: str) -> dict[str, float]:
    factors = {}
    for part in filter(None, (p.strip() for p in (text or "").split(","))):
        method, _, value = part.partition("=")
        factors[method.strip()] = float(value)
    return factors


def split_method(method: str) -> tuple[str, int | None]:
    """`fast@65536` -> ("fast", 65536); `fast` -> ("fast", None)."""
    preset, _, batch = method.partition("@")
    return preset, int(batch) if batch else None


def run_learned(method, scene, views, args, common, minutes: float) -> list[dict]:
    preset, batch = split_method(method)
    rows = []
    # Long budgets are logged about as often on the log-time axis as short ones.
    every = max(args.every, 60.0 * minutes / 40)
    with tempfile.TemporaryDirectory() as scratch:
        model_dir = Path(args.keep_models) / common["scene"] / method if args.keep_models else Path(scratch)
        result = train(scene, model_dir, TrainConfig(preset=preset, minutes=minutes, scale=args.scale, batch_size=batch,
                                                     validate_seconds=every, seed=args.seed, device=args.device))
        for record in result.history:
            rows.append({**common, "method": method, "train_s": record["elapsed"], "psnr": record["val_psnr"],
                         "ssim": "", "render_s": "", "model_bytes": "", "steps": record["step"], "kind": "ray sample", "batch": batch or ""})
        field = LightField.load(model_dir, args.device)
        size = (Path(model_dir) / MODEL_NAME).stat().st_size  # the render-only file a user ships
        final = score(lambda v: field.render_view(v, args.scale, depth=False).rgb, views, args.scale)
        rows.append({**common, "method": method, "train_s": round(result.elapsed, 1), "psnr": final["psnr"], "ssim": final["ssim"],
                     "lpips": final["lpips"], "render_s": final["render_s"], "model_bytes": size, "steps": result.step, "kind": "full views", "batch": batch or "",
                     "per_view": final["per_view"], "parameters": count_parameters(field.field),
                     "render_precision": "half" if field.half else "full"})
    return rows


def run_classic(mode, scene, train_views, views, args, common) -> list[dict]:
    started = time.perf_counter()
    slab = fit_slab(scene, train_views, scale=args.scale)
    classic = ClassicLightField(train_views, slab, args.scale, device=pick_device(args.device))
    setup = time.perf_counter() - started
    final = score(lambda v: classic.render_view(v, args.scale, mode=mode), views, args.scale)
    photos = classic.images.numel()  # uint8 bytes: the "model" is the photos themselves
    return [{**common, "method": f"classic-{mode}", "train_s": round(setup, 1), "psnr": final["psnr"], "ssim": final["ssim"],
             "lpips": final["lpips"], "render_s": final["render_s"], "model_bytes": photos, "steps": 0, "kind": "full views", "per_view": final["per_view"]}]


def chart(rows, path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(16, 4.8))
    methods = sorted({r["method"] for r in rows})
    for i, method in enumerate(methods):
        colour = f"C{i}"
        curve = [r for r in rows if r["method"] == method and r["kind"] == "ray sample" and r["psnr"] not in ("", None)]
        final = [r for r in rows if r["method"] == method and r["kind"] == "full views"]
        if curve:
            axes[0].plot([max(r["train_s"], 1) for r in curve], [r["psnr"] for r in curve], "-", color=colour, label=method)
        for r in final:
            if method.startswith("classic"):
                axes[0].axhline(r["psnr"], color=colour, linestyle="--", label=f"{method} (no training)")
            else:
                axes[0].plot([r["train_s"]], [r["psnr"]], "o", color=colour)
            axes[1].plot([r["render_s"] * 1000], [r["psnr"]], "o", color=colour, label=method)
            axes[2].plot([r["model_bytes"] / 1e6], [r["psnr"]], "o", color=colour, label=method)
    axes[0].set(xscale="log", xlabel="training time (s, log)", ylabel="held-out PSNR (dB)", title="quality vs training time")
    axes[1].set(xscale="log", xlabel="render time per frame (ms, log)", title="quality vs render time")
    axes[2].set(xscale="log", xlabel="model size (MB; classic: the photos)", title="quality vs model size")
    for ax in axes:
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--scene", required=True)
    parser.add_argument("--images")
    parser.add_argument("--scale", type=float, default=0.5)
    parser.add_argument("--minutes", type=float, default=5.0)
    parser.add_argument("--every", type=float, default=15.0)
    parser.add_argument("--methods", default="fast,authors,paper,classic-plane,classic-sweep")
    parser.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: torch's default)")
    parser.add_argument("--device")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--name", help="name used in the output files (default: the scene folder's name)")
    parser.add_argument("--budget-factor", default="", help="e.g. authors=20: that method trains 20 times --minutes")
    parser.add_argument("--cache", help="folder that keeps each method's rows for reuse by a later run")
    parser.add_argument("--retrain", default="", help="comma-separated methods to run again even when cached")
    parser.add_argument("--keep-models", help="keep each trained model in DIR/<name>/<method> (default: thrown away)")
    args = parser.parse_args()
    skip_unless_present(args.scene)
    skip_unless_present(args.images, option="--images")
    if args.threads:
        torch.set_num_threads(args.threads)
    device = pick_device(args.device)
    scene = load_scene(args.scene, args.images)
    train_views, held_out = split_views(scene)
    name = args.name or Path(args.scene).name
    width, height = held_out[0].scaled_camera(args.scale).width, held_out[0].scaled_camera(args.scale).height
    common = {"scene": name, "resolution": f"{width}x{height}", "train_views": len(train_views), "held_out": len(held_out),
              "seed": args.seed, "threads": torch.get_num_threads(), "hardware": hardware(device)}
    factors = parse_factors(args.budget_factor)
    retrain = set(filter(None, args.retrain.split(",")))
    rows = []
    for method in args.methods.split(","):
        minutes = args.minutes * factors.get(method, 1.0)
        method_common = {**common, "budget_min": minutes, "date": date.today().isoformat(),
                         "load_at_start": round(os.getloadavg()[0], 2)}
        cache = Path(args.cache) / name / f"{method}.json" if args.cache else None
        key = {k: method_common[k] for k in ("scene", "resolution", "seed", "threads", "budget_min")}
        cached = json.loads(cache.read_text()) if cache is not None and cache.is_file() else None
        if cached is not None and cached["key"] == key and method not in retrain:
            print(f"== {method}: reused from {cache} ({cached['rows'][-1]['date']})", file=sys.stderr, flush=True)
            rows += cached["rows"]
        else:
            print(f"== {method} ({minutes:g} min)", file=sys.stderr, flush=True)
            if method.startswith("classic-"):
                method_rows = run_classic(method.split("-", 1)[1], scene, train_views, held_out, args, method_common)
            else:
                method_rows = run_learned(method, scene, held_out, args, method_common, minutes)
            rows += method_rows
            if cache is not None:
                cache.parent.mkdir(parents=True, exist_ok=True)
                cache.write_text(json.dumps({"key": key, "rows": method_rows}))
        final = rows[-1]
        print(f"   {method}: {final['psnr']:.2f} dB, SSIM {final['ssim']:.3f}, render {final['render_s'] * 1000:.0f} ms/frame", file=sys.stderr)
    DOCS.mkdir(exist_ok=True)
    fields = list(dict.fromkeys(k for r in rows for k in r))
    with open(DOCS / f"bench_{name}.csv", "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=fields)
        writer.writeheader()
        writer.writerows(rows)
    chart(rows, DOCS / f"bench_{name}.png", f"{name} {common['resolution']}, {len(train_views)} train / {len(held_out)} held-out views, "
          f"{args.minutes:g} min budget{budget_note(factors)}; {common['threads']} threads; {common['hardware']}; "
          f"{date.today().isoformat()}")
    print(f"\n{name} at {common['resolution']}, {common['threads']} threads, {common['hardware']}\n")
    print("| method | budget (min) | training (s) | steps | held-out PSNR | SSIM | LPIPS | render (ms/frame) | model (MB) | load at start | date |\n"
          "|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        if r["kind"] == "full views":
            lpips = f"{r['lpips']:.3f}" if isinstance(r.get("lpips"), float) else "-"
            print(f"| {r['method']} | {r['budget_min']:g} | {r['train_s']} | {r['steps']} | {r['psnr']:.2f} | {r['ssim']:.3f} | {lpips} | "
                  f"{r['render_s'] * 1000:.0f} | {r['model_bytes'] / 1e6:.2f} | {r['load_at_start']} | {r['date']} |")


def budget_note(factors: dict[str, float]) -> str:
    return "".join(f", {method} x{factor:g}" for method, factor in factors.items())


if __name__ == "__main__":
    main()

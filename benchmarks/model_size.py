"""Model size against held-out quality: texture variants of the fast field, float32 and model.pt.

    python benchmarks/model_size.py --scene ../shared/data/canclip --scale 0.5 --steps 3000 \
        --variants "c8;c4;c6,x0.8;c8,x0.7" [--threads 1] [--out docs/model_size_canclip.csv]

A variant is comma-separated: `cN` texture channels, `xF` finest texture size as a factor of
the default (about one texel per training pixel), `lN` texture levels.  Each variant trains
the fast field for the same number of steps (steps, not minutes: machine load does not bias
the comparison), then every held-out view is rendered in full from checkpoint.pt (float32)
and from model.pt (8-bit feature grids, float16 and float32 weights, written afresh from the
checkpoint by this version) and scored.  `--existing NAME=DIR` scores an already trained
model folder instead of training one.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from speed_accuracy import append_rows  # noqa: E402

from neulf_core.autosize import texture_overrides  # noqa: E402
from neulf_core.checkpoint import CHECKPOINT_NAME, load_checkpoint, save_render_model  # noqa: E402
from neulf_core.metrics import psnr  # noqa: E402
from neulf_core.render import LightField  # noqa: E402
from neulf_core.scene import load_scene, split_views  # noqa: E402
from neulf_core.train import TrainConfig, train  # noqa: E402
from reference_data import skip_unless_present  # noqa: E402


def parse_variant(text: str, train_views, scale: float) -> dict:
    channels, factor, levels = None, 1.0, None
    for part in filter(None, (p.strip() for p in text.split(","))):
        kind, value = part[0], part[1:]
        if kind == "c":
            channels = int(value)
        elif kind == "x":
            factor = float(value)
        elif kind == "l":
            levels = int(value)
        else:
            raise SystemExit(f"unknown variant part {part!r}")
    return texture_overrides(train_views, scale, factor, channels=channels, levels=levels)


def held_out_scores(full: LightField, small: LightField, views, scale: float) -> tuple[float, float, float]:
    """Mean PSNR of the float32 and the model.pt renders, and their largest pixel difference."""
    scores, largest = [], 0.0
    for view in views:
        target = view.load_image(scale).astype(np.float32) / 255.0
        a, b = (lf.render_view(view, scale, depth=False).rgb for lf in (full, small))
        scores.append((psnr(a, target), psnr(b, target)))
        largest = max(largest, float(np.abs(a - b).max()))
    return float(np.mean([s[0] for s in scores])), float(np.mean([s[1] for s in scores])), largest


def score_model(name: str, model_dir: Path, held_out, scale: float, steps) -> dict:
    full = LightField.load(model_dir / CHECKPOINT_NAME, "cpu")
    with tempfile.TemporaryDirectory() as folder:  # model.pt as this version writes it
        shipped = save_render_model(Path(folder), load_checkpoint(model_dir))
        small, model_pt_bytes = LightField.load(shipped, "cpu"), shipped.stat().st_size
    config = full.meta["field_config"]
    float32_bytes = sum(t.numel() * 4 for t in full.field.state_dict().values())
    psnr_float32, psnr_model_pt, largest = held_out_scores(full, small, held_out, scale)
    return {"variant": name, "texture_size": "x".join(map(str, config["texture_size"])),
            "channels": config["texture_channels"], "levels": config["texture_levels"], "steps": steps,
            "psnr_float32": round(psnr_float32, 4), "psnr_model_pt": round(psnr_model_pt, 4),
            "max_rgb_difference": round(largest, 6),
            "weights_float32_mb": round(float32_bytes / 1e6, 3),
            "model_pt_mb": round(model_pt_bytes / 1e6, 3),
            "checkpoint_mb": round((model_dir / CHECKPOINT_NAME).stat().st_size / 1e6, 3)}


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--scene", required=True)
    parser.add_argument("--images")
    parser.add_argument("--scale", type=float, default=0.5)
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--variants", default="", help="semicolon-separated, e.g. \"c8;c4;c8,x0.7\"")
    parser.add_argument("--existing", action="append", default=[], help="NAME=MODEL_DIR: score a trained model")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", help="CSV to append rows to")
    args = parser.parse_args()
    skip_unless_present(args.scene)
    skip_unless_present(args.images, option="--images")
    torch.set_num_threads(args.threads)
    scene = load_scene(args.scene, args.images)
    train_views, held_out = split_views(scene)
    rows = [score_model(name, Path(folder), held_out, args.scale, "")
            for name, folder in (item.split("=", 1) for item in args.existing)]
    for text in filter(None, (v.strip() for v in args.variants.split(";"))):
        overrides = parse_variant(text, train_views, args.scale)
        with tempfile.TemporaryDirectory() as model_dir:
            started = time.perf_counter()
            train(scene, model_dir, TrainConfig(preset="fast", steps=args.steps, scale=args.scale, seed=args.seed,
                                                field_overrides=overrides, validate_seconds=1e9, checkpoint_seconds=1e9))
            rows.append({**score_model(text, Path(model_dir), held_out, args.scale, args.steps),
                         "train_s": round(time.perf_counter() - started, 1)})
        print(rows[-1], file=sys.stderr, flush=True)
    for row in rows:
        row.update(scene=Path(args.scene).name, scale=args.scale, seed=args.seed)
    if args.out:
        append_rows(Path(args.out), rows)
    print("| variant | texture | channels | float32 PSNR | model.pt PSNR | model.pt (MB) | checkpoint (MB) |\n|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['variant']} | {r['texture_size']} x {r['levels']} levels | {r['channels']} | {r['psnr_float32']:.3f} | "
              f"{r['psnr_model_pt']:.3f} | {r['model_pt_mb']:.2f} | {r['checkpoint_mb']:.2f} |")


if __name__ == "__main__":
    main()

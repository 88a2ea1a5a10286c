"""Held-out evaluation: render each held-out view through its own camera, compare with its photo."""

from __future__ import annotations

import csv
import json
import time
from pathlib import Path

import numpy as np

from .errors import NeulfError
from .images import save_rgb
from .lpips import load_lpips, lpips_distance
from .metrics import psnr, ssim
from .render import LightField
from .scene import load_scene


def evaluate_model(model_dir, scene_dir, *, images_dir=None, out_dir=None, views=None, device=None,
                   save_images: bool = True) -> dict:
    light_field = LightField.load(model_dir, device, precision="full")  # scores are float32's
    scene = load_scene(scene_dir, images_dir)
    light_field.check_scene(scene)
    names = views or light_field.meta["scene"]["held_out"]
    if not names:
        raise NeulfError("the model was trained without held-out views (--holdout-every 0); name views with --views.")
    out = Path(out_dir) if out_dir else Path(model_dir) / "eval"
    scale = light_field.trained_scale
    mean_colour = np.asarray(light_field.meta["scene"]["mean_colour"], dtype=np.float32)
    rows, baseline = [], []
    perceptual = load_lpips()  # None until the user fetched its weights (python -m neulf_core fetch-lpips)
    for name in names:
        view = scene.view(name)
        photo = view.load_image(scale)
        started = time.perf_counter()
        rendering = light_field.render_view(view, scale, depth=False)
        seconds = time.perf_counter() - started
        target = photo.astype(np.float32) / 255.0
        rows.append({"view": view.name, "psnr": psnr(rendering.rgb, target), "ssim": ssim(rendering.rgb, target),
                     "render_seconds": seconds, "width": photo.shape[1], "height": photo.shape[0]})
        if perceptual is not None:
            rows[-1]["lpips"] = lpips_distance(perceptual, rendering.rgb, target)
        baseline.append(psnr(np.broadcast_to(mean_colour, target.shape), target))
        if save_images:
            save_rgb(out / f"{view.stem}.png", rendering.rgb)
    report = {
        "model": str(model_dir), "scene": str(scene_dir), "scale": scale, "views": rows,
        "mean_psnr": float(np.mean([r["psnr"] for r in rows])), "mean_ssim": float(np.mean([r["ssim"] for r in rows])),
        "mean_colour_psnr": float(np.mean(baseline)), "device": str(light_field.device),
    }
    if perceptual is not None:
        report["mean_lpips"] = float(np.mean([r["lpips"] for r in rows]))
    out.mkdir(parents=True, exist_ok=True)
    (out / "eval.json").write_text(json.dumps(report, indent=2))
    with open(out / "eval.csv", "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    report["written"] = str(out / "eval.json")
    return report

"""Held-out evaluation: render each held-out view through its own camera, compare with its photo."""

from __future__ import annotations

import csv
import io
import json
import time
from pathlib import Path

import numpy as np

from .errors import NeulfError
from .files import atomic_write_bytes
from .images import save_rgb
from .lpips import load_lpips, lpips_distance
from .metrics import psnr, ssim
from .outputs import refuse_clashing_names, refuse_writing_over_photos, view_file_stems
from .render import SAMPLE_CONTRAST, LightField
from .poses import fit_view_pose
from .scene import camera_spacing, load_scene, select_views
from .trained_scene import (changed_cameras_note, changed_photos_note, images_dir_as_trained, other_photos_note,
                            scale_as_trained)


def evaluate_model(model_dir, scene_dir, *, images_dir=None, out_dir=None, views=None, device=None,
                   save_images: bool = True, fit_poses: bool = False, pixel_samples: int | None = None,
                   sample_contrast: float = SAMPLE_CONTRAST) -> dict:
    """Scores per held-out view, each rendered with `pixel_samples` points per pixel (None: the
    render's default, LightField.default_pixel_samples) in the pixels of more contrast than
    `sample_contrast` (what `render` writes); with `fit_poses` also after fitting each view's pose to its photo
    (poses.fit_view_pose), the fairer score where the reconstruction's poses carry error."""
    light_field = LightField.load(model_dir, device, precision="full")  # scores are float32's
    saved = light_field.meta["scene"]
    scene = load_scene(scene_dir, images_dir_as_trained(scene_dir, images_dir, saved))
    light_field.check_scene(scene)
    names = _view_names(views, saved["held_out"], scene)
    model_path = Path(model_dir).expanduser()  # (a model file given: its folder's eval/, not model.pt/eval)
    out = Path(out_dir).expanduser() if out_dir else (model_path.parent if model_path.is_file() else model_path) / "eval"
    chosen = [scene.view(name) for name in names]
    stems = view_file_stems(chosen, scene.views)  # (a rig's left/f1.png and right/f1.png: left_f1, right_f1)
    if save_images:
        files = {view.name: [f"{stems[view.name]}.png"] for view in chosen}
        refuse_clashing_names(files, out)
        refuse_writing_over_photos(out, [name for names in files.values() for name in names],
                                   [view.image_path for view in scene.views], scene.images_dir, scene.root)
    notes = [note for note in (other_photos_note(chosen, saved), changed_cameras_note(chosen, saved),
                               changed_photos_note(chosen, saved, "their scores compare the model with other photos "
                                                                   "than it learnt.")) if note]
    mean_colour = np.asarray(light_field.meta["scene"]["mean_colour"], dtype=np.float32)
    rows, baseline, used_samples = [], [], set()
    perceptual = load_lpips()  # None until the user fetched its weights (python -m neulf_core fetch-lpips)
    for view in chosen:
        scale = scale_as_trained(view, saved, light_field.trained_scale)  # (photos of another folder: note)
        photo = view.load_image(scale)
        started = time.perf_counter()
        rendering = light_field.render_view(view, scale, depth=False, pixel_samples=pixel_samples,
                                            sample_contrast=sample_contrast)
        seconds = time.perf_counter() - started
        used_samples.add(rendering.pixel_samples)
        notes += [f"{view.name}: {warning}" for warning in rendering.warnings]  # (rays past the capture: a low score)
        target = photo.astype(np.float32) / 255.0
        rows.append({"view": view.name, "psnr": psnr(rendering.rgb, target), "ssim": ssim(rendering.rgb, target),
                     "render_seconds": seconds, "width": photo.shape[1], "height": photo.shape[0]})
        if perceptual is not None:
            rows[-1]["lpips"] = lpips_distance(perceptual, rendering.rgb, target)
        if fit_poses:
            spacing = camera_spacing(np.asarray(light_field.meta["rig"]["centres"]))  # the training rig's
            fitted, degrees, moved = fit_view_pose(light_field, view, scale, spacing)
            fitted_render = light_field.render_view(fitted, scale, depth=False, pixel_samples=pixel_samples,
                                                    sample_contrast=sample_contrast)
            rows[-1].update(psnr_pose_fitted=psnr(fitted_render.rgb, target),
                            pose_fit_degrees=degrees, pose_fit_shift=moved)
        baseline.append(psnr(np.broadcast_to(mean_colour, target.shape), target))
        if save_images:
            save_rgb(out / f"{stems[view.name]}.png", rendering.rgb)
    report = {
        "model": str(model_dir), "scene": str(scene_dir), "scale": light_field.trained_scale, "views": rows,
        "images": str(scene.images_dir) if scene.images_dir else None, "warnings": notes,
        "mean_psnr": float(np.mean([r["psnr"] for r in rows])), "mean_ssim": float(np.mean([r["ssim"] for r in rows])),
        "mean_colour_psnr": float(np.mean(baseline)), "device": str(light_field.device), "sample_contrast": sample_contrast,
        # (the points each view took: None asked takes the default, render.default_pixel_samples)
        "pixel_samples": used_samples.pop() if len(used_samples) == 1 else sorted(used_samples),
        # (which state of the model was scored: an eval run while training goes on is tied to its step)
        "model_step": light_field.meta.get("progress", {}).get("step"),
        "model_status": light_field.meta.get("progress", {}).get("status"),
    }
    if perceptual is not None:
        report["mean_lpips"] = float(np.mean([r["lpips"] for r in rows]))
    if fit_poses:
        report["mean_psnr_pose_fitted"] = float(np.mean([r["psnr_pose_fitted"] for r in rows]))
    # Each written whole or not at all, as the renders (files.atomic_write_bytes), and eval.json
    # last: a run stopped between the two had left a new eval.json beside an older eval.csv.  Now
    # an eval.json is there only when the eval.csv beside it is of the same run.
    table = io.StringIO(newline="")
    writer = csv.DictWriter(table, fieldnames=list(rows[0]))
    writer.writeheader()
    writer.writerows(rows)
    (out / "eval.json").unlink(missing_ok=True)
    atomic_write_bytes(out / "eval.csv", table.getvalue().encode())
    atomic_write_bytes(out / "eval.json", json.dumps(report, indent=2).encode())
    report["written"] = str(out / "eval.json")
    return report


def _view_names(views, held_out: list[str], scene) -> list[str]:
    """The views to score: `views` names them, as a list or as one name in a string (not
    spelt out letter by letter); None or empty means the model's held-out views; "held-out"
    and "all" (every view of the scene, the training views too: how well the model fits its
    photos) may stand among names.  Each view is scored once."""
    if isinstance(views, Path):
        views = str(views)
    if isinstance(views, str):
        views = [views] if views.strip() else None
    try:
        names = [str(name) for name in views] if views is not None else []
    except TypeError:
        raise NeulfError(f"views={views!r}: give a view name, a list of view names, 'all' or 'held-out'.") from None
    return [view.name for view in select_views(scene, names or ["held-out"], held_out)]

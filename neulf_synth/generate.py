"""Render the project's forward-facing test scene with exact ground truth.

`generate_scene(out_dir)` builds the scene from an empty Blender session (this replaces
whatever scene the current bpy session holds), renders every camera of a small planar rig
with Cycles, and writes:

    images/view_RR_CC.png                  8-bit sRGB RGB, row RR and column CC of the rig
    ground_truth/cameras.json              K, R, t per view (COLMAP conventions), exposures
    ground_truth/depth_view_RR_CC.npy      float32 HxW depth along the optical axis, inf = none
    ground_truth/object_index_view_RR_CC.npy  uint8 HxW object pass index, 0 = background
    ground_truth/scene.json                objects (pass index, matrix_world, size), planes
    sparse_gt/0/                           binary COLMAP model with the exact poses (optional)
    summary.json                           the returned summary: paths and timings
"""

from __future__ import annotations

import json
from pathlib import Path
import time
from typing import Callable

import bpy
import numpy as np
from PIL import Image

from . import layout
from .blender_scene import add_camera, build_scene
from .cameras import intrinsics_from_blender, render_size, world_to_camera
from .colmap_model import write_model
from .render import render_view

UNITS = ("Blender scene units (metres); world Z up; the rig looks along +Y; "
         "depth is z along the camera's optical axis")
POINTS_PER_VIEW = 1500


def generate_scene(out_dir, *, variant: str = "lambertian", grid=(4, 4), size=(320, 240),
                   samples: int = 32, exposure_jitter_stops: float = 0.0, seed: int = 0,
                   write_gt_model: bool = True,
                   progress: Callable[[str], None] | None = None) -> dict:
    """Render the scene into `out_dir` and return a summary (also written as summary.json).

    `grid` is (rows, cols) of the camera rig, `size` the image (width, height). `progress`,
    if given, receives one line per rendered view.
    """
    _validate(variant, grid, size, samples, exposure_jitter_stops)
    out = Path(out_dir).resolve()
    images_dir, truth_dir = out / "images", out / "ground_truth"
    images_dir.mkdir(parents=True, exist_ok=True)
    truth_dir.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()

    texture_factor = layout.FINE_TEXTURE_FACTOR if variant == "fine" else 1.0
    scene, objects = build_scene(variant, tuple(size), samples, seed, texture_factor)
    views = layout.camera_views(tuple(grid), seed, exposure_jitter_stops)
    cameras = [add_camera(scene, view.name, view.position, layout.LOOK_AT) for view in views]
    build_seconds = time.perf_counter() - started

    records, render_seconds, render_cpu_seconds, outputs = [], [], [], []
    for number, (view, camera) in enumerate(zip(views, cameras), start=1):
        image_path = images_dir / f"{view.name}.png"
        rendered = render_view(scene, camera, view.exposure_stops, image_path)
        depth_path = truth_dir / f"depth_{view.name}.npy"
        index_path = truth_dir / f"object_index_{view.name}.npy"
        np.save(depth_path, rendered.depth)
        np.save(index_path, rendered.object_index)
        records.append(_view_record(scene, camera, image_path.name, view.exposure_stops))
        render_seconds.append(rendered.seconds)
        render_cpu_seconds.append(rendered.cpu_seconds)
        outputs.append((image_path, depth_path, index_path))
        if progress:
            progress(f"[{number}/{len(views)}] {image_path.name} rendered in "
                     f"{rendered.seconds:.2f} s (exposure {view.exposure_stops:+.2f} stops)")

    cameras_path = truth_dir / "cameras.json"
    _write_json(cameras_path, {"views": records, "units": UNITS, "variant": variant,
                               "seed": seed})
    scene_path = truth_dir / "scene.json"
    _write_json(scene_path, _scene_record(objects, variant))

    model_started = time.perf_counter()
    model_dir = out / "sparse_gt" / "0" if write_gt_model else None
    if model_dir is not None:
        _write_gt_model(model_dir, records, outputs, seed)
    model_seconds = time.perf_counter() - model_started

    summary = {
        "out_dir": str(out),
        "variant": variant, "grid": list(grid), "size": list(size), "samples": samples,
        "exposure_jitter_stops": exposure_jitter_stops, "seed": seed,
        "blender_version": bpy.app.version_string,
        "images": [str(image) for image, _, _ in outputs],
        "depth": [str(depth) for _, depth, _ in outputs],
        "object_index": [str(index) for _, _, index in outputs],
        "cameras_json": str(cameras_path),
        "scene_json": str(scene_path),
        "sparse_gt": str(model_dir) if model_dir is not None else None,
        "timings": {
            "build_scene_s": round(build_seconds, 3),
            "render_s": [round(s, 3) for s in render_seconds],
            "render_total_s": round(sum(render_seconds), 3),
            # CPU time of all render threads: on a shared machine, this divided by the core
            # count estimates the wall time the renders would take on an idle one.
            "render_cpu_total_s": round(sum(render_cpu_seconds), 3),
            "gt_model_s": round(model_seconds, 3),
            "total_s": round(time.perf_counter() - started, 3),
        },
    }
    _write_json(out / "summary.json", summary)
    return summary


def _validate(variant, grid, size, samples, exposure_jitter_stops) -> None:
    if variant not in layout.VARIANTS:
        raise ValueError(f"variant must be one of {layout.VARIANTS}, got {variant!r}")
    if len(grid) != 2 or min(grid) < 1:
        raise ValueError(f"grid must be (rows, cols) with both >= 1, got {grid!r}")
    if len(size) != 2 or min(size) < 8:
        raise ValueError(f"size must be (width, height) of at least 8 pixels, got {size!r}")
    if samples < 1:
        raise ValueError(f"samples must be >= 1, got {samples}")
    if exposure_jitter_stops < 0:
        raise ValueError(f"exposure_jitter_stops must be >= 0, got {exposure_jitter_stops}")


def _view_record(scene, camera, image_name: str, exposure_stops: float) -> dict:
    width, height = render_size(scene.render)
    K = intrinsics_from_blender(camera.data, scene.render)
    R, t = world_to_camera(camera.matrix_world)
    return {"name": image_name, "width": width, "height": height, "K": K.tolist(),
            "R": R.tolist(), "t": t.tolist(), "exposure_stops": exposure_stops}


def _scene_record(objects: dict, variant: str) -> dict:
    """What tests need to check geometry: every object's transform, size and pass index."""
    specs = {spec.name: spec for spec in layout.scene_objects()}
    return {
        "variant": variant,
        "units": UNITS,
        "look_at": layout.LOOK_AT.tolist(),
        "objects": [
            {"name": name, "kind": specs[name].kind, "pass_index": obj.pass_index,
             "material": obj.active_material.name, "size": specs[name].size,
             "matrix_world": [list(row) for row in obj.matrix_world]}
            for name, obj in objects.items()
        ],
        # Planes as (point, unit normal towards the cameras) in world coordinates.
        "planes": {
            name: {"point": list(objects[name].matrix_world.translation),
                   "normal": list((objects[name].matrix_world.to_3x3()
                                   @ objects[name].data.polygons[0].normal).normalized())}
            for name, spec in specs.items() if spec.kind == "quad"
        },
    }


def _write_gt_model(model_dir: Path, records: list[dict], outputs: list[tuple], seed: int) -> None:
    # A few views spread over the rig (first, middle, last) cover the scene well enough.
    sources = []
    for index in sorted({0, len(records) // 2, len(records) - 1}):
        image_path, depth_path, _ = outputs[index]
        image = np.asarray(Image.open(image_path).convert("RGB"))
        sources.append((records[index], np.load(depth_path), image))
    write_model(model_dir, records, sources, POINTS_PER_VIEW, seed)


def _write_json(path: Path, data: dict) -> None:
    path.write_text(json.dumps(data, indent=1) + "\n")

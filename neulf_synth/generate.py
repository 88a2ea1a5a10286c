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

from dataclasses import dataclass
import json
from pathlib import Path
import time
from typing import Callable

import bpy
import numpy as np

from . import layout
from .blender_scene import add_camera, build_scene
from .cameras import intrinsics_from_blender, render_size, world_to_camera
from .materials import appearance
from .render import render_view

UNITS = ("Blender scene units (metres); world Z up; the rig looks along +Y; "
         "depth is z along the camera's optical axis")
POINTS_PER_VIEW = 1500
# Everything generate_scene writes, as glob patterns relative to the output folder.
OUTPUT_PATTERNS = ("images/view_*.png", "ground_truth/depth_view_*.npy",
                   "ground_truth/object_index_view_*.npy", "ground_truth/cameras.json",
                   "ground_truth/scene.json", "sparse_gt/0/*.bin", "summary.json")


@dataclass
class ViewOutput:
    record: dict  # this view's entry in cameras.json
    image: Path
    depth: Path
    object_index: Path
    seconds: float
    cpu_seconds: float


def generate_scene(out_dir, *, variant: str = "lambertian", grid=(4, 4), size=(320, 240),
                   samples: int = 32, exposure_jitter_stops: float = 0.0, seed: int = 0, arrangement: int = 0,
                   write_gt_model: bool = True,
                   progress: Callable[[str], None] | None = None) -> dict:
    """Render the scene into `out_dir` and return a summary (also written as summary.json).

    `variant`: "lambertian", "shiny" (mirror sphere, glass monkey) or "fine" (texture
    frequencies x6). `grid` is (rows, cols) of the camera rig, `size` the image (width,
    height), `samples` the most Cycles samples per pixel (adaptive sampling stops earlier
    where a pixel has converged). Each view's exposure is drawn uniformly in
    [-exposure_jitter_stops, exposure_jitter_stops]. `seed` fixes camera jitter, exposures and
    Cycles' noise. `arrangement`: 0 the documented layout, another number the objects placed by
    a draw of their own (layout.arranged_objects). `progress`, if given, receives one line per
    rendered view.
    """
    _validate(variant, grid, size, samples, exposure_jitter_stops)
    started = time.perf_counter()
    out = Path(out_dir).resolve()
    _remove_previous_outputs(out)
    texture_factor = layout.FINE_TEXTURE_FACTOR if variant == "fine" else 1.0
    scene, objects = build_scene(variant, tuple(size), samples, seed, texture_factor, arrangement)
    views = layout.camera_views(tuple(grid), seed, exposure_jitter_stops)
    build_seconds = time.perf_counter() - started

    outputs = _render_views(scene, views, out, progress)
    truth_dir = out / "ground_truth"
    _write_json(truth_dir / "cameras.json", {"views": [o.record for o in outputs],
                                             "units": UNITS, "variant": variant, "seed": seed})
    _write_json(truth_dir / "scene.json", _scene_record(objects, variant, arrangement))
    model_started = time.perf_counter()
    model_dir = out / "sparse_gt" / "0" if write_gt_model else None
    if model_dir is not None:
        _write_gt_model(model_dir, outputs, seed)
    timings = {
        "build_scene_s": build_seconds,
        "render_s": [o.seconds for o in outputs],
        "render_total_s": sum(o.seconds for o in outputs),
        # CPU time of all render threads: on a shared machine, this divided by the core
        # count estimates the wall time the renders would take on an idle one.
        "render_cpu_total_s": sum(o.cpu_seconds for o in outputs),
        "gt_model_s": time.perf_counter() - model_started,
        "total_s": time.perf_counter() - started,
    }
    summary = {
        "out_dir": str(out),
        "variant": variant, "grid": list(grid), "size": list(size), "samples": samples,
        "exposure_jitter_stops": exposure_jitter_stops, "seed": seed, "arrangement": arrangement,
        "blender_version": bpy.app.version_string,
        "images": [str(o.image) for o in outputs],
        "depth": [str(o.depth) for o in outputs],
        "object_index": [str(o.object_index) for o in outputs],
        "cameras_json": str(truth_dir / "cameras.json"),
        "scene_json": str(truth_dir / "scene.json"),
        "sparse_gt": str(model_dir) if model_dir is not None else None,
        "timings": _rounded(timings),
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


def _remove_previous_outputs(out: Path) -> None:
    """Delete files of an earlier run (e.g. a larger grid), so none can be mistaken for ours.

    Only files matching OUTPUT_PATTERNS are touched; anything else in `out` stays.
    """
    for pattern in OUTPUT_PATTERNS:
        for path in out.glob(pattern):
            path.unlink()


def _render_views(scene, views: list[layout.ViewSpec], out: Path,
                  progress: Callable[[str], None] | None) -> list[ViewOutput]:
    images_dir, truth_dir = out / "images", out / "ground_truth"
    images_dir.mkdir(parents=True, exist_ok=True)
    truth_dir.mkdir(parents=True, exist_ok=True)
    cameras = [add_camera(scene, view.name, view.position, layout.LOOK_AT) for view in views]
    outputs = []
    for number, (view, camera) in enumerate(zip(views, cameras), start=1):
        image = images_dir / f"{view.name}.png"
        rendered = render_view(scene, camera, view.exposure_stops, image)
        depth = truth_dir / f"depth_{view.name}.npy"
        object_index = truth_dir / f"object_index_{view.name}.npy"
        np.save(depth, rendered.depth)
        np.save(object_index, rendered.object_index)
        record = _view_record(scene, camera, image.name, view.exposure_stops)
        outputs.append(ViewOutput(record, image, depth, object_index,
                                  rendered.seconds, rendered.cpu_seconds))
        if progress:
            progress(f"[{number}/{len(views)}] {image.name} rendered in "
                     f"{rendered.seconds:.2f} s (exposure {view.exposure_stops:+.2f} stops)")
    return outputs


def _view_record(scene, camera, image_name: str, exposure_stops: float) -> dict:
    width, height = render_size(scene.render)
    K = intrinsics_from_blender(camera.data, scene.render)
    R, t = world_to_camera(camera.matrix_world)
    return {"name": image_name, "width": width, "height": height, "K": K.tolist(),
            "R": R.tolist(), "t": t.tolist(), "exposure_stops": exposure_stops}


def _scene_record(objects: dict, variant: str, arrangement: int = 0) -> dict:
    """What tests need to check geometry: every object's transform, size and pass index."""
    specs = {spec.name: spec for spec in layout.scene_objects(arrangement)}
    return {
        "variant": variant,
        "units": UNITS,
        "look_at": layout.LOOK_AT.tolist(),
        "objects": [
            {"name": name, "kind": specs[name].kind, "pass_index": obj.pass_index,
             "material": obj.active_material.name,
             "appearance": appearance(variant, specs[name].material), "size": specs[name].size,
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


def _write_gt_model(model_dir: Path, outputs: list[ViewOutput], seed: int) -> None:
    # Imported here: pycolmap and Pillow are needed only for the model, not for rendering.
    from PIL import Image

    from .colmap_model import write_model

    # A few views spread over the rig (first, middle, last) cover the scene well enough.
    sources = []
    for index in sorted({0, len(outputs) // 2, len(outputs) - 1}):
        output = outputs[index]
        image = np.asarray(Image.open(output.image).convert("RGB"))
        sources.append((output.record, np.load(output.depth), image))
    write_model(model_dir, [o.record for o in outputs], sources, POINTS_PER_VIEW, seed)


def _rounded(timings: dict) -> dict:
    return {key: [round(v, 3) for v in value] if isinstance(value, list) else round(value, 3)
            for key, value in timings.items()}


def _write_json(path: Path, data: dict) -> None:
    path.write_text(json.dumps(data, indent=1) + "\n")

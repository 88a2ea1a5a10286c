"""Renders one view: the sRGB PNG plus its ground-truth depth and object-index maps.

Cycles' depth pass is planar depth (z along the camera's optical axis), not ray length;
`tests/test_synth.py` checks this against the analytic depth of the back wall. Background
pixels get Cycles' 1e10 sentinel, which becomes inf here.
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass
import os
from pathlib import Path
import sys
import tempfile
import time

import bpy
import numpy as np

from .blender_scene import GROUND_TRUTH_OUTPUT_NODE


@dataclass
class RenderedView:
    depth: np.ndarray  # float32 (H, W), row 0 at the top, inf where nothing was hit
    object_index: np.ndarray  # uint8 (H, W), the hit object's pass_index, 0 for background
    seconds: float  # wall-clock time of the render
    cpu_seconds: float  # CPU time of this process (all render threads) during the render


def render_view(scene, camera, exposure_stops: float, image_path: Path) -> RenderedView:
    scene.camera = camera
    scene.view_settings.exposure = exposure_stops
    scene.render.filepath = str(image_path)
    file_output = scene.compositing_node_group.nodes[GROUND_TRUTH_OUTPUT_NODE]
    with tempfile.TemporaryDirectory(prefix="neulf_synth_exr_") as exr_dir:
        file_output.directory = exr_dir + "/"
        start, cpu_start = time.perf_counter(), time.process_time()
        with _blender_log_silenced():
            bpy.ops.render.render(write_still=True)
        seconds, cpu_seconds = time.perf_counter() - start, time.process_time() - cpu_start
        depth = read_single_channel_exr(_find_exr(exr_dir, "Depth"))
        object_index = read_single_channel_exr(_find_exr(exr_dir, "ObjectIndex"))
    depth[depth >= camera.data.clip_end] = np.inf
    return RenderedView(depth, np.rint(object_index).astype(np.uint8), seconds, cpu_seconds)


@contextmanager
def _blender_log_silenced():
    """Hide Blender's "Saved: ..." lines, which it prints to file descriptor 1 for every file.

    Render failures still surface: bpy.ops raises them as Python exceptions.
    """
    sys.stdout.flush()
    saved_stdout = os.dup(1)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        yield
    finally:
        os.dup2(saved_stdout, 1)
        os.close(saved_stdout)
        os.close(devnull)


def _find_exr(directory: str, item_name: str) -> Path:
    # The File Output node decorates file names (prefix, frame number) differently across
    # Blender versions; each view gets its own directory, so matching the item name suffices.
    matches = sorted(Path(directory).glob(f"*{item_name}*.exr"))
    if len(matches) != 1:
        found = sorted(p.name for p in Path(directory).iterdir())
        raise RuntimeError(f"expected one {item_name} EXR in {directory}, found {found}")
    return matches[0]


def read_single_channel_exr(path: Path) -> np.ndarray:
    """First channel of a float EXR as float32 (H, W) with row 0 at the top."""
    image = bpy.data.images.load(str(path), check_existing=False)
    try:
        image.colorspace_settings.is_data = True  # raw values, no colour conversion
        width, height = image.size
        pixels = np.empty(width * height * image.channels, dtype=np.float32)
        image.pixels.foreach_get(pixels)
    finally:
        bpy.data.images.remove(image)
    # Blender stores image rows bottom to top.
    return pixels.reshape(height, width, -1)[::-1, :, 0].copy()

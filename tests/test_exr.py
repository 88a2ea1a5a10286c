"""neulf_core/exr.py: the OpenEXR files `render --exr` writes, read back by the tests' own
reader (tests/exr_file.py, written from the file-format document) and by Blender's."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from exr_file import read_exr
from neulf_core.exr import NO_DEPTH, depth_for_compositing, rendering_channels, srgb_to_linear, write_exr


def _channels(height=5, width=7):
    rng = np.random.default_rng(0)
    return {"R": rng.random((height, width), np.float32), "G": rng.random((height, width), np.float32),
            "B": np.linspace(0, 4, height * width, dtype=np.float32).reshape(height, width),  # above 1: HDR kept
            "Z": rng.random((height, width), np.float32) * 10 + 1}


def test_written_channels_read_back_exactly(tmp_path):
    channels = _channels()
    write_exr(tmp_path / "a.exr", channels)
    back = read_exr(tmp_path / "a.exr")
    assert sorted(back) == ["B", "G", "R", "Z"]
    for name, plane in channels.items():
        assert np.array_equal(back[name], plane), name  # row 0 at the top both ways
    assert [p.name for p in tmp_path.iterdir()] == ["a.exr"]  # written beside and renamed: no partial file left


def test_channels_of_other_sizes_none_or_empty_are_refused(tmp_path):
    with pytest.raises(ValueError, match="same size"):
        write_exr(tmp_path / "b.exr", {"R": np.zeros((2, 3)), "G": np.zeros((3, 2))})
    with pytest.raises(ValueError, match="same size"):
        write_exr(tmp_path / "b.exr", {"R": np.zeros((2, 3, 3))})
    with pytest.raises(ValueError, match="at least one channel"):
        write_exr(tmp_path / "b.exr", {})
    with pytest.raises(ValueError, match="at least one pixel"):  # (Blender's reader refuses such a file)
        write_exr(tmp_path / "b.exr", {"R": np.zeros((0, 3))})
    assert list(tmp_path.iterdir()) == []


def test_a_renderings_channels_are_linear_colour_and_compositing_depth():
    rgb = np.array([[[0.0, 0.5, 1.0], [0.04045, 0.2, 0.9]]], np.float32)
    depth = np.array([[2.5, np.nan]], np.float32)
    channels = rendering_channels(rgb, depth)
    assert channels["G"][0, 0] == pytest.approx(0.21404, abs=1e-5) and channels["B"][0, 0] == 1.0
    assert channels["R"][0, 1] == pytest.approx(0.04045 / 12.92)
    assert channels["Z"].tolist() == [[2.5, NO_DEPTH]]
    assert "Z" not in rendering_channels(rgb, None) and "A" not in rendering_channels(rgb, None)
    with_alpha = rendering_channels(rgb, depth, np.array([[True, False]]))
    assert with_alpha["A"].tolist() == [[1.0, 0.0]]
    assert with_alpha["B"][0, 1] == 0.0 and with_alpha["B"][0, 0] == 1.0  # premultiplied: no colour off the slab
    assert depth_for_compositing(np.array([np.inf, -np.inf, 1.0])).tolist() == [NO_DEPTH, NO_DEPTH, 1.0]
    assert srgb_to_linear(np.array([-0.5, 1.5])).tolist() == [0.0, 1.0]


def test_blender_reads_the_file(tmp_path):
    """Blender's own EXR reader (bpy, in a fresh process): the colour channels as written."""
    pytest.importorskip("bpy")
    channels = _channels()
    write_exr(tmp_path / "c.exr", channels)
    script = ("import bpy, json, numpy as np, sys\n"
              "image = bpy.data.images.load(sys.argv[1])\n"
              "width, height = image.size\n"
              "pixels = np.empty(width * height * image.channels, np.float32)\n"
              "image.pixels.foreach_get(pixels)\n"
              "print('PIXELS', json.dumps({'size': [width, height], 'channels': image.channels, "
              "'float': image.is_float, 'values': pixels.tolist()}))\n")
    run = subprocess.run([sys.executable, "-c", script, str(tmp_path / "c.exr")], capture_output=True, text=True,
                         timeout=300)
    line = next((l for l in run.stdout.splitlines() if l.startswith("PIXELS ")), None)
    assert line is not None, run.stdout[-2000:] + run.stderr[-2000:]
    seen = json.loads(line[len("PIXELS "):])
    assert seen["size"] == [7, 5] and seen["float"]
    pixels = np.array(seen["values"], np.float32).reshape(5, 7, seen["channels"])[::-1]  # Blender: bottom row first
    for index, name in enumerate("RGB"):
        assert np.allclose(pixels[..., index], channels[name], atol=1e-6), name

"""Writing frames to an H.264 MP4 (PyAV), and depth maps to viewable colour images."""

from __future__ import annotations

from pathlib import Path
from typing import Iterable

import numpy as np

from .errors import NeulfError

# Anchor colours of a perceptually ordered map (dark blue -> cyan -> yellow -> dark red).
_DEPTH_COLOURS = np.array([[48, 18, 59], [70, 134, 251], [27, 229, 181], [164, 252, 60], [251, 185, 56], [228, 70, 10], [122, 4, 3]], float)


def depth_to_colour(depth: np.ndarray) -> np.ndarray:
    """(H, W) depth -> (H, W, 3) uint8, near = warm, far = cool, spread by inverse depth."""
    inverse = np.where(np.isfinite(depth) & (depth > 0), 1.0 / np.where(depth > 0, depth, 1.0), np.nan)
    finite = inverse[np.isfinite(inverse)]
    if finite.size == 0:
        return np.zeros((*depth.shape, 3), np.uint8)
    lo, hi = np.percentile(finite, [1, 99])
    unit = np.clip((inverse - lo) / max(hi - lo, 1e-12), 0, 1)
    unit = np.nan_to_num(unit, nan=0.0)
    position = unit * (len(_DEPTH_COLOURS) - 1)
    index = np.minimum(position.astype(int), len(_DEPTH_COLOURS) - 2)
    weight = (position - index)[..., None]
    colour = _DEPTH_COLOURS[index] * (1 - weight) + _DEPTH_COLOURS[index + 1] * weight
    colour[~np.isfinite(inverse)] = 0
    return colour.astype(np.uint8)


def write_video(frames: Iterable[np.ndarray], path: str | Path, fps: int = 30) -> int:
    """Encode (H, W, 3) frames (uint8 or float [0, 1]) to `path`; returns the frame count."""
    import av  # imported here: only video writing needs it

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    count = 0
    container = av.open(str(path), mode="w")
    try:
        stream = None
        for frame in frames:
            if frame.dtype != np.uint8:
                frame = np.clip(np.round(frame * 255), 0, 255).astype(np.uint8)
            if stream is None:
                stream = container.add_stream("libx264", rate=fps)
                # H.264 with yuv420p needs even sizes; pad by repeating the last row/column.
                stream.height, stream.width = frame.shape[0] + frame.shape[0] % 2, frame.shape[1] + frame.shape[1] % 2
                stream.pix_fmt = "yuv420p"
                stream.options = {"crf": "18"}
            frame = np.pad(frame, ((0, stream.height - frame.shape[0]), (0, stream.width - frame.shape[1]), (0, 0)), mode="edge")
            for packet in stream.encode(av.VideoFrame.from_ndarray(np.ascontiguousarray(frame), format="rgb24")):
                container.mux(packet)
            count += 1
        if stream is None:
            raise NeulfError("no frames to write to the video.")
        for packet in stream.encode():
            container.mux(packet)
    finally:
        container.close()
    return count

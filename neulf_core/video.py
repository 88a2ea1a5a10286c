"""Writing frames to an H.264 MP4 (PyAV), and depth maps to viewable colour images."""

from __future__ import annotations

import contextlib
import math
import os
import secrets
from fractions import Fraction
from pathlib import Path
from typing import Iterable

import numpy as np

from .errors import NeulfError

# The containers write_video puts H.264 in, by file suffix (what the CLI's --out takes).
VIDEO_SUFFIXES = (".mp4", ".mov", ".mkv", ".m4v")
# No player shows more frames a second; a rate far past it (1e300) overflowed in the encoder.
FASTEST_FRAME_RATE = 1000

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


class VideoCutShort(KeyboardInterrupt):
    """A video stopped part-way (Ctrl-C, SIGTERM): the file asked for was not written; the
    frames so far were kept as `partial` (NAME.partial.mp4), or None where none could be."""

    def __init__(self, path: Path, partial: Path | None, frames: int):
        left = f"the earlier {path} is kept as it was" if path.exists() else f"{path} was not written"
        kept = f"the frames made are in {partial}" if partial else "it was stopped inside the encoder: none were kept"
        super().__init__(f"the video stopped after {frames} frame(s), unfinished: {left}; {kept}")
        self.path, self.partial, self.frames = path, partial, frames


def _remove_abandoned_temporaries(path: Path) -> None:
    """Delete the temporaries of earlier runs for `path` whose process is gone (killed outright,
    SIGKILL, before it could remove its own): each had stayed beside the video, as big as the
    frames it had written.  A live process's (another run writing the same name) is left."""
    from .lock import process_alive

    for leftover in path.parent.glob(f".{path.stem}.*.tmp{path.suffix}"):
        pid = leftover.name[len(path.stem) + 2:].split(".", 1)[0]
        if pid.isdigit() and not process_alive(int(pid)):
            leftover.unlink(missing_ok=True)


def partial_video_path(path: str | Path) -> Path:
    """Where a video stopped part-way keeps its frames: spiral.mp4 -> spiral.partial.mp4."""
    path = Path(path)
    return path.with_name(f"{path.stem}.partial{path.suffix}")


def write_video(frames: Iterable[np.ndarray], path: str | Path, fps: float = 30) -> int:
    """Encode frames to `path` (.mp4, .mov, .mkv or .m4v); returns the frame count.

    Frames are (H, W, 3) RGB, (H, W) grey or (H, W, 4) RGBA (alpha dropped), uint8 or float
    [0, 1], all the size of the first; `fps` may be fractional (29.97).

    The video is encoded under a temporary name beside `path`, which it replaces only once
    finished: a run stopped part-way had replaced an earlier video with a cut-short one that
    played as finished (Ctrl-C) or with an unplayable stub (SIGTERM).  An error leaves nothing;
    a KeyboardInterrupt between two frames (the user chose to stop there) keeps the frames so
    far as partial_video_path(path) and raises VideoCutShort, which says where."""
    import av  # imported here: only video writing needs it

    path = _video_path(path)
    rate = _frame_rate(fps)
    path.parent.mkdir(parents=True, exist_ok=True)
    _remove_abandoned_temporaries(path)
    # (the suffix kept last: PyAV picks the container from it)
    temporary = path.with_name(f".{path.stem}.{os.getpid()}.{secrets.token_hex(4)}.tmp{path.suffix}")
    count, encoding = 0, False
    container = av.open(str(temporary), mode="w")
    try:
        stream = None
        for frame in frames:
            frame = _rgb_uint8(frame, count)
            if stream is None:
                size = frame.shape[:2]
                stream = container.add_stream("libx264", rate=rate)
                # H.264 with yuv420p needs even sizes; pad by repeating the last row/column.
                stream.height, stream.width = size[0] + size[0] % 2, size[1] + size[1] % 2
                stream.pix_fmt = "yuv420p"
                stream.options = {"crf": "18"}
            elif frame.shape[:2] != size:
                # Padding or cropping it to fit would put a wrong frame in the video, silently.
                raise NeulfError(f"video frame {count} is {frame.shape[1]}x{frame.shape[0]} but the first frame is "
                                 f"{size[1]}x{size[0]}: every frame of a video must be the same size.")
            frame = np.pad(frame, ((0, stream.height - size[0]), (0, stream.width - size[1]), (0, 0)), mode="edge")
            frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(frame), format="rgb24")
            # A KeyboardInterrupt anywhere but here lands between two frames, what is encoded
            # whole; here, a packet the encoder gave could be lost (a broken video): `encoding`.
            encoding = True
            container.mux(stream.encode(frame))
            count += 1
            encoding = False
        if stream is None:
            raise NeulfError("no frames to write to the video.")
        encoding = True
        _finish(container, stream, temporary)
    except KeyboardInterrupt as stop:
        if count == 0:
            _discard(container, temporary)
            raise
        if encoding:  # (rare: a frame's render takes the time) nothing whole to keep
            _discard(container, temporary)
            raise VideoCutShort(path, None, count) from stop
        try:
            _finish(container, stream, temporary)
        except BaseException:  # (a second Ctrl-C while finishing)
            _discard(container, temporary)
            raise
        partial = partial_video_path(path)
        os.replace(temporary, partial)
        raise VideoCutShort(path, partial, count) from stop
    except BaseException:
        _discard(container, temporary)
        raise
    os.replace(temporary, path)
    return count


def _finish(container, stream, path: Path) -> None:
    """The encoder's held-back frames written, the container closed, the file on disk."""
    container.mux(stream.encode())
    container.close()
    with open(path, "rb+") as handle:  # (on disk before it replaces anything: files.atomic_write_bytes's care)
        os.fsync(handle.fileno())


def _discard(container, path: Path) -> None:
    """The cut-short temporary file removed (the error that stopped it is the one to say)."""
    with contextlib.suppress(Exception):
        container.close()
    path.unlink(missing_ok=True)


def _video_path(path: str | Path) -> Path:
    """`path` checked before anything is rendered: PyAV picks the container from the suffix,
    and one that cannot hold H.264 (.png, .gif, none) fails only at the first frame."""
    path = Path(path).expanduser()
    if path.is_dir() or path.suffix.lower() not in VIDEO_SUFFIXES:
        raise NeulfError(f"cannot write a video to {path}: give a file name ending in {', '.join(VIDEO_SUFFIXES)} (H.264).")
    return path


def _frame_rate(fps) -> Fraction:
    """`fps` as the exact fraction PyAV wants (it takes no float): 29.97 -> 2997/100, and
    30000/1001 (NTSC) back to itself; a rate that rounds to zero is refused with the rest."""
    try:
        value = float(fps)
    except (TypeError, ValueError):
        value = math.nan
    rate = Fraction(value).limit_denominator(1001) if math.isfinite(value) else Fraction(0)
    if rate <= 0 or rate > FASTEST_FRAME_RATE:
        raise NeulfError(f"video frame rate {fps!r}: give a positive number of frames per second up to "
                         f"{FASTEST_FRAME_RATE} (e.g. 30 or 29.97).")
    return rate


def _rgb_uint8(frame, index: int) -> np.ndarray:
    """Frame `index` as (H, W, 3) uint8: grey repeated into RGB, alpha dropped (a video has
    none), floats taken as [0, 1] with NaN black."""
    frame = np.asarray(frame)
    if frame.ndim == 2:
        frame = frame[..., None]
    if frame.ndim != 3 or frame.shape[2] not in (1, 3, 4) or 0 in frame.shape[:2] or not (
            np.issubdtype(frame.dtype, np.number) or frame.dtype == bool):
        raise NeulfError(f"video frame {index} is a {frame.dtype} array of shape {frame.shape}: give (H, W, 3) "
                         "RGB frames, uint8 or float in [0, 1] ((H, W) grey and (H, W, 4) RGBA are taken too).")
    if frame.shape[2] == 1:
        frame = np.repeat(frame, 3, axis=2)
    frame = frame[..., :3]
    if frame.dtype != np.uint8:
        frame = np.clip(np.round(np.nan_to_num(frame.astype(np.float64), nan=0.0) * 255), 0, 255).astype(np.uint8)
    return frame

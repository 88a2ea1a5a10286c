"""Photos from a video: a handheld capture filmed rather than photographed.

A walk-around clip holds thousands of frames, most of them near copies of their neighbours and
many blurred by the camera's motion.  Structure from motion wants a few dozen sharp photos
spread over the path, so the clip's duration is cut into equal windows and each window gives
its sharpest frame: the one whose grayscale Laplacian varies most (motion blur takes the fine
detail away first).  Frames are turned as the video is shown (a phone's portrait clip is stored
sideways with a rotation to apply) and written as PNG, in order, for `reconstruct`.
"""

from __future__ import annotations

import contextlib
import math
from pathlib import Path
from typing import Callable

import numpy as np

from .errors import NeulfError
from .images import IMAGE_EXTENSIONS, save_rgb

# Containers a phone or camera writes video in (what `frames` takes; `reconstruct` names them).
VIDEO_INPUT_SUFFIXES = (".mp4", ".mov", ".m4v", ".mkv", ".avi", ".webm", ".mts")
DEFAULT_FRAME_COUNT = 60  # photos a walk-around clip gives: enough overlap for SfM, a minute of it on a CPU
SHARPNESS_WIDTH = 480  # frames are judged at this width: sharpness there is the detail SfM's features see


def is_video(path: Path) -> bool:
    return Path(path).suffix.lower() in VIDEO_INPUT_SUFFIXES


def sharpness(grey: np.ndarray) -> float:
    """Variance of the 4-neighbour Laplacian of a grayscale frame (judged at SHARPNESS_WIDTH)."""
    grey = grey.astype(np.float32)
    laplacian = (grey[1:-1, :-2] + grey[1:-1, 2:] + grey[:-2, 1:-1] + grey[2:, 1:-1] - 4 * grey[1:-1, 1:-1])
    return float(laplacian.var()) if laplacian.size else 0.0


# FFmpeg's demuxers for a single image file (a PNG or JPEG given as the video: "gave 1 frame(s)
# ... film a longer, slower pass" had followed).  Not GIF's, nor image2 (an image sequence):
# those may hold many frames.
STILL_IMAGE_FORMATS = {"png_pipe", "jpeg_pipe", "webp_pipe", "bmp_pipe", "tiff_pipe", "exr_pipe", "dpx_pipe",
                       "j2k_pipe", "pgm_pipe", "ppm_pipe", "qoi_pipe", "svg_pipe", "jpegxl_pipe", "hdr_pipe"}


def _judged(frame) -> np.ndarray:
    """The frame's grayscale at most SHARPNESS_WIDTH wide, from the decoder's own scaler: every
    frame is judged, and a full-size RGB copy of each (6 MB at 1080p) would be work thrown away
    for all but the sharpest."""
    width = min(frame.width, SHARPNESS_WIDTH)
    height = max(3, round(frame.height * width / frame.width))
    return frame.reformat(width=width, height=height, format="gray").to_ndarray()


def upright(rgb: np.ndarray, rotation: float) -> np.ndarray:
    """The frame as the video is shown: `rotation` (PyAV's VideoFrame.rotation) is the
    counter-clockwise turn the display applies, in degrees."""
    quarter_turns = int(round(rotation / 90.0)) % 4
    return np.ascontiguousarray(np.rot90(rgb, quarter_turns)) if quarter_turns else rgb


def extract_frames(video: Path, out_dir: Path, count: int = DEFAULT_FRAME_COUNT,
                   progress: Callable[[int, int], None] | None = None) -> list[Path]:
    """The sharpest frame of each of `count` equal windows of `video`'s duration, written to
    `out_dir` as frame_0001.png, ... (a new or empty folder); returns their paths.
    `progress(done, total)` follows the frames decoded (total: the container's estimate)."""
    import av

    video, out_dir = Path(video).expanduser(), Path(out_dir).expanduser()
    _refuse_inputs(video, out_dir, count)
    try:
        container = av.open(str(video))
    except (av.error.FFmpegError, OSError) as exc:
        raise NeulfError(f"cannot read {video} as a video ({exc}); give a video file (MP4, MOV, ...).") from None
    created = not out_dir.exists()
    written: list[Path] = []
    try:
        with container, _decoding_errors_said(video):
            if not container.streams.video:
                raise NeulfError(f"{video} holds no video stream.")
            if container.format.name in STILL_IMAGE_FORMATS:  # (FFmpeg reads a photo as a one-frame video)
                raise NeulfError(f"{video} is a still image, not a video: give a video file (MP4, MOV, ...), or "
                                 "reconstruct a folder of photos.")
            stream = container.streams.video[0]
            stream.thread_type = "AUTO"
            total = _frame_estimate(stream, container)
            out_dir.mkdir(parents=True, exist_ok=True)
            for rgb in _sharpest_per_window(container.decode(stream), total, count, progress):
                path = out_dir / f"frame_{len(written) + 1:04d}.png"
                save_rgb(path, rgb)  # (written whole: a stopped run leaves no cut PNG)
                written.append(path)
        if len(written) < 3:
            raise NeulfError(f"{video} gave {len(written)} frame(s); a capture needs at least 3 (20 or more work best): "
                             "film a longer, slower pass over the scene.")
    except BaseException:  # (Ctrl-C, SIGTERM, a broken stream: no half set of photos to reconstruct)
        for path in written:
            path.unlink(missing_ok=True)
        if created and out_dir.is_dir() and not any(out_dir.iterdir()):
            out_dir.rmdir()
        raise
    return written


@contextlib.contextmanager
def _decoding_errors_said(video: Path):
    """A clip damaged part-way (a copy cut short) fails inside FFmpeg: one line, not its traceback."""
    import av

    try:
        yield
    except av.error.FFmpegError as exc:
        raise NeulfError(f"{video} could not be read to its end ({exc}): copy the video again, or trim it to the "
                         "part that plays.") from None


def _refuse_inputs(video: Path, out_dir: Path, count: int) -> None:
    if not video.is_file():
        raise NeulfError(f"{video} does not exist or is not a file; give the video of the capture.")
    if not isinstance(count, int) or isinstance(count, bool) or count < 3:
        raise NeulfError(f"--count must be a whole number of at least 3 (a capture needs 3 photos), not {count!r}.")
    if out_dir.exists() and (not out_dir.is_dir() or any(p.suffix.lower() in IMAGE_EXTENSIONS for p in out_dir.iterdir())):
        raise NeulfError(f"--out {out_dir} is a file or already holds photos: give a new or empty folder (frames "
                         "written among other photos would be reconstructed with them).")


def _frame_estimate(stream, container) -> int:
    """The stream's frame count, or (containers that do not store it) duration x frame rate."""
    if stream.frames:
        return int(stream.frames)
    seconds = float(stream.duration * stream.time_base) if stream.duration else (container.duration or 0) / 1e6
    rate = float(stream.average_rate or stream.guessed_rate or 30)
    return max(1, int(math.ceil(seconds * rate)))


def _sharpest_per_window(frames, total: int, count: int, progress):
    """The sharpest frame (upright RGB) of each of `count` windows over the decoded `frames`,
    `total` of them expected (frames past the estimate fall into the last), yielded as each
    window ends: one frame is held at a time, not a clip's worth (60 frames of 4K: 1.5 GB)."""
    windows = min(count, total)
    window, best = 0, None
    for index, frame in enumerate(frames):
        at = min(windows - 1, index * windows // total)
        if at != window and best is not None:
            yield best[1]
            best = None
        window = at
        score = sharpness(_judged(frame))
        if best is None or score > best[0]:  # (only a frame that wins is turned into RGB)
            best = (score, upright(frame.to_ndarray(format="rgb24"), getattr(frame, "rotation", 0) or 0))
        if progress is not None:
            progress(index + 1, total)
    if best is not None:
        yield best[1]

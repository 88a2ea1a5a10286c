"""What Render Video sets for its render and puts back after: the H.264 output, the sizes it
takes, the file a path names, and the handlers that restore the artist's settings when an
interactive render (which runs on after the operator) ends."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import bpy

from .model_folder import abspath
from ..neulf_core.errors import NeulfError


def configure_video(scene, filepath: str) -> None:
    settings = scene.render.image_settings
    if hasattr(settings, "media_type"):  # 5.0+
        settings.media_type = "VIDEO"
    settings.file_format = "FFMPEG"
    scene.render.ffmpeg.format = "MPEG4"
    scene.render.ffmpeg.codec = "H264"
    scene.render.filepath = filepath


# What Render Video changes for its render and puts back after: the artist's engine and output
# (a next Ctrl+F12 would otherwise write an MP4 where an image sequence was set up).
VIDEO_RENDER_SETTINGS = (("render", ("engine", "filepath")),
                         ("render.image_settings", ("media_type", "file_format", "color_mode", "color_depth",
                                                    "quality", "compression", "exr_codec")),
                         ("render.ffmpeg", ("format", "codec")))


def _settings_owner(scene, path: str):
    owner = scene
    for part in path.split("."):
        owner = getattr(owner, part)
    return owner


def saved_render_settings(scene) -> list:
    return [(path, name, getattr(_settings_owner(scene, path), name)) for path, names in VIDEO_RENDER_SETTINGS
            for name in names if hasattr(_settings_owner(scene, path), name)]


def restore_render_settings(scene, saved: list) -> None:
    for path, name, value in saved:
        try:
            setattr(_settings_owner(scene, path), name, value)
        except (TypeError, ValueError, AttributeError):  # (a value the restored format does not offer)
            pass


def restore_after_render(scene, saved: list, video: Path | None = None):
    """Put the settings back once an interactive render (which runs on after the operator) ends.
    A render that ends early (cancelled, or a frame failed) removes its `video`, which stops
    where the render did and would otherwise pass for the whole camera path -- as the blocking
    path does.  Returns `forget()`: for a render that did not start (Blender was rendering
    already), the handlers are removed and the settings put back at once (left registered, a
    later render's cancel would have removed this video)."""
    def remove_handlers():
        for handlers in (bpy.app.handlers.render_complete, bpy.app.handlers.render_cancel):
            for handler in (restore, cut_short):
                if handler in handlers:
                    handlers.remove(handler)

    def restore(*_args):
        remove_handlers()
        target = bpy.data.scenes.get(scene_name)
        if target is not None:
            restore_render_settings(target, saved)

    def cut_short(*_args):
        restore()
        if video is not None and video.is_file():
            video.unlink()
            target = bpy.data.scenes.get(scene_name)
            if target is not None:
                target.neulf.last_status = (f"Render Video stopped before the last frame; the partial video was removed "
                                            f"({video.name})")

    scene_name = scene.name
    bpy.app.handlers.render_complete.append(restore)
    bpy.app.handlers.render_cancel.append(cut_short)
    return restore


def refuse_odd_video_size(render) -> None:
    """H.264 takes even widths and heights only, and Blender's writer does not pad (the CLI's
    video does): said before the render, not as FFmpeg's error after the first frame."""
    width = render.resolution_x * render.resolution_percentage // 100
    height = render.resolution_y * render.resolution_percentage // 100
    if width % 2 or height % 2:
        raise NeulfError(f"an H.264 video needs an even width and height, and this render is {width}x{height} "
                         f"(Output > Resolution {render.resolution_x}x{render.resolution_y} at "
                         f"{render.resolution_percentage} %): set an even size, e.g. {width + width % 2}x"
                         f"{height + height % 2} at 100 %.")


def video_path(filepath: str) -> str:
    """The video file a path names: a folder (an existing one, or a path ending in a slash) gets
    neulf.mp4 inside it; a name without .mp4 gets it."""
    given = filepath or "//neulf.mp4"
    path = abspath(given)
    if not os.path.isabs(path):  # ('//' in a file never saved: no folder to be relative to)
        raise NeulfError(f"'{given}' is relative to the .blend, which is not saved yet: save it first, or choose the "
                         "video's folder.")
    if given.endswith(("/", "\\")) or os.path.isdir(path):
        path = os.path.join(path, "neulf.mp4")
    if not path.lower().endswith(".mp4"):
        path += ".mp4"
    return path


def refuse_unwritable_video(path: str) -> None:
    """Said before the render starts: a folder that cannot be made or written (a file in the way,
    a read-only place) had ended in a traceback, or in Blender's "Could not open file for
    writing", which names no file, after the first frame's render."""
    folder = Path(path).parent
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as exc:
        raise NeulfError(f"cannot write the video {path} ({exc.strerror or exc}): choose another file or folder for "
                         "Render Video.") from None

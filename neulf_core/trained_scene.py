"""What a trained model recorded of the scene it trained on, against the scene read now.

A model's model.json keeps its photos' folder and sizes and its cameras beyond their centres
(the scene's fingerprint holds the names and centres).  Eval, render and resume read the same
photos where no other folder is asked for; photos of another size are rendered and scored at the
size the model trained at; a camera edited in the model since (a focal length, a turn) is said,
and refused on resume.  (A model trained on LLFF's images_16/ had been scored and resumed on
images_8/, four times its pixels, without a word.)
"""

from __future__ import annotations

import functools
import hashlib
from pathlib import Path

import numpy as np

from .scene import View


def images_dir_as_trained(scene_dir: str | Path, images_dir: str | Path | None, saved_scene: dict | None):
    """The photos to read a trained model's scene with: the folder asked for; else the one its
    training read (model.json's scene.images), where that is there; else the scene's default.
    (Without this, a model trained on LLFF's images_16/ was scored and resumed on images_8/,
    four times its pixels, without a word.)"""
    if images_dir is not None:
        return images_dir
    recorded = (saved_scene or {}).get("images")
    if recorded:
        path = Path(recorded) if Path(recorded).is_absolute() else Path(scene_dir).expanduser() / recorded
        if path.is_dir():
            return path
    return None


def trained_photo_size(view: View, saved_scene: dict | None) -> tuple[int, int] | None:
    """The size of `view`'s photo when the model trained, where the model recorded it and the
    photo read now has another size (another images folder); else None."""
    trained = ((saved_scene or {}).get("photo_sizes") or {}).get(view.name)
    if not trained or tuple(trained) == view.size:
        return None
    return int(trained[0]), int(trained[1])


def scale_as_trained(view: View, saved_scene: dict | None, scale: float) -> float:
    """The scale that gives `view`'s photo read now the pixel size the model trained it at (its
    recorded photo size times `scale`): the same pictures whichever images folder is read."""
    trained = trained_photo_size(view, saved_scene)
    return scale if trained is None else scale * trained[0] / view.size[0]


def other_photos_note(views: list[View], saved_scene: dict | None) -> str | None:
    """One line for photos of another size than the model trained on, or None."""
    differ = [(v, trained_photo_size(v, saved_scene)) for v in views]
    differ = [(v, size) for v, size in differ if size is not None]
    if not differ:
        return None
    view, size = differ[0]
    return (f"{len(differ)} of the photos read are of another size than the model trained on ({view.name}: "
            f"{view.size[0]}x{view.size[1]}, trained on {size[0]}x{size[1]}; the model read "
            f"{(saved_scene or {}).get('images') or 'another folder'}): rendered (and scored) at the size it trained at; "
            "give --images with the folder it trained on for its own photos.")


def camera_record(view: View) -> list:
    """What a model records of a view's camera beyond its centre (which the fingerprint holds):
    the model, K and distortion relative to the image size (the same for any images_N folder),
    and the rotation."""
    camera, (width, height) = view.camera, view.size
    params = np.asarray(camera.params, dtype=np.float64)
    fx, fy = (params[i] for i in camera.focal_length_idxs()) if len(camera.focal_length_idxs()) == 2 else \
        (params[camera.focal_length_idxs()[0]],) * 2
    cx, cy = (params[i] for i in camera.principal_point_idxs())
    extra = [float(params[i]) for i in camera.extra_params_idxs()]
    return [camera.model.name, fx / width, fy / height, cx / width, cy / height, *extra,
            *np.asarray(view.R, dtype=np.float64).ravel().tolist()]


def changed_cameras(views: list[View], saved_scene: dict | None) -> list[str]:
    """Names of `views` whose camera (camera_record) differs from the one the model trained with:
    a focal length or a turn edited in the model with the centres kept, which the fingerprint
    does not see.  K's entries are compared to 0.5 % (a one-focal camera scaled to a file of a
    slightly other aspect ratio moves them by about 0.1 %), distortion and rotation to 1e-4.
    Models that recorded none: nothing to compare."""
    recorded = (saved_scene or {}).get("cameras") or {}
    changed = []
    for view in views:
        before, now = recorded.get(view.name), camera_record(view)
        if before is None:
            continue
        if before[0] != now[0] or len(before) != len(now):
            changed.append(view.name)
            continue
        before, now = np.asarray(before[1:], float), np.asarray(now[1:], float)
        if (np.abs(now[:4] - before[:4]) / np.maximum(np.abs(before[:4]), 1e-3)).max() > 5e-3 or np.abs(now[4:] - before[4:]).max(initial=0) > 1e-4:
            changed.append(view.name)
    return changed


def changed_cameras_note(views: list[View], saved_scene: dict | None) -> str | None:
    changed = changed_cameras(views, saved_scene)
    if not changed:
        return None
    shown = ", ".join(changed[:3]) + (" ..." if len(changed) > 3 else "")
    return (f"{len(changed)} view(s) ({shown}) have another camera (focal length, principal point, distortion or "
            "rotation) than when the model trained: they are rendered as the scene says now, through a light field "
            "learnt with the old cameras; train a new model for the new ones.")


def other_reconstruction(saved_scene: dict, scene, what_to_do: str) -> str:
    """The message for a scene whose fingerprint (names and centres) is not the model's.  Where
    the model recorded this very folder, the reconstruction in it changed (COLMAP run again in
    place): saying "another reconstruction (this folder)" had told the user to give the folder
    they had given."""
    root = saved_scene.get("root")
    if root and Path(root).expanduser().resolve() == Path(scene.root).expanduser().resolve():
        return (f"the camera poses in {scene.root} changed since the model trained (COLMAP run again there, or the "
                f"model edited): {what_to_do} with the reconstruction it trained on (a copy of it), or train a new "
                "model for this one.")
    return (f"the model was trained on another reconstruction ({root}, {len(saved_scene.get('views', []))} views): "
            f"{what_to_do} with that scene, or train a new model for this one.")


def photo_digest(path: Path) -> str:
    """A short digest of a photo file's bytes: what model.json keeps to notice photos replaced
    by others of the same name and size (a capture's folder refilled, photos mirrored or
    edited), which the scene's fingerprint (names, centres) and the sizes do not see.  The
    bytes, not the pixels: hashing a file is a hundred times cheaper than decoding it.  Kept
    per file state: each member and second start of a training reads the same photos."""
    status = Path(path).stat()
    return _file_digest(str(Path(path).resolve()), status.st_size, status.st_mtime_ns)


@functools.lru_cache(maxsize=4096)
def _file_digest(path: str, _size: int, _mtime_ns: int) -> str:
    """photo_digest of `path` as it is at that size and modification time (the cache's key)."""
    digest = hashlib.sha1()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()[:16]


def photo_digests(views: list[View]) -> dict[str, str]:
    return {view.name: photo_digest(view.image_path) for view in views if view.image_path is not None}


def changed_photos(views: list[View], saved_scene: dict | None) -> list[str]:
    """Names of `views` whose photo is not the file the model trained on (other bytes), where
    the model recorded its digest and the photo read is of the trained size (another size is
    another images folder: other_photos_note says that)."""
    recorded = (saved_scene or {}).get("photo_digests") or {}
    return [view.name for view in views
            if view.image_path is not None and view.name in recorded and trained_photo_size(view, saved_scene) is None
            and photo_digest(view.image_path) != recorded[view.name]]


def changed_photos_note(views: list[View], saved_scene: dict | None, consequence: str) -> str | None:
    changed = changed_photos(views, saved_scene)
    if not changed:
        return None
    shown = ", ".join(changed[:3]) + (" ..." if len(changed) > 3 else "")
    return (f"{len(changed)} photo(s) ({shown}) are not the files the model trained on (their bytes differ: replaced, "
            f"edited or saved again): {consequence}")

"""Services for the Blender extension, callable in-process or from a worker process.

Blender's own Python has no torch or pycolmap, so the extension runs this module in another
interpreter: ``python -m neulf_core.worker --scratch DIR`` reads one JSON request per line on
stdin and answers one JSON line per request on stdout::

    -> {"id": 3, "op": "render", "args": {"model_dir": "...", "K": [[...]], ...}}
    <- {"id": 3, "progress": 0.5}                           (zero or more)
    <- {"id": 3, "ok": true, "result": {...}}               or
    <- {"id": 3, "ok": false, "error": "one line for the user", "kind": "NeulfError"}

Arrays in a result travel as ``.npy`` files in the scratch folder: ``{"__npy__": PATH}`` (the
extension decodes them: neulf_blender/jobs.py `decode`).
When torch imports inside Blender (or in tests) the extension calls :class:`Service`
directly and gets the arrays themselves: both routes run the same code.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import traceback
import uuid
from pathlib import Path

import numpy as np

from .errors import NeulfError, as_user_error
from .model_files import CHECKPOINT_NAME, METADATA_NAME, MODEL_NAME, has_render_model

PROTOCOL_VERSION = 1


class Service:
    """What the Blender side asks of neulf_core; plain values and numpy arrays in and out."""

    def __init__(self, device: str | None = None):
        self.device = device
        self._cached: tuple[tuple, object] | None = None  # ((path, mtime, device), LightField)

    # ------------------------------------------------------------------ environment
    def info(self) -> dict:
        # Everything training and rendering import (Check had passed a Python without Pillow,
        # and training then failed): a missing one fails here, named (jobs.explain_failure).
        import av  # noqa: F401  (the video)
        import PIL  # noqa: F401
        import pycolmap
        import torch

        from . import __version__
        from .device import describe_device, pick_device

        device = pick_device(self.device)
        return {"protocol": PROTOCOL_VERSION, "neulf_core": __version__, "python": sys.executable,
                "python_version": sys.version.split()[0], "torch": torch.__version__,
                "pycolmap": getattr(pycolmap, "__version__", "?"), "device": device.type,
                "device_name": describe_device(device)}

    # ------------------------------------------------------------------ scenes
    def describe_scene(self, scene_dir: str, images_dir: str | None = None, model_dir: str | None = None,
                       holdout_every: int = 8) -> dict:
        """Cameras (pinhole K, world-to-camera R, t), sparse points and the light slab of a scene.

        The slab is the trained model's when `model_dir` holds one, else fitted like training
        would (every `holdout_every`-th view held out)."""
        from .checkpoint import saved_scene_record
        from .rays import pinhole_K
        from .scene import load_scene, split_views
        from .slab import fit_slab
        from .trained_scene import images_dir_as_trained

        # (the photos the model trained on, where the scene has several folders or they lie elsewhere)
        asked = images_dir
        images_dir = images_dir_as_trained(scene_dir, images_dir, saved_scene_record(model_dir) if model_dir else None)
        scene = load_scene(scene_dir, images_dir)
        views = []
        for view in scene.views:
            width, height = view.size
            views.append({"name": view.name, "width": width, "height": height, "K": pinhole_K(view.camera).tolist(),
                          "R": view.R.tolist(), "t": view.t.tolist(), "model": view.camera.model.name,
                          "image_path": str(view.image_path) if view.image_path else None})
        notes = list(scene.notes)
        distorted = sorted({v["model"] for v in views} - {"PINHOLE", "SIMPLE_PINHOLE"})
        if distorted:
            notes.append(f"camera model {', '.join(distorted)}: Blender cameras are the undistorted pinhole part")
        slab, slab_source = None, "fitted"
        if model_dir and _has_model(model_dir):
            info = self.model_info(model_dir)
            if info["fingerprint"] not in (None, scene.fingerprint()):
                notes.append(f"the model in {model_dir} was trained on another reconstruction; its slab is not shown")
            else:
                slab, slab_source = info["slab"], "model"
        if slab is None:
            train_views, _ = split_views(scene, holdout_every)
            slab = fit_slab(scene, train_views).to_dict()
        return {"root": str(scene.root),
                "images_dir_from_model": str(images_dir) if asked is None and images_dir is not None else None,
                "kind": scene.kind, "fingerprint": scene.fingerprint(), "views": views,
                "points": np.asarray(scene.points, dtype=np.float32), "slab": slab, "slab_source": slab_source,
                "notes": notes}

    # ------------------------------------------------------------------ models
    def restore_metadata(self, model_dir: str) -> list[str]:
        """model.json written again from the checkpoint, in the model folder and each member's,
        where it is missing or damaged; the folders it was written in."""
        from .checkpoint import restore_metadata
        from .members import member_folders, read_state

        path = Path(model_dir).expanduser()
        state = read_state(path)  # (a damaged members.json: its own one-line error)
        return [str(folder) for folder in member_folders(path, state) if restore_metadata(folder)]

    def model_info(self, model_dir: str) -> dict:
        """The model's metadata (slab, scene, rig, training progress) without loading weights."""
        path = Path(model_dir).expanduser()
        meta_path = path / METADATA_NAME
        if not meta_path.is_file():
            self.light_field(model_dir)  # raises the checkpoint's own clear error
            raise NeulfError(f"{path} has a checkpoint but no model.json; train or resume it once more to rewrite it.")
        try:
            meta = json.loads(meta_path.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise NeulfError(f"cannot read {meta_path} ({exc}); train or resume the model once more.") from None
        scene = meta.get("scene", {})
        return {"model_dir": str(path), "slab": meta.get("slab"), "rig": meta.get("rig"),
                "fingerprint": scene.get("fingerprint"), "scene_root": scene.get("root"),
                "views": scene.get("views", []), "progress": meta.get("progress", {}),
                "train_config": meta.get("train_config", {})}

    def light_field(self, model_dir: str):
        from .checkpoint import checkpoint_path
        from .render import LightField

        path = checkpoint_path(Path(model_dir))
        key = (str(path.resolve()), model_stamp(model_dir), self.device)
        if self._cached is None or self._cached[0] != key:
            self._cached = None  # free the previous model first
            self._cached = (key, LightField.load(model_dir, self.device))
        return self._cached[1]

    def render(self, model_dir: str, K, width: int, height: int, R, t, depth: bool = True, chunk: int | None = None,
               on_progress=None, focus_distance: float | None = None, aperture: float = 0.0,
               pixel_samples: int | None = None, max_lens_samples: int | None = None) -> dict:
        """RGB (H, W, 3) float32 in [0, 1], row 0 at the top; depth along the optical axis.
        `aperture` > 0 (lens radius, model units) refocuses at `focus_distance` with at most
        `max_lens_samples` lens samples (None: refocus.MAX_SAMPLES); each pixel the mean over
        `pixel_samples` points of it (render.PIXEL_SAMPLES; None: the model's default for the
        camera, LightField.default_pixel_samples); `chunk` rays
        per call of the field (None or 0: the device's own, LightField.default_chunk)."""
        field = self.light_field(model_dir)
        report = None if on_progress is None else (lambda done, total: on_progress(done / total))
        lens = {"max_samples": int(max_lens_samples)} if max_lens_samples else {}
        rendering = field.render(np.asarray(K), int(width), int(height), np.asarray(R), np.asarray(t), depth=depth,
                                 chunk=int(chunk) if chunk else None, on_chunk=report, focus_distance=focus_distance, aperture=aperture,
                                 pixel_samples=None if pixel_samples is None else int(pixel_samples), **lens)
        return {"rgb": rendering.rgb, "depth": rendering.depth, "valid": rendering.valid,
                "warnings": list(rendering.warnings)}

    def depth_at(self, model_dir: str, K, R, t, x: float, y: float) -> dict:
        """Depth along the optical axis of the ray through image point (x, y) (pixel units,
        top-left origin; pixel (i, j) has its centre at (i + 0.5, j + 0.5)): a 1-ray render."""
        # (imported here: Blender's Python imports this module and has no pycolmap or torch)
        from .rays import single_pixel_K
        from .render import picked_depth

        field = self.light_field(model_dir)
        rendering = field.render(single_pixel_K(K, x, y), 1, 1, np.asarray(R), np.asarray(t), depth=True)
        value = picked_depth(float(rendering.depth[0, 0]), x, y, what_to_do="; click on the captured scene itself, "
                                                                             "from a camera in front of it")
        return {"depth": value, "rgb": rendering.rgb[0, 0].tolist(), "warnings": list(rendering.warnings)}

    def spiral(self, model_dir: str, frames: int = 60, camera: dict | None = None) -> dict:
        """A camera path through the capture: world-to-camera poses plus the rig's pinhole, and
        warnings (a rig from one place makes a still path; with `camera`, the pinhole that will
        fly it -- K, width, height and its lens in mm -- frames that see past the capture, and the
        lens that keeps them inside)."""
        from .paths import NO_RIG, STILL_SPIRAL, past_capture_warning, rig_has_baseline, saved_rig, spiral_path
        from .slab import Slab

        info = self.model_info(model_dir)
        if not info.get("slab"):
            raise NeulfError(f"{NO_RIG}.")
        centres, K, width, height = saved_rig(info)
        slab = Slab.from_dict(info["slab"])
        poses = spiral_path(slab, centres, frames=int(frames))
        if not rig_has_baseline(slab, centres):
            warnings = [STILL_SPIRAL]
        elif camera is not None:
            warnings = [past_capture_warning(slab, camera["K"], int(camera["width"]), int(camera["height"]), poses,
                                             lens_mm=camera.get("lens_mm"))]
        else:
            warnings = []
        return {"R": [p[0].tolist() for p in poses], "t": [p[1].tolist() for p in poses], "K": K.tolist(),
                "width": width, "height": height, "warnings": [note for note in warnings if note]}


def model_stamp(model_dir) -> tuple:
    """The modification times of every file a render of the model reads: the first member's
    checkpoint.pt and model.pt, members.json, and each member's files, so a member trained on
    (its checkpoint replaced) loads again (keyed on the first's checkpoint alone, a second
    member trained on had rendered stale until Blender restarted)."""
    folder = Path(model_dir).expanduser()
    if folder.is_file():
        return (folder.stat().st_mtime_ns,)
    names = [folder / CHECKPOINT_NAME, folder / MODEL_NAME, folder / "members.json"]
    names += sorted(folder.glob(f"members/*/{CHECKPOINT_NAME}")) + sorted(folder.glob(f"members/*/{MODEL_NAME}"))
    stamps = []
    for name in names:
        try:
            stamps.append((str(name), name.stat().st_mtime_ns))
        except OSError:
            stamps.append((str(name), None))
    return tuple(stamps)


def _has_model(model_dir: str) -> bool:
    path = Path(model_dir).expanduser()
    return (path / METADATA_NAME).is_file() or has_render_model(path)


# ----------------------------------------------------------------------------- JSON lines


def _encode(value, scratch: Path):
    if isinstance(value, np.ndarray):
        path = scratch / f"{uuid.uuid4().hex}.npy"
        np.save(path, value)
        return {"__npy__": str(path)}
    if isinstance(value, dict):
        return {k: _encode(v, scratch) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_encode(v, scratch) for v in value]
    return value


OPS = {"info", "describe_scene", "model_info", "restore_metadata", "render", "depth_at", "spiral"}


def serve(stdin, stdout, scratch: Path, device: str | None = None) -> None:
    service = Service(device)

    def send(message: dict) -> None:
        stdout.write(json.dumps(message) + "\n")
        stdout.flush()

    for line in stdin:
        if not line.strip():
            continue
        request_id = None
        try:
            request = json.loads(line)
            request_id = request.get("id")
            op, args = request.get("op"), dict(request.get("args") or {})
            if op == "quit":
                send({"id": request_id, "ok": True, "result": None})
                return
            if op not in OPS:
                raise NeulfError(f"the worker has no operation '{op}' (update the extension and neulf_core together).")
            if op == "render":
                args["on_progress"] = lambda f: send({"id": request_id, "progress": f})
            result = getattr(service, op)(**args)
            send({"id": request_id, "ok": True, "result": _encode(result, scratch)})
        except NeulfError as exc:
            send({"id": request_id, "ok": False, "error": str(exc), "kind": "NeulfError"})
        except Exception as exc:  # noqa: BLE001
            user_error = as_user_error(exc)  # (out of memory, a missing package: what to do, in words)
            if user_error is not None:
                send({"id": request_id, "ok": False, "error": str(user_error), "kind": "NeulfError"})
                continue
            traceback.print_exc(file=sys.stderr)  # programming errors: one line back, the traceback on stderr
            send({"id": request_id, "ok": False, "error": f"{type(exc).__name__}: {exc}", "kind": type(exc).__name__})


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m neulf_core.worker", description=__doc__.splitlines()[0])
    parser.add_argument("--scratch", required=True, help="folder for .npy results (the client removes them)")
    parser.add_argument("--device", help="cpu, cuda, mps (default: the fastest available)")
    args = parser.parse_args(argv)
    scratch = Path(args.scratch)
    scratch.mkdir(parents=True, exist_ok=True)
    # Keep stdout for the protocol: anything a library prints goes to stderr.
    protocol_out = os.fdopen(os.dup(1), "w", buffering=1)
    os.dup2(2, 1)  # C libraries writing to fd 1 land on stderr too
    sys.stdout = sys.stderr
    serve(sys.stdin, protocol_out, scratch, args.device)
    return 0


if __name__ == "__main__":
    sys.exit(main())

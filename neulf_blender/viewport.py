"""The 3D viewport's Rendered shading: the light field seen from the viewport's own camera,
so a user can fly through the capture.  No bpy here: the engine (engine.py) passes the
view's matrices in and draws what comes out.

Nothing renders while Blender draws.  The engine's `view_draw` tells a PreviewRenderer which
view it shows and draws the newest finished image; the renderer's thread renders that view
coarse first (at most PREVIEW_PIXELS pixels), then, while the view stays, at four times those
pixels and at the region's full size.  While the user orbits, each coarse pass runs to its end
and is shown, and the next one takes the newest view.  A view already rendered renders nothing
again, so redraws (overlays, a moving mouse) cost no network pass.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass

import numpy as np

from . import convert
from ..neulf_core.errors import NeulfError

PREVIEW_PIXELS = 40_000  # the coarse pass of a new view (about 267 x 150)
# A camera's depth of field in the preview: at most this many lens samples in the passes below full
# size and in the full-size one (F12: up to refocus.MAX_SAMPLES, 96).  Each sample is a pass of the network:
# at 14 samples a coarse pass took 0.8 s instead of 43 ms (docs/BENCHMARKS.md, "The viewport preview").
COARSE_LENS_SAMPLES = 4
FULL_LENS_SAMPLES = 16
WORKER_BAND_PIXELS = 40_000  # a worker renders a full-size view in bands of this many pixels (about 50 ms each)
IDLE_SECONDS = 10.0      # a renderer's thread ends after this long with nothing to render


def view_request(view_matrix, window_matrix, width: int, height: int, root_matrix) -> dict:
    """The pinhole a 3D viewport shows, in the model's COLMAP frame (as capture.camera_request
    gives it for a camera): K, width, height, R, t and the root's uniform `scale`.

    `view_matrix` is world-to-view and `window_matrix` the projection (RegionView3D's), both
    with Blender's camera axes; `root_matrix` the capture root's world matrix."""
    P = np.asarray(window_matrix, dtype=np.float64).reshape(4, 4)
    if abs(P[3, 3]) > 1e-9:  # (a perspective projection has 0 there, an orthographic one 1)
        raise NeulfError("an orthographic view cannot look through a light field: switch the viewport to "
                         "perspective (Numpad 5) or look through a camera (Numpad 0).")
    if width < 1 or height < 1:
        raise NeulfError("the viewport has no size to render.")
    # The projection's entries as BLENDER_NOTES gives them for calc_matrix_camera.
    fx, fy = P[0, 0] * width / 2.0, P[1, 1] * height / 2.0
    cx, cy = width / 2.0 * (1.0 - P[0, 2]), height / 2.0 * (1.0 + P[1, 2])
    root = np.asarray(root_matrix, dtype=np.float64).reshape(4, 4)
    convert.refuse_uneven_scale(root)
    camera_to_world = np.linalg.inv(np.asarray(view_matrix, dtype=np.float64).reshape(4, 4))
    try:
        R, t = convert.pose_from_matrix(np.linalg.inv(root) @ camera_to_world)
    except ValueError as exc:
        raise NeulfError(str(exc)) from None
    return {"K": [[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], "width": int(width), "height": int(height),
            "R": R.tolist(), "t": t.tolist(), "scale": convert.uniform_scale(root)}


def scaled_request(request: dict, factor: float) -> dict:
    """The same view at `factor` times the pixels along each side: K scales with the image,
    since pixel coordinates start at the top-left corner (centres at +0.5)."""
    if factor >= 1.0:
        return dict(request)
    width = max(1, round(request["width"] * factor))
    height = max(1, round(request["height"] * factor))
    sx, sy = width / request["width"], height / request["height"]
    K = np.asarray(request["K"], dtype=np.float64)
    K = np.diag([sx, sy, 1.0]) @ K
    return {**request, "K": K.tolist(), "width": width, "height": height}


def coarse_factor(width: int, height: int, pixels: int = PREVIEW_PIXELS) -> float:
    """The scale of the coarse pass: at most `pixels` pixels, never above full size."""
    return min(1.0, math.sqrt(pixels / max(1, width * height)))


def view_key(request: dict, model: str, model_stamp: float) -> tuple:
    """What decides a preview image: the view (to a hundred-thousandth, so float noise in
    Blender's matrices does not re-render), the camera's depth of field where the view looks
    through it, and the model, with its file's time (a model being trained refreshes the
    preview at each checkpoint)."""
    numbers = tuple(round(float(x), 5) for x in np.ravel([request["K"], request["R"]]))
    position = tuple(round(float(x), 5) for x in request["t"])
    lens = tuple(round(float(request[k]), 6) for k in ("focus_distance", "aperture") if request.get(k) is not None)
    return (model, model_stamp, request["width"], request["height"], numbers, position, lens)


@dataclass(frozen=True)
class PreviewImage:
    key: tuple
    full_size: bool
    rgb: np.ndarray   # (H, W, 3) sRGB in [0, 1], row 0 at the top
    seconds: float


class PreviewRenderer:
    """Renders the newest view asked for, in a thread of its own: coarse, then full size.

    `render(request, should_stop)` returns the image of a request (render_function: neulf_core's
    render through the extension's core; a pass's request carries its `max_lens_samples`, fewer
    for the coarse pass); it may raise InterruptedError when `should_stop()`,
    which turns true once another view is wanted.  `on_image()` is called from the thread after
    each finished image (the engine asks Blender for a redraw)."""

    def __init__(self, render, on_image=None, preview_pixels: int = PREVIEW_PIXELS):
        self._render = render
        self._on_image = on_image
        self.preview_pixels = preview_pixels
        self._lock = threading.Condition()
        self._wanted: tuple | None = None   # (key, request)
        self._done_key = None               # the last key rendered to the end (or failed)
        self._image: PreviewImage | None = None
        self._thread: threading.Thread | None = None
        self._closed = False
        self.error: str | None = None       # why the wanted view could not be rendered
        self.renders = 0                    # images rendered (coarse and full passes)

    def want(self, key, request: dict) -> None:
        """Show this view: renders it unless it is the one being rendered or already shown."""
        with self._lock:
            if self._wanted is not None and self._wanted[0] == key:
                return
            self._wanted, self.error = (key, request), None
            if self._thread is None or not self._thread.is_alive():
                self._thread = threading.Thread(target=self._run, name="neulf-viewport", daemon=True)
                self._thread.start()
            self._lock.notify_all()

    def image(self) -> PreviewImage | None:
        """The newest finished image (of this view, or while it renders, of an earlier one)."""
        return self._image

    @property
    def busy(self) -> bool:
        with self._lock:
            return self._wanted is not None and self._wanted[0] != self._done_key and self.error is None

    def wait(self, timeout: float = 60.0) -> bool:
        """Until the wanted view is rendered at full size (or failed); False on timeout."""
        deadline = time.monotonic() + timeout
        while self.busy:
            if time.monotonic() > deadline:
                return False
            time.sleep(0.01)
        return True

    def close(self) -> None:
        with self._lock:
            self._closed = True
            self._lock.notify_all()

    # ------------------------------------------------------------------ the thread

    def _next(self):
        """The view to render next, or None when closed or idle for IDLE_SECONDS."""
        with self._lock:
            idle_since = time.monotonic()
            while not self._closed and (self._wanted is None or self._wanted[0] == self._done_key):
                left = IDLE_SECONDS - (time.monotonic() - idle_since)
                if left <= 0:
                    self._thread = None  # (want() starts another)
                    return None
                self._lock.wait(left)
            return None if self._closed else self._wanted

    def _moved_on(self, key) -> bool:
        return self._closed or self._wanted is None or self._wanted[0] != key

    def _run(self) -> None:
        while True:
            wanted = self._next()
            if wanted is None:
                return
            key, request = wanted
            for index, factor in enumerate(self.passes(request["width"], request["height"])):
                first = index == 0
                if not first and self._moved_on(key):
                    break
                if not self._render_pass(key, request, factor, first):
                    break

    def passes(self, width: int, height: int) -> list[float]:
        """The scales a view renders at, coarse to full: at most preview_pixels, then four times
        as many (where that is still below full size), then full size."""
        scales = [coarse_factor(width, height, self.preview_pixels), coarse_factor(width, height, 4 * self.preview_pixels)]
        return sorted({scale for scale in scales if scale < 1.0}) + [1.0]

    def _render_pass(self, key, request: dict, factor: float, first: bool) -> bool:
        """One image of the view; whether to go on to its next pass.  A view's first pass runs
        to its end even where the view has moved on meanwhile, and is shown: while the user
        orbits, the view changes faster than any pass ends, and an image of a view a moment
        old is better than none.  A later pass stops as soon as another view is wanted."""
        started = time.monotonic()
        stop = (lambda: self._closed) if first else (lambda: self._moved_on(key))
        lens_samples = COARSE_LENS_SAMPLES if factor < 1.0 else FULL_LENS_SAMPLES
        try:
            rgb = self._render({**scaled_request(request, factor), "max_lens_samples": lens_samples}, stop)
        except InterruptedError:
            return False
        except Exception as exc:  # a broken model, a worker that stopped: said in the viewport
            with self._lock:
                if not self._moved_on(key):
                    self.error = str(exc) if isinstance(exc, NeulfError) else f"{type(exc).__name__}: {exc}"
                    self._done_key = key
            return False
        with self._lock:
            if self._closed:
                return False
            self._image = PreviewImage(key, factor >= 1.0, np.asarray(rgb), time.monotonic() - started)
            self.renders += 1
            if factor >= 1.0:
                self._done_key = key
            going_on = not self._moved_on(key)
        if self._on_image is not None:
            self._on_image()
        return going_on


def row_bands(request: dict, pixels: int):
    """The request cut into bands of whole rows of at most `pixels` pixels: (first row, request).
    Each band's K is the full image's with the principal point moved up by the band's first row,
    so its pixels are the same rays as the full image's."""
    rows = max(1, pixels // request["width"])
    for top in range(0, request["height"], rows):
        K = np.array(request["K"], dtype=np.float64)
        K[1, 2] -= top
        yield top, {**request, "K": K.tolist(), "height": min(rows, request["height"] - top)}


def render_function(core):
    """A PreviewRenderer's `render(request, should_stop)` through the extension's core
    (core.Core): neulf_core's render of one view, one point a pixel, no depth (a depth of field
    with the request's `max_lens_samples`, which PreviewRenderer sets per pass).  In Blender's own
    Python a newer view interrupts it between chunks.  A worker's render cannot be interrupted
    but by killing the worker (whose start costs seconds), so there the view renders in bands
    of WORKER_BAND_PIXELS, a call each, and stops between them: without that, a full-size pass
    begun in a pause of an orbit held the viewport for its whole 0.4-2.3 s (at 960x540 to
    1920x1080 on 2 cores; docs/BENCHMARKS.md, "The viewport preview")."""
    options = {"depth": False, "pixel_samples": 1}

    def render(request, should_stop):
        if core.in_process:
            return core.call("render", should_stop=should_stop, **options, **request)["rgb"]
        bands = []
        for _top, band in row_bands(request, WORKER_BAND_PIXELS):
            if bands and should_stop():
                raise InterruptedError("another view")
            bands.append(core.call("render", **options, **band)["rgb"])
        return np.concatenate(bands, axis=0)
    return render


def status_line(renderer: PreviewRenderer, key) -> str:
    """What the viewport's corner says about the preview."""
    if renderer.error:
        return f"NeuLF: {renderer.error}"
    shown = renderer.image()
    if shown is None or shown.key != key:
        return "NeuLF: rendering the view"
    height, width = shown.rgb.shape[:2]
    if not shown.full_size:
        return f"NeuLF: preview {width} x {height}, rendering full size"
    return f"NeuLF: {width} x {height} in {shown.seconds:.2f} s (one point a pixel; F12 renders the final image)"

"""Progress reporting for people (a bar on stderr) and for programs (JSON lines on stdout)."""

from __future__ import annotations

import json
import sys
import time


def emit(progress, **event) -> None:
    """Send one event to a `progress` callback, where there is one."""
    if progress is not None:
        progress(event)


class JsonLines:
    """One JSON object per event, flushed at once (the Blender worker reads these)."""

    def __init__(self, stream=None, every_seconds: float = 0.5):
        self.stream = stream or sys.stdout
        self.every = every_seconds
        self._last_step = 0.0

    def __call__(self, event: dict) -> None:
        if event.get("event") == "step":  # thin out per-step events
            now = time.monotonic()
            if now - self._last_step < self.every:
                return
            self._last_step = now
        self.stream.write(json.dumps(event, default=str) + "\n")
        self.stream.flush()


_open_bar = None  # the Bar whose line is unfinished, so an error message starts a new line


def end_line() -> None:
    """Finish a half-drawn progress line (before printing an error)."""
    global _open_bar
    if _open_bar is not None:
        _open_bar.stream.write("\n")
        _open_bar.stream.flush()
        _open_bar = None


class Bar:
    """A one-line progress bar redrawn in place on a terminal, plus plain lines for notable
    events; when stderr is not a terminal (logs, CI) the bar becomes a line every 10%."""

    def __init__(self, stream=None, width: int = 30):
        self.stream = stream or sys.stderr
        self.width = width
        self.val = None
        self._last = 0.0
        self._last_decile = -1
        self.interactive = bool(getattr(self.stream, "isatty", lambda: False)())

    def _bar(self, fraction: float, text: str) -> None:
        global _open_bar
        fraction = min(1.0, max(0.0, fraction))
        if not self.interactive:
            decile = int(fraction * 10)
            if decile != self._last_decile:
                self._last_decile = decile
                self.stream.write(f"{fraction:6.1%} {text}\n")
                self.stream.flush()
            return
        filled = int(round(self.width * fraction))
        self.stream.write(f"\r[{'#' * filled}{'.' * (self.width - filled)}] {fraction:6.1%} {text}\033[K")
        self.stream.flush()
        _open_bar = self

    def __call__(self, event: dict) -> None:
        kind = event.get("event")
        if kind == "start":
            self._line(f"training on {event['train_views']} views ({len(event['held_out'])} held out), "
                       f"preset {event['preset']}, {event['device']}")
            for note in event.get("notes", []):
                self._line(f"note: {note}")
        elif kind == "loading" and "done" in event:
            if self.interactive:
                self._bar(event["done"] / event["total"], f"loading {event['message']}")
        elif kind in ("step", "validate"):
            if kind == "validate" and event.get("val_psnr") is not None:
                self.val = event["val_psnr"]
            now = time.monotonic()
            if kind == "step" and now - self._last < 0.2:
                return
            self._last = now
            val = f" val {self.val:.2f} dB" if self.val is not None else ""
            self._bar(event.get("fraction", 0.0), f"step {event['step']} {event['elapsed']:.0f}s loss {event['loss']:.5f}{val}")
        elif kind == "warning":
            self._line(f"warning: {event['message']}")
        elif kind == "poses":
            self._line(f"camera poses corrected by {event['median_degrees']:.3f} deg (median; largest "
                       f"{event['max_degrees']:.3f}) and shifted by {event['median_shift']:.1%} of the camera spacing")
        elif kind in ("finished", "cancelled"):
            val = f", held-out PSNR {event['val_psnr']:.2f} dB (ray sample)" if event.get("val_psnr") is not None else ""
            self._line(f"{kind} after {event['step']} steps{members_text(event)}, {event['elapsed']:.0f} s{val}; "
                       f"model in {event['model_dir']}")
        elif kind in ("stage", "losses", "passes", "appearance", "pose_check", "field_restart"):
            self._line(event.get("message", ""))

    def _line(self, text: str) -> None:
        global _open_bar
        self.stream.write(("\r\033[K" if self.interactive else "") + text + "\n")
        self.stream.flush()
        _open_bar = None


def members_text(event: dict) -> str:
    """How a model of several members spent its budget, for the line that ends training: each
    member's steps (members of a shared batch each train all the steps of a steps budget, so the
    step count said is one member's)."""
    steps = event.get("member_steps") or []
    if len(steps) < 2:
        return ""
    share = f", each with 1/{len(steps)} of the rays a step" if event.get("members_split") == "batch" else ""
    return f" ({' + '.join(str(s) for s in steps)} in its {len(steps)} members{share})"


def make_reporter(mode: str):
    return JsonLines() if mode == "json" else Bar()

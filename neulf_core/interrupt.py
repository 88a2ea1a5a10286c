"""Ctrl-C in a Python script that calls train(): a stop between two steps, not halfway
through one.

The CLI and Blender stop a training through `should_stop` (their own signal handlers set it),
so what is saved is a run paused between steps, which resumes to the very weights of one never
stopped.  A script's Ctrl-C is a KeyboardInterrupt, which can land anywhere, an optimiser step
half taken included; `ctrl_c_stops` turns the first one into the same stop.

Setting a run up (reading the photos, building the rays, the plane sweep) saves nothing a stop
could lose, and takes up to minutes on a large capture: there a stop need not wait for the first
step.  `stops_at_once` marks those spans; the signal handlers then interrupt at once (a SIGTERM
had waited 12-18 s for the first step: a fault audit, 2026-12-07).
"""

from __future__ import annotations

import contextlib
import signal
import threading


# Whether a stop signal interrupts at once, innermost span last (the main thread's: signals reach no other).
_at_once: list[bool] = []


@contextlib.contextmanager
def stops_at_once(at_once: bool = True):
    """A span where a stop signal interrupts at once (`at_once`), or, nested inside one, a span
    where it waits for the step in progress (a training's steps and its last checkpoint)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    _at_once.append(at_once)
    try:
        yield
    finally:
        _at_once.pop()


def stop_interrupts_at_once() -> bool:
    """True inside a stops_at_once span (of the main thread): nothing a stop could lose is running."""
    return bool(_at_once) and _at_once[-1] and threading.current_thread() is threading.main_thread()


@contextlib.contextmanager
def ctrl_c_stops(should_stop):
    """(stop, ctrl_c): where Python's own Ctrl-C handler is in place (a script's main thread), a
    first Ctrl-C asks the run to stop between two steps, as `should_stop` does, so the saved
    run resumes to the weights of one never stopped (a KeyboardInterrupt could land halfway
    through a step); a second one interrupts at once.  `ctrl_c()` says whether one came.
    Elsewhere (the CLI and Blender have their own handlers; other threads) nothing changes."""
    if (threading.current_thread() is not threading.main_thread()
            or signal.getsignal(signal.SIGINT) is not signal.default_int_handler):
        yield should_stop, lambda: False
        return
    asked = []

    def on_ctrl_c(signum, frame):
        if asked or stop_interrupts_at_once():
            raise KeyboardInterrupt
        asked.append(True)

    previous = signal.signal(signal.SIGINT, on_ctrl_c)
    try:
        yield (lambda: bool(asked) or (should_stop is not None and bool(should_stop()))), lambda: bool(asked)
    finally:
        signal.signal(signal.SIGINT, previous)

"""Ctrl-C in a Python script that calls train(): a stop between two steps, not halfway
through one.

The CLI and Blender stop a training through `should_stop` (their own signal handlers set it),
so what is saved is a run paused between steps, which resumes to the very weights of one never
stopped.  A script's Ctrl-C is a KeyboardInterrupt, which can land anywhere, an optimiser step
half taken included; `ctrl_c_stops` turns the first one into the same stop.
"""

from __future__ import annotations

import contextlib
import signal
import threading


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
        if asked:
            raise KeyboardInterrupt
        asked.append(True)

    previous = signal.signal(signal.SIGINT, on_ctrl_c)
    try:
        yield (lambda: bool(asked) or (should_stop is not None and bool(should_stop()))), lambda: bool(asked)
    finally:
        signal.signal(signal.SIGINT, previous)

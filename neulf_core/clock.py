"""Training time: the wall clock less the time the process stood stopped.

Ctrl-Z (then `fg`), `kill -STOP` (then `-CONT`), a scheduler suspending a job: the process
stands still while time.monotonic goes on, and a minutes budget counted the pause -- a run
stopped over lunch ended the moment it was continued (a fault audit, 2026-12-07).  Every stopped
process is continued by SIGCONT; its handler marks that one came, and the training loop then
leaves the gap it measured around the stop out of the clock (StepClock).  The gap is found only
where a training loop is running: a stop while the photos load still counts.
"""

from __future__ import annotations

import contextlib
import signal
import threading
import time

_continued = [False]  # a SIGCONT came since the training loop last looked
_stopped_seconds = [0.0]  # seconds found stopped, in this process


def running_time() -> float:
    """time.monotonic() less the seconds this process was found stopped: what budgets count."""
    return time.monotonic() - _stopped_seconds[0]


def stopped_seconds() -> float:
    return _stopped_seconds[0]


@contextlib.contextmanager
def watching_for_continue():
    """Mark each SIGCONT while the block runs (the main thread's: signals reach no other; a
    system without SIGCONT, Windows, has no Ctrl-Z to count either)."""
    if not hasattr(signal, "SIGCONT") or threading.current_thread() is not threading.main_thread():
        yield
        return

    def on_continue(_signum, _frame):
        _continued[0] = True

    previous = signal.signal(signal.SIGCONT, on_continue)
    try:
        yield
    finally:
        signal.signal(signal.SIGCONT, previous if previous is not None else signal.SIG_DFL)


class StepClock:
    """Each step's interval, from one `tick` to the next.  Where a SIGCONT came during one, the
    process stood stopped in it: all of it beyond the interval before counts as stopped."""

    def __init__(self):
        _continued[0] = False  # (one from before this loop is not its own)
        self.last, self.last_interval = time.monotonic(), 0.0

    def tick(self) -> None:
        now = time.monotonic()
        interval = now - self.last
        if _continued[0]:
            _continued[0] = False
            _stopped_seconds[0] += max(0.0, interval - self.last_interval)
            interval = min(interval, self.last_interval)
        self.last, self.last_interval = now, interval

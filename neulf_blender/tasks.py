"""Jobs in flight (training, reconstruction, installs) and the timer that drains them.

Each job is a plain `jobs.ProcessJob`; `poll_all()` applies what arrived and runs the
job's `on_done(job)` on Blender's main thread when it ends.  A `bpy.app.timers` callback
calls it twice a second; tests and background mode call it (or `job.wait()`) directly.
"""

import bpy

ACTIVE: dict = {}   # name -> (job, on_done)
INTERVAL = 0.5
# Counts the files opened in this Blender (handlers.on_load_pre): a job keeps running when the
# user opens another .blend, and its on_done must not write into that file's data.
opened_files = 0


def same_file_since(opened: int) -> bool:
    """Whether the .blend open when `opened` was read (tasks.opened_files) is still open."""
    return opened == opened_files


def start(name: str, job, on_done=None) -> None:
    ACTIVE[name] = (job, on_done)
    if not bpy.app.background and not bpy.app.timers.is_registered(_tick):
        bpy.app.timers.register(_tick, first_interval=INTERVAL, persistent=True)


def get(name: str):
    entry = ACTIVE.get(name)
    return entry[0] if entry else None


def running(name: str) -> bool:
    job = get(name)
    return job is not None and job.running


def poll_all() -> bool:
    """Drain every job; returns whether any is still running."""
    busy = False
    for name, (job, on_done) in list(ACTIVE.items()):
        job.poll()
        if job.running:
            busy = True
        elif on_done is not None:
            ACTIVE[name] = (job, None)
            on_done(job)
    return busy


def _tick():
    busy = poll_all()
    for window in bpy.context.window_manager.windows:
        for area in window.screen.areas:
            if area.type in ("VIEW_3D", "PREFERENCES", "PROPERTIES"):
                area.tag_redraw()
    return INTERVAL if busy else None


def cancel_all() -> None:
    for job, _ in ACTIVE.values():
        if job.running:
            job.cancel()

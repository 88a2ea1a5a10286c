"""One training process per model folder.

Two trainings writing the same checkpoint would overwrite each other's work (for example
Blender reopened while the training it started before a crash still runs, and Train pressed
again).  `training_lock` holds MODEL_DIR/training.lock (process id, host) for the duration
of a training; a second one is refused with a message that names the first.  A lock left by
a process that no longer exists (SIGKILL, power cut) is taken over.
"""

from __future__ import annotations

import contextlib
import json
import os
import platform
import sys
import time
from pathlib import Path

from .errors import NeulfError

LOCK_NAME = "training.lock"


def _process_alive(pid: int) -> bool:
    if sys.platform == "win32":  # os.kill(pid, 0) would terminate the process on Windows
        import ctypes

        handle = ctypes.windll.kernel32.OpenProcess(0x1000, False, pid)  # PROCESS_QUERY_LIMITED_INFORMATION
        if not handle:
            return False
        code = ctypes.c_ulong()
        ctypes.windll.kernel32.GetExitCodeProcess(handle, ctypes.byref(code))
        ctypes.windll.kernel32.CloseHandle(handle)
        return code.value == 259  # STILL_ACTIVE
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


# A process counts as started after a lock only by more than this: the boot time /proc gives is
# whole seconds, and a wall clock set back a little must not free a live training's lock.
PID_REUSE_MARGIN_SECONDS = 60


def _process_started_at(pid: int) -> float | None:
    """When process `pid` started (seconds since the epoch), where the system says (Linux's
    /proc); None elsewhere."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        boot = next(float(line.split()[1]) for line in Path("/proc/stat").read_text().splitlines()
                    if line.startswith("btime "))
        return boot + int(fields[19]) / os.sysconf("SC_CLK_TCK")  # (field 22: start time, in clock ticks)
    except (OSError, ValueError, IndexError, StopIteration, AttributeError):
        return None


def _holder(path: Path) -> dict | None:
    """The lock's owner, or None when the lock is stale (its process is gone, or its number
    now belongs to a process started after the lock was written: a container restarted, its
    new process given the same number) or unreadable."""
    owner = _read_owner(path)
    if owner is None:
        return None
    pid, host = int(owner["pid"]), str(owner["host"])
    if host != platform.node():
        return owner  # cannot check a process on another machine: assume it runs
    if not _process_alive(pid):
        return None
    started, claimed = _process_started_at(pid), owner.get("started")
    if started is not None and isinstance(claimed, (int, float)) and started > claimed + PID_REUSE_MARGIN_SECONDS:
        return None
    return owner


def _read_owner(path: Path) -> dict | None:
    """A lock's or claim's record ({"pid", "host", "started"}), or None where it cannot be read."""
    try:
        owner = json.loads(path.read_text())
        int(owner["pid"]), str(owner["host"])
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return owner


def training_holder(model_dir: Path) -> dict | None:
    """The process training MODEL_DIR now ({"pid", "host", "started"}), or None.  Lets a caller
    (Blender reopened after a crash) say that a training still runs before it starts one."""
    path = Path(model_dir) / LOCK_NAME
    return _holder(path) if path.is_file() else None


def being_trained_message(model_dir: Path, owner: dict, what_next: str) -> str:
    """One line: who trains MODEL_DIR, `what_next` to do, and, where the owner runs on another
    machine (a shared folder: its process cannot be checked), how to free a lock it left."""
    path = Path(model_dir) / LOCK_NAME
    gone = f" (if that process is gone, delete {path})" if owner["host"] != platform.node() else ""
    return f"{model_dir} is being trained by process {owner['pid']} on {owner['host']}; {what_next}{gone}."


def _try_create(path: Path) -> bool:
    try:
        fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
    except FileExistsError:
        return False
    with os.fdopen(fd, "w") as handle:
        json.dump({"pid": os.getpid(), "host": platform.node(), "started": time.time()}, handle)
    return True


def claim(path: Path) -> None:
    """Record this process at `path` (a new file), as a training lock does: for work folders
    another run must not remove while this one uses them (reconstruct's)."""
    if not _try_create(Path(path)):
        raise FileExistsError(path)


def claim_holder(path: Path, unreadable_for_seconds: float) -> dict | None:
    """The process whose claim `path` is, while it runs; None where there is no claim or its
    process is gone.  A claim that cannot be read (being written, or a passing read error on a
    network folder) counts as held until it is `unreadable_for_seconds` old."""
    path = Path(path)
    try:
        age = time.time() - path.stat().st_mtime
    except OSError:
        return None
    owner = _holder(path)
    if owner is None and age < unreadable_for_seconds and _read_owner(path) is None:
        return {"pid": "?", "host": platform.node(), "started": None}
    return owner


@contextlib.contextmanager
def training_lock(model_dir: Path):
    model_dir = Path(model_dir)
    if model_dir.exists() and not model_dir.is_dir():
        raise NeulfError(f"{model_dir} is a file; a model is a folder: choose another --out.")
    created = not model_dir.exists()
    model_dir.mkdir(parents=True, exist_ok=True)
    path = model_dir / LOCK_NAME
    try:
        while not _try_create(path):
            owner = _holder(path)
            if owner is not None:
                raise NeulfError(being_trained_message(model_dir, owner, "wait for it to finish or stop it, then resume"))
            with contextlib.suppress(FileNotFoundError):
                path.unlink()  # stale: its process is gone
        try:
            yield
        finally:
            with contextlib.suppress(FileNotFoundError):
                path.unlink()
    finally:
        if created and model_dir.is_dir() and not any(model_dir.iterdir()):
            model_dir.rmdir()  # a training that failed before its first checkpoint leaves nothing behind

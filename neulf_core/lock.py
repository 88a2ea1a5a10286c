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
import secrets
import sys
import threading
import time
from pathlib import Path

from .errors import NeulfError

LOCK_NAME = "training.lock"


def process_alive(pid: int) -> bool:
    """Whether process `pid` runs on this machine (a lock's or a temporary's owner)."""
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
    if not process_alive(pid):
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


def _new_record() -> dict:
    return {"pid": os.getpid(), "host": platform.node(), "started": time.time()}


def _try_create(path: Path) -> dict | None:
    """Create `path` holding this process's record, and return the record; None where `path`
    exists.  The record is written to a file of its own, then linked to `path` (which fails where
    `path` exists), so the file is created already holding it: created empty and written after,
    a process that read it in between took it for a stale lock, deleted it and took its own, and
    two trainings held the folder."""
    record = _new_record()
    # (".new", not ".tmp": checkpoint.remove_stale_temporaries deletes a folder's .tmp files
    # while another process may be linking its lock's; the name is no longer than a checkpoint's
    # temporary, train's check of the folder's path length covers it)
    temporary = path.with_name(f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}.new")
    try:
        temporary.write_text(json.dumps(record))
        os.link(temporary, path)
    except FileExistsError:
        return None
    except OSError:  # no hard links (FAT32/exFAT, some network shares), or no room for the longer name
        return _create_then_write(path, record)
    finally:
        with contextlib.suppress(OSError):
            temporary.unlink()
    return record


def _create_then_write(path: Path, record: dict) -> dict | None:
    """`_try_create` where a file cannot be linked: created exclusively, then written (a reader
    that finds it empty waits, `_being_written`)."""
    try:
        descriptor = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o666)
    except FileExistsError:
        return None
    with os.fdopen(descriptor, "w") as handle:
        json.dump(record, handle)
    return record


# How long a lock that cannot be read counts as being written (_create_then_write's window, a
# passing read error on a network folder) before it counts as stale.
UNREADABLE_GRACE_SECONDS = 2.0


def _being_written(path: Path) -> bool:
    try:
        age = time.time() - path.stat().st_mtime
    except OSError:
        return False
    # (a modification time in the future -- a share whose server clock runs ahead, a folder copied
    # with its times -- is no write in progress: waiting for it had hung training silently)
    return 0 <= age < UNREADABLE_GRACE_SECONDS and _read_owner(path) is None


def claim(path: Path) -> None:
    """Record this process at `path` (a new file), as a training lock does: for work folders
    another run must not remove while this one uses them (reconstruct's)."""
    if _try_create(Path(path)) is None:
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


# The training locks this process holds: the lock file's resolved path -> (the thread holding it,
# how many times it was taken).  The auto preset holds its folder's lock through its size search
# and takes it again for its final training (train_auto -> train) in the same thread.
_held: dict[str, list] = {}
_held_guard = threading.Lock()


@contextlib.contextmanager
def training_lock(model_dir: Path):
    """Hold MODEL_DIR's training lock for the block (module docstring); a thread that holds it
    already takes it again.  A second process, or another thread of this one, is refused."""
    model_dir = Path(model_dir)
    if model_dir.exists() and not model_dir.is_dir():
        raise NeulfError(f"{model_dir} is a file; a model is a folder: choose another --out.")
    key = str((model_dir / LOCK_NAME).resolve())
    with _held_guard:
        entry = _held.get(key)
        again = entry is not None and entry[0] == threading.get_ident()
        if again:
            entry[1] += 1
    if again:
        try:
            yield
        finally:
            with _held_guard:
                entry[1] -= 1
        return
    created = not model_dir.exists()
    model_dir.mkdir(parents=True, exist_ok=True)
    path = model_dir / LOCK_NAME
    try:
        record = _take(path, model_dir)
        with _held_guard:
            _held[key] = [threading.get_ident(), 1]
        try:
            yield
        finally:
            with _held_guard:
                del _held[key]
            _release(path, record)
    finally:
        if created and model_dir.is_dir() and not any(model_dir.iterdir()):
            with contextlib.suppress(OSError):  # (as the lock's own deletion)
                model_dir.rmdir()  # a training that failed before its first checkpoint leaves nothing behind


def _take(path: Path, model_dir: Path) -> dict:
    """Create the lock `path` (taking over a stale one) and return its record, or refuse."""
    while (record := _try_create(path)) is None:
        owner = _holder(path)
        if owner is not None:
            raise NeulfError(being_trained_message(model_dir, owner, "wait for it to finish or stop it, then resume"))
        if _being_written(path):
            time.sleep(0.01)
        else:
            _remove_if_stale(path)
    return record


def _remove_if_stale(path: Path) -> None:
    """Delete the lock `path` if its process is gone, one process at a time: two that both found
    it stale deleted it in turn, the second deleting the lock the first had made meanwhile, and
    both trained.  A process holding `path`.takeover judges the lock again and deletes it; no
    lock can appear in its place in between (locks are made only where none is, and only a
    process holding the takeover deletes another's)."""
    takeover = path.with_name(f".{path.name}.takeover")
    if _try_create(takeover) is None:
        # Another process is deleting the stale lock (for microseconds); if that process died
        # meanwhile its takeover file is stale in turn.
        _remove_dead_takeover(takeover)
        time.sleep(0.01)
        return
    try:
        if path.exists() and _holder(path) is None and not _being_written(path):
            with contextlib.suppress(FileNotFoundError):
                path.unlink()
    finally:
        with contextlib.suppress(FileNotFoundError):
            takeover.unlink()


def _remove_dead_takeover(takeover: Path) -> None:
    """Delete `takeover` where the process that made it is gone (it died while deleting a stale
    lock): only on that evidence, read from the very file deleted.  A takeover that vanished
    while being read had been taken for a dead one and deleted -- by then it was the next
    process's new takeover, so two processes judged the stale lock at once and one deleted the
    lock the other's neighbour had just made (two trainings held the folder)."""
    try:
        judged = _identity(takeover)
        if _read_owner(takeover) is not None:
            removable = _holder(takeover) is None  # (its process is gone)
        else:  # (left unwritten for longer than a write takes: its writer died; a future time counts so too)
            age = time.time() - takeover.stat().st_mtime
            removable = not 0 <= age < UNREADABLE_GRACE_SECONDS
        if not removable or _identity(takeover) != judged:
            return  # (alive, being written, or replaced while judged: not this process's to delete)
        # Moved aside first: only one process can move a given file, and the one moved is checked
        # to be the file judged (a new takeover made meanwhile is put back).
        aside = takeover.with_name(f"{takeover.name}.{os.getpid()}.{secrets.token_hex(4)}.dead")
        os.rename(takeover, aside)
    except OSError:
        return
    try:
        if _identity(aside) != judged:
            with contextlib.suppress(OSError):
                os.link(aside, takeover)  # (fails where yet another was made: that one stands)
    finally:
        with contextlib.suppress(OSError):
            aside.unlink()


def _identity(path: Path) -> tuple[int, int, int]:
    """Which file `path` is now: a file deleted and another made in its place (maybe reusing its
    inode number) differ in their modification time, which a rename keeps (it changes the
    change time)."""
    status = path.stat()
    return status.st_dev, status.st_ino, status.st_mtime_ns


def _release(path: Path, record: dict) -> None:
    """Delete the lock `path` if it is still this process's own (`record`): one taken over
    meanwhile as stale (a clock or process number misjudged) is another training's now."""
    if _read_owner(path) == record:
        # (a lock that cannot be deleted -- the folder turned read-only, the disk gone -- is left:
        # its process ends, so the next training takes it over as stale; raised here, its error
        # had hidden the one that ended the training, "cannot write training.lock" for the checkpoint's)
        with contextlib.suppress(OSError):
            path.unlink()

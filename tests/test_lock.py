"""The training lock (lock.py) under processes that race for it, the auto preset's size search
under it, and a model folder whose path leaves no room for the files training writes."""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from neulf_core.errors import NeulfError
from neulf_core.lock import LOCK_NAME, training_holder, training_lock

REPO = Path(__file__).resolve().parent.parent

# One racer: for each trial, at the trial's instant, take the lock of folder ROOT/<trial>; while
# holding it, count the racers that hold it too (each marks itself in the folder).
RACER = r"""
import json, os, sys, time
from pathlib import Path
from neulf_core.errors import NeulfError
from neulf_core.lock import training_lock

root, trials, first, period, hold = Path(sys.argv[1]), int(sys.argv[2]), float(sys.argv[3]), float(sys.argv[4]), float(sys.argv[5])
for trial in range(trials):
    folder, start = root / str(trial), first + trial * period
    time.sleep(max(0.0, start - time.time() - 0.02))
    while time.time() < start:  # (the last moments spun: the racers leave together)
        pass
    try:
        with training_lock(folder):
            mark = folder / f"holding.{os.getpid()}"
            mark.touch()
            time.sleep(hold)
            together = len(list(folder.glob("holding.*")))
            mark.unlink()
        print(json.dumps([trial, "held", together]), flush=True)
    except NeulfError:
        print(json.dumps([trial, "refused", 0]), flush=True)
"""


def race(root: Path, racers: int, trials: int, period: float = 0.45, hold: float = 0.3) -> list:
    first = time.time() + 1.0 + 0.1 * racers  # (after every racer has started)
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    processes = [subprocess.Popen([sys.executable, "-c", RACER, str(root), str(trials), str(first), str(period),
                                   str(hold)], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
                 for _ in range(racers)]
    rows = []
    for process in processes:
        out, err = process.communicate(timeout=120)
        assert process.returncode == 0, err
        rows += [json.loads(line) for line in out.splitlines()]
    assert len(rows) == racers * trials
    return rows


def dead_process_id() -> int:
    process = subprocess.Popen([sys.executable, "-c", "pass"])
    process.wait()
    return process.pid


@pytest.mark.parametrize("left_by", ["nobody", "a process that is gone"])
def test_processes_racing_for_a_lock_never_hold_it_together(tmp_path, left_by, record_property):
    """Six processes take one folder's lock at the same instant, twenty times.  The lock was
    created empty and written after: a racer that read it in between took it for a stale lock,
    deleted it and took its own (and the loser's release then deleted the winner's), so two or
    three held it together in 4 of 20 trials.  Where a stale lock is left (its process gone),
    two racers that both judged it stale deleted it in turn, the second deleting the first's new
    lock."""
    trials, gone = 20, dead_process_id()
    for trial in range(trials):
        (tmp_path / str(trial)).mkdir()
        if left_by != "nobody":
            stale = {"pid": gone, "host": platform.node(), "started": time.time()}
            (tmp_path / str(trial) / LOCK_NAME).write_text(json.dumps(stale))
    rows = race(tmp_path, racers=6, trials=trials)
    shared = sorted({trial for trial, what, together in rows if what == "held" and together > 1})
    held = {trial for trial, what, _ in rows if what == "held"}
    record_property("message", f"{len(shared)} of {trials} trials with two holders at once")
    assert shared == [], f"trials with two holders at once: {shared}"
    assert held == set(range(trials))  # each folder was trained by one racer (a stale lock taken over)
    leftovers = [p.relative_to(tmp_path) for p in tmp_path.rglob("*") if p.is_file()]
    assert leftovers == []  # no lock, temporary or takeover file stays behind


def test_a_lock_is_released_only_while_it_is_still_this_process(tmp_path):
    """A holder's release deleted whatever training.lock was there: a lock another process had
    taken meanwhile (the race above) was deleted, and the folder left unlocked while trained."""
    sleeper = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        with training_lock(tmp_path):
            other = {"pid": sleeper.pid, "host": platform.node(), "started": time.time()}
            (tmp_path / LOCK_NAME).write_text(json.dumps(other))  # (as a racer that took the lock over would)
        assert training_holder(tmp_path)["pid"] == sleeper.pid
        with pytest.raises(NeulfError, match=f"being trained by process {sleeper.pid}"):
            with training_lock(tmp_path):
                pass
    finally:
        sleeper.kill()
        sleeper.wait()


def test_a_lock_that_cannot_be_deleted_leaves_the_error_that_ended_the_training(tmp_path, monkeypatch, record_property):
    """The model folder turned read-only while training (a remounted disk): the checkpoint's
    write failed, and then the lock's deletion did, whose error ("cannot read or write
    training.lock") hid the checkpoint's.  The lock is left, and the next training takes it over
    as stale (its process has ended)."""
    import errno

    real_unlink = Path.unlink

    def read_only(path, *args, **kwargs):
        if path.name == LOCK_NAME:
            raise OSError(errno.EROFS, "Read-only file system", str(path))
        return real_unlink(path, *args, **kwargs)

    monkeypatch.setattr(Path, "unlink", read_only)
    failed = OSError(errno.EROFS, "Read-only file system", str(tmp_path / "checkpoint.pt"))
    with pytest.raises(OSError) as raised:
        with training_lock(tmp_path / "new"):
            raise failed
    assert raised.value is failed
    with pytest.raises(OSError) as raised:
        with training_lock(tmp_path):
            raise failed
    assert raised.value is failed and (tmp_path / LOCK_NAME).is_file()
    monkeypatch.setattr(Path, "unlink", real_unlink)
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    (tmp_path / LOCK_NAME).write_text(json.dumps({"pid": int(dead.stdout), "host": platform.node(),
                                                  "started": time.time() - 5}))  # (as the ended process left it)
    with training_lock(tmp_path):  # taken over as stale
        assert training_holder(tmp_path)["pid"] == os.getpid()
    record_property("message", "the checkpoint's own error (the lock a read-only folder keeps is taken over later)")


def test_a_lock_being_written_is_not_taken_for_a_stale_one(tmp_path):
    """Where a lock cannot be linked into place whole (a drive without hard links), it is made
    empty and written just after: one found empty and new is waited for, not deleted."""
    sleeper = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        (tmp_path / LOCK_NAME).touch()
        writer = threading.Timer(0.3, lambda: (tmp_path / LOCK_NAME).write_text(
            json.dumps({"pid": sleeper.pid, "host": platform.node(), "started": time.time()})))
        writer.start()
        with pytest.raises(NeulfError, match=f"being trained by process {sleeper.pid}"):
            with training_lock(tmp_path):
                pass
        writer.join()
    finally:
        sleeper.kill()
        sleeper.wait()


def test_the_thread_holding_a_lock_takes_it_again_and_others_are_refused(tmp_path):
    """The auto preset holds the lock through its search and its final train() takes it again;
    another thread of the process is still refused."""
    with training_lock(tmp_path / "m"):
        with training_lock(tmp_path / "m"):
            refused = []

            def other_thread():
                try:
                    with training_lock(tmp_path / "m"):
                        pass
                except NeulfError as error:
                    refused.append(str(error))

            thread = threading.Thread(target=other_thread)
            thread.start()
            thread.join()
            assert refused and f"process {os.getpid()}" in refused[0]
        assert training_holder(tmp_path / "m")["pid"] == os.getpid()  # still held: the outer block runs
    assert not (tmp_path / "m").exists()


def test_the_auto_presets_search_holds_the_lock(tiny_scene, tmp_path):
    """While the auto preset's size search ran (40 % of the budget) the folder was not locked: a
    second training of it ran to its end, and the auto run, its search spent, was then refused
    as overwriting a model."""
    from neulf_core.autosize import train_auto
    from neulf_core.train import TrainConfig

    model, seen = tmp_path / "model", {}

    def progress(event):
        if event.get("event") == "autosize" and not seen:  # the search's first candidate is done
            seen["holder"] = training_holder(model)
            seen["second"] = subprocess.run(
                [sys.executable, "-m", "neulf_core", "train", str(tiny_scene), "--out", str(model), "--steps", "5",
                 "--batch-size", "64"], env={**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"},
                capture_output=True, text=True, timeout=300)

    config = TrainConfig(preset="auto", steps=30, batch_size=256, validate_seconds=1e9, checkpoint_seconds=1e9)
    result = train_auto(tiny_scene, model, config, progress=progress)
    assert seen["holder"] is not None and seen["holder"]["pid"] == os.getpid()
    assert seen["second"].returncode != 0 and f"being trained by process {os.getpid()}" in seen["second"].stderr
    assert result.status == "finished"
    assert training_holder(model) is None and not (model / LOCK_NAME).exists()


def long_folder(base: Path, room: int) -> Path:
    """A folder path under `base` that leaves `room` characters for the names inside it before
    the system's path limit (PATH_MAX counts the terminating NUL)."""
    limit = os.pathconf(base, "PC_PATH_MAX") - 1
    longest_part = os.pathconf(base, "PC_NAME_MAX")
    path = str(base)
    while limit - room - len(path) - 1 > longest_part:
        path += "/" + "d" * (longest_part - 10)
    return Path(path + "/" + "m" * (limit - room - len(path) - 1))


@pytest.mark.skipif(sys.platform == "win32", reason="os.pathconf: POSIX")
def test_a_model_folder_path_too_long_for_the_checkpoint_is_refused_before_training(tiny_scene, tmp_path):
    """Room for training.lock but not for a checkpoint's temporary name
    (.checkpoint.pt.PID.HEX.tmp, and under members/N/ and second_start/): the run trained until
    its first checkpoint, which failed ("File name too long"), its work lost."""
    from neulf_core.train import TrainConfig, train

    model = long_folder(tmp_path, room=len("/" + LOCK_NAME) + 2)
    config = TrainConfig(preset="planes", steps=20, batch_size=64, validate_seconds=1e9, members=1, two_starts=False,
                         field_overrides={"spatial_res": [8, 16], "channels": 4})
    events = []
    with pytest.raises(NeulfError, match=r"^the model folder's path is too long: .*choose a shorter --out folder\.$"):
        train(tiny_scene, model, config, progress=events.append)
    assert events == []  # refused before the scene was loaded, let alone a step trained
    assert not model.exists()
    # Room for the top folder's files, but not for a second member's second start: refused too.
    model = long_folder(tmp_path, room=45)
    with pytest.raises(NeulfError, match="path is too long"):
        train(tiny_scene, model, TrainConfig(preset="planes", steps=20, batch_size=64, members=2))
    assert not model.exists()
    # The auto preset says so before its size search.
    from neulf_core.autosize import train_auto

    with pytest.raises(NeulfError, match="path is too long"):
        train_auto(tiny_scene, model, TrainConfig(preset="auto", steps=30, batch_size=256), progress=events.append)
    assert events == [] and not model.exists()


def test_an_empty_lock_dated_in_the_future_is_not_waited_for(tmp_path):
    """An unreadable lock whose modification time is ahead of this clock (a share whose server
    runs ahead, a folder copied with its times) is stale, not one being written: training had
    waited for the clock to catch up without a word."""
    import os
    import time

    from neulf_core.lock import LOCK_NAME, training_lock

    folder = tmp_path / "model"
    folder.mkdir()
    lock = folder / LOCK_NAME
    lock.write_text("")
    ahead = time.time() + 600
    os.utime(lock, (ahead, ahead))
    started = time.monotonic()
    with training_lock(folder):
        assert time.monotonic() - started < 1.0


def test_a_takeover_that_vanished_while_read_is_not_deleted(tmp_path, monkeypatch):
    """A process waiting on another's takeover read it just as that one deleted it and the next
    process made its own: the read found nothing, and the new takeover was deleted as a dead one's
    (two processes then judged the stale lock at once, and one deleted the lock a third had just
    made: two holders).  Simulated here by a read that finds nothing once, of a live takeover."""
    import neulf_core.lock as lock

    takeover = tmp_path / f".{LOCK_NAME}.takeover"
    takeover.write_text(json.dumps({"pid": os.getpid(), "host": platform.node(), "started": time.time()}))
    read_owner, reads = lock._read_owner, []

    def vanished_once(path):
        reads.append(path)
        return None if len(reads) == 1 else read_owner(path)

    monkeypatch.setattr(lock, "_read_owner", vanished_once)
    lock._remove_if_stale(tmp_path / LOCK_NAME)
    assert takeover.exists() and reads, "a live takeover was deleted"


@pytest.mark.parametrize("left", ["by a process that is gone", "unwritten long ago"])
def test_a_dead_processes_takeover_is_deleted(tmp_path, left):
    """A process that died while deleting a stale lock left its takeover: the next deletes it
    (and leaves nothing of its own behind), so the folder can be trained again."""
    from neulf_core.lock import _remove_dead_takeover

    takeover = tmp_path / f".{LOCK_NAME}.takeover"
    if left == "by a process that is gone":
        takeover.write_text(json.dumps({"pid": dead_process_id(), "host": platform.node(), "started": time.time()}))
    else:
        takeover.write_text("")
        os.utime(takeover, (time.time() - 60, time.time() - 60))
    _remove_dead_takeover(takeover)
    assert list(tmp_path.iterdir()) == []
    takeover.write_text("")  # (one being written now is left alone)
    _remove_dead_takeover(takeover)
    assert takeover.exists()
    with training_lock(tmp_path / "model"):
        pass

"""Processes that run neulf_core outside Blender: training, reconstruction, installs, and the
persistent render worker.  No bpy here: reader threads put plain values on queues and a
`poll()` (called by a bpy timer, or in a loop in background mode) turns them into state.
"""

from __future__ import annotations

import json
import os
import queue
import signal
import subprocess
import threading
import time
from collections import deque
from pathlib import Path

from .wording import panel_words
from ..neulf_core.errors import NeulfError, missing_module_message

ADDON_ROOT = Path(__file__).resolve().parent.parent  # the folder holding neulf_core/


def core_environment(extra_paths=()) -> dict:
    """Environment for a Python that must import this extension's neulf_core."""
    env = dict(os.environ)
    paths = [str(ADDON_ROOT), *[str(p) for p in extra_paths if p]]
    if env.get("PYTHONPATH"):
        paths.append(env["PYTHONPATH"])
    env["PYTHONPATH"] = os.pathsep.join(paths)
    env["PYTHONUNBUFFERED"] = "1"
    env.pop("PYTHONHOME", None)  # Blender's own, wrong for another interpreter
    return env


def _popen(argv, env, cwd=None):
    kwargs = {}
    if os.name == "nt":  # own process group: Ctrl+Break reaches the worker, not Blender
        kwargs["creationflags"] = subprocess.CREATE_NEW_PROCESS_GROUP
    try:
        return subprocess.Popen(argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env,
                                cwd=cwd, text=True, encoding="utf-8", errors="replace", bufsize=1, **kwargs)
    except OSError as exc:
        why = "a folder, not a program" if os.path.isdir(argv[0]) else exc.strerror
        raise NeulfError(f"cannot start {argv[0]} ({why}); check the Python interpreter in the NeuLF "
                         "preferences.") from None


def _pump(stream, tag, out: queue.Queue) -> None:
    for line in iter(stream.readline, ""):
        out.put((tag, line.rstrip("\n")))
    out.put((tag, None))


def explain_failure(stderr_lines) -> str:
    """One line for the user from a failed process's stderr."""
    lines = [line.strip() for line in stderr_lines if line.strip()]
    for line in reversed(lines):
        if line.lower().startswith("error:"):  # neulf_core's "error: ...", pip's "ERROR: ..."
            return panel_words(line[len("error:"):].strip())
    for line in reversed(lines):
        if "No module named" in line:
            return missing_module_message(line.split("No module named", 1)[1].strip(" '\""))
    return lines[-1] if lines else "the process ended without a message."


def ending_text(stderr_lines, returncode: int | None) -> str:
    """explain_failure, or where a process left no message and a signal ended it, which one:
    SIGKILL is what the system's out-of-memory killer sends."""
    if returncode is None or returncode >= 0 or any(line.strip() for line in stderr_lines):
        return explain_failure(stderr_lines)
    try:
        name = signal.Signals(-returncode).name
    except ValueError:
        name = f"signal {-returncode}"
    why = ", as the system does when memory runs out" if -returncode == getattr(signal, "SIGKILL", 9) else ""
    return f"the process was killed ({name}{why})."


class ProcessJob:
    """A subprocess read line by line; `poll()` applies what arrived and returns `state`."""

    kind = "process"

    def __init__(self, argv: list[str], env: dict | None = None, cwd=None):
        self.argv = argv
        self.state = {"status": "running", "fraction": 0.0, "message": "starting", "error": None, "started": time.time()}
        self._stderr = deque(maxlen=50)
        self._queue: queue.Queue = queue.Queue()
        self._open_streams = 2
        self.process = _popen(argv, env, cwd)
        self.process.stdin.close()
        for stream, tag in ((self.process.stdout, "out"), (self.process.stderr, "err")):
            threading.Thread(target=_pump, args=(stream, tag, self._queue), daemon=True).start()
        self._cancelled = False

    @property
    def running(self) -> bool:
        return self.state["status"] == "running"

    def poll(self) -> dict:
        while True:
            try:
                tag, line = self._queue.get_nowait()
            except queue.Empty:
                break
            if line is None:
                self._open_streams -= 1
            elif tag == "out":
                self.on_stdout(line)
            else:
                self._stderr.append(line)
                self.on_stderr(line)
        if self._open_streams == 0 and self.running and self.process.poll() is not None:
            self._finish(self.process.returncode)
        self.state["elapsed_wall"] = time.time() - self.state["started"]
        return self.state

    def wait(self, timeout: float | None = None, interval: float = 0.1) -> dict:
        """Block until the process ends (background mode and tests)."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while self.poll()["status"] == "running":
            if deadline is not None and time.monotonic() > deadline:
                self.cancel()
                raise NeulfError(f"{self.kind} did not finish within {timeout:.0f} s; it was cancelled.")
            time.sleep(interval)
        return self.state

    def cancel(self) -> None:
        """Ask the process to stop (training saves a checkpoint first)."""
        if self.process.poll() is None:
            self._cancelled = True
            if os.name == "nt":
                self.process.send_signal(signal.CTRL_BREAK_EVENT)
            else:
                self.process.send_signal(signal.SIGTERM)

    def kill(self) -> None:
        if self.process.poll() is None:
            self.process.kill()

    # ------------------------------------------------------------------ subclass hooks
    def on_stdout(self, line: str) -> None:
        self.state["message"] = line

    def on_stderr(self, line: str) -> None:
        pass

    def _finish(self, code: int) -> None:
        if code == 0:
            self.state.update(status="finished", fraction=1.0)
        elif self._cancelled:
            self.state.update(status="cancelled")
        else:
            self.state.update(status="failed", error=ending_text(self._stderr, code))


class TrainJob(ProcessJob):
    """`python -m neulf_core train ... --progress json`: one JSON event per stdout line."""

    kind = "training"

    def __init__(self, python: str, scene_dir: str, model_dir: str, *, minutes: float | None = None,
                 steps: int | None = None, resume: bool = False, preset: str | None = None, scale: float | None = None,
                 images_dir: str | None = None, device: str | None = None, env: dict | None = None,
                 checkpoint_seconds: float | None = None, sweep_teacher: bool | None = None,
                 depth_layers: int = -1, appearance: bool | None = None, refine_poses: bool | None = None,
                 back_surface: bool | None = None, stop_early: bool = True, two_starts: bool = True, members: int = 0):
        argv = [python, "-m", "neulf_core", "train", scene_dir, "--out", model_dir, "--progress", "json"]
        argv += ["--steps", str(int(steps))] if steps else ["--minutes", repr(float(minutes or 5.0))]
        if resume:
            argv.append("--resume")
        if preset and not resume:
            argv += ["--preset", preset]
        if scale and not resume:
            argv += ["--scale", repr(float(scale))]
        if sweep_teacher is not None and not resume:  # a resumed model keeps its own choice
            argv.append("--sweep-teacher" if sweep_teacher else "--no-sweep-teacher")
        if depth_layers >= 0 and not resume:  # -1: the trainer's choice for the scene
            argv += ["--depth-layers", str(int(depth_layers))]
        if appearance is not None and not resume:  # None: the trainer's choice from the photos' exposures
            argv.append("--appearance" if appearance else "--no-appearance")
        if refine_poses is not None and not resume:  # None: the trainer's pose check decides
            argv.append("--refine-poses" if refine_poses else "--no-refine-poses")
        if back_surface is not None and not resume:  # None: the trainer's rule (deep scenes); a saved field keeps its own
            argv.append("--back-surface" if back_surface else "--no-back-surface")
        if not two_starts and not resume:  # on: the trainer's rule (few photos, a budget that pays)
            argv.append("--no-two-starts")
        if members > 0 and not resume:  # 0: the trainer's rule; a model being continued keeps its own count
            argv += ["--members", str(int(members))]
        if not stop_early:  # also when continuing: a model that stopped at the limit then trains on
            argv += ["--max-passes", "0"]
        if images_dir:
            argv += ["--images", images_dir]
        if device:
            argv += ["--device", device]
        if checkpoint_seconds:
            argv += ["--checkpoint-seconds", repr(float(checkpoint_seconds))]
        self.model_dir = model_dir
        super().__init__(argv, env)
        self.state.update(step=0, elapsed=0.0, val_psnr=None, loss=None, device="", warnings=[])

    def on_stdout(self, line: str) -> None:
        try:
            event = json.loads(line)
        except json.JSONDecodeError:
            return
        kind = event.get("event")
        state = self.state
        if kind == "start":
            state.update(device=event.get("device", ""), message=f"training on {event.get('train_views')} views, "
                         f"{event.get('device', '')}")
        elif kind == "loading":
            state["message"] = f"loading {event.get('message', '')}"
        elif kind in ("step", "validate"):
            state.update(step=event.get("step", state["step"]), elapsed=event.get("elapsed", state["elapsed"]),
                         fraction=event.get("fraction", state["fraction"]), loss=event.get("loss"),
                         message=f"{'second start, ' if event.get('start') == 2 else ''}step {event.get('step')}")
            if kind == "validate" and event.get("val_psnr") is not None:
                state["val_psnr"] = event["val_psnr"]
        elif kind == "warning":
            state["warnings"].append(event.get("message", ""))
            if event.get("barely_trained"):  # (a busy machine's minutes spent before many steps)
                state["barely_trained"] = True
        elif kind == "losses":  # few photos: the multi-view losses are on by default
            state["losses"] = True
        elif kind == "appearance":  # the photos' exposures differ: a colour transform per photo
            state["appearance"] = event.get("exposure_difference_stops")
        elif kind == "passes":  # few photos: training ends at this step at the latest
            state["pass_limit"] = event.get("steps")
        elif kind == "stage":  # e.g. few photos: a second start, the better one kept
            state["message"] = event.get("message", "")
            if event.get("kept"):
                state["start_kept"] = event["kept"]
        elif kind == "pose_check":  # Refine Poses on Auto: the first steps' verdict on the poses
            state["message"] = event.get("message", "")
            state["pose_check"] = bool(event.get("refining"))
        elif kind == "field_restart":  # the poses are far off: the field starts again, smoother
            state["message"] = event.get("message", "")
            state["field_restart"] = True
        elif kind == "poses":  # Refine Poses: the corrections it found
            state["poses"] = {k: event.get(k) for k in ("median_degrees", "max_degrees", "median_shift", "max_shift")}
        elif kind in ("finished", "cancelled"):
            state["ended"] = kind  # (said by the trainer itself: an exit status alone can be anything's)
            state.update(step=event.get("step", state["step"]), elapsed=event.get("elapsed", state["elapsed"]),
                         val_psnr=event.get("val_psnr", state["val_psnr"]), message=kind,
                         last_member_step=(event.get("member_steps") or [None])[-1])
            if kind == "cancelled":
                self._cancelled = True

    def _finish(self, code: int) -> None:
        super()._finish(code)
        if self._cancelled and self.state["status"] in ("failed", "finished"):
            self.state["status"] = "cancelled"
            self.state["error"] = None
        elif self.state["status"] == "finished" and not self.state.get("ended"):
            # exit status 0 without the trainer's last event: the interpreter ran something else
            self.state.update(status="failed", error=(
                f"{self.argv[0]} ended without training (no progress from neulf_core): choose a Python "
                "with torch in the add-on's preferences (Python with torch), and press Check"))


class FramesJob(ProcessJob):
    """`python -m neulf_core frames VIDEO --out PHOTOS --count N`: "[frames] D/T frames read" on stderr."""

    kind = "frame picking"

    def __init__(self, python: str, video: str, photos_dir: str, count: int, env: dict | None = None):
        self.photos_dir = photos_dir
        super().__init__([python, "-m", "neulf_core", "frames", video, "--out", photos_dir, "--count", str(int(count))],
                         env)

    def on_stderr(self, line: str) -> None:
        if line.startswith("[frames]"):
            self.state["message"] = "picking sharp frames: " + line.removeprefix("[frames]").strip()
            try:
                done, total = line.split()[1].split("/")
                self.state["fraction"] = min(1.0, int(done) / max(1, int(total)))
            except (IndexError, ValueError):
                pass


class ReconstructJob(ProcessJob):
    """`python -m neulf_core reconstruct IMAGES --out SCENE`: progress lines on stderr."""

    kind = "reconstruction"

    def __init__(self, python: str, images_dir: str, scene_dir: str, env: dict | None = None):
        self.scene_dir = scene_dir
        super().__init__([python, "-m", "neulf_core", "reconstruct", images_dir, "--out", scene_dir], env)

    def on_stderr(self, line: str) -> None:
        if line.startswith("["):
            self.state["message"] = line
            if line.endswith(")") and "/" in line.rsplit("(", 1)[-1]:
                try:
                    done, total = line.rsplit("(", 1)[-1].rstrip(")").split("/")
                    self.state["fraction"] = int(done) / max(1, int(total))
                except ValueError:
                    pass


class CommandJob(ProcessJob):
    """Any command (pip installs, checks); stdout lines become the message."""

    kind = "command"

    def __init__(self, argv, env=None, kind="command"):
        self.kind = kind
        super().__init__(argv, env)
        self.lines: list[str] = []

    def on_stdout(self, line: str) -> None:
        self.lines.append(line)
        if line.strip():
            self.state["message"] = line.strip()[:200]


class ThreadCall:
    """`work(on_progress, should_stop)` run on a thread of its own: what a modal operator polls
    (`running`, `fraction`) and cancels, so Blender stays usable while it runs.  It ends with
    `result`, or `error` (one line), or `cancelled`."""

    def __init__(self, work):
        self.fraction, self.result, self.error, self.cancelled = 0.0, None, None, False
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(work,), daemon=True)
        self._thread.start()

    @property
    def running(self) -> bool:
        return self._thread.is_alive()

    def cancel(self) -> None:
        self._stop.set()

    def wait(self, timeout: float | None = None) -> None:
        self._thread.join(timeout)

    def _progress(self, fraction: float) -> None:
        self.fraction = fraction

    def _run(self, work) -> None:
        try:
            self.result = work(on_progress=self._progress, should_stop=self._stop.is_set)
        except InterruptedError:
            self.cancelled = True
        except NeulfError as exc:
            self.error = str(exc)
        except Exception as exc:  # noqa: BLE001  (a bug: the console gets the traceback, the user one line)
            import traceback

            traceback.print_exc()
            self.error = f"NeuLF failed ({type(exc).__name__}: {exc}); the console has the details."


# ----------------------------------------------------------------------------- render worker


class WorkerClient:
    """A persistent `python -m neulf_core.worker` speaking JSON lines (see neulf_core/worker.py)."""

    def __init__(self, python: str, scratch: str | Path, env: dict | None = None, device: str | None = None):
        self.python = python
        self.scratch = Path(scratch)
        self.env = env
        self.device = device
        self.process = None
        self._lines: queue.Queue = queue.Queue()
        self._stderr = deque(maxlen=50)
        self._next_id = 0
        self._one_call = threading.Lock()  # (the viewport's render thread and Blender's share the worker)

    def _start(self) -> None:
        self.scratch.mkdir(parents=True, exist_ok=True)
        argv = [self.python, "-m", "neulf_core.worker", "--scratch", str(self.scratch)]
        if self.device:
            argv += ["--device", self.device]
        self.process = _popen(argv, self.env)
        self._lines = queue.Queue()
        threading.Thread(target=_pump, args=(self.process.stdout, "out", self._lines), daemon=True).start()
        threading.Thread(target=self._pump_stderr, args=(self.process.stderr,), daemon=True).start()

    def _pump_stderr(self, stream) -> None:
        for line in iter(stream.readline, ""):
            self._stderr.append(line.rstrip("\n"))

    @property
    def alive(self) -> bool:
        return self.process is not None and self.process.poll() is None

    def call(self, op: str, *, on_progress=None, should_stop=None, timeout: float | None = None, **args):
        with self._one_call:
            return self._call(op, on_progress, should_stop, timeout, args)

    def _call(self, op: str, on_progress, should_stop, timeout: float | None, args: dict):
        # (this call's lines only: an earlier call's traceback had been given as the cause of a worker
        # the system killed later)
        self._stderr.clear()
        if not self.alive:
            self._start()
        self._next_id += 1
        request_id = self._next_id
        try:
            self.process.stdin.write(json.dumps({"id": request_id, "op": op, "args": args}) + "\n")
            self.process.stdin.flush()
        except (BrokenPipeError, OSError):
            self._died()
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            if should_stop is not None and should_stop():
                self.close(force=True)  # the only way to interrupt it; restarts on the next call
                raise InterruptedError("cancelled")
            if deadline is not None and time.monotonic() > deadline:
                self.close(force=True)
                raise NeulfError(f"the NeuLF worker did not answer '{op}' within {timeout:.0f} s.")
            try:
                _tag, line = self._lines.get(timeout=0.05)
            except queue.Empty:
                continue
            if line is None:
                self._died()
            try:
                message = json.loads(line)
            except json.JSONDecodeError:
                continue
            if message.get("id") != request_id:
                continue
            if "progress" in message:
                if on_progress is not None:
                    on_progress(float(message["progress"]))
                continue
            if message.get("ok"):
                return decode(message.get("result"))
            raise NeulfError(message.get("error") or "the NeuLF worker failed without a message.")

    def _died(self):
        if self.process is not None:
            try:
                self.process.wait(timeout=5)
            except subprocess.TimeoutExpired:
                pass
        time.sleep(0.05)  # let the stderr reader catch the last lines
        detail = ending_text(self._stderr, None if self.process is None else self.process.poll())
        self.process = None
        raise NeulfError(f"the NeuLF worker stopped: {detail}")

    def close(self, force: bool = False) -> None:
        if self.process is None:
            return
        if self.process.poll() is None:
            if not force:
                try:
                    self.process.stdin.write(json.dumps({"id": 0, "op": "quit"}) + "\n")
                    self.process.stdin.flush()
                    self.process.wait(timeout=5)
                except (OSError, subprocess.TimeoutExpired):
                    pass
            if self.process.poll() is None:
                self.process.kill()
                self.process.wait(timeout=5)
        self.process = None


def decode(value):
    """A worker result with its arrays loaded: ``{"__npy__": PATH}`` -> the array (file removed).

    The inverse of neulf_core.worker's encoding, kept here because this side runs in Blender's
    Python: importing neulf_core.worker there would pull in what it imports (pycolmap, torch),
    which a stock Blender does not have."""
    import numpy as np

    if isinstance(value, dict):
        if set(value) == {"__npy__"}:
            path = Path(value["__npy__"])
            array = np.load(path)
            path.unlink(missing_ok=True)
            return array
        return {k: decode(v) for k, v in value.items()}
    if isinstance(value, list):
        return [decode(v) for v in value]
    return value


def python_check_job(python: str, env: dict | None = None) -> CommandJob:
    """Runs the worker's `info` in `python`: what is installed and which device it would use."""
    code = "import json; from neulf_core.worker import Service; print(json.dumps(Service().info()))"
    return CommandJob([python, "-c", code], env, kind="dependency check")


def pip_install_job(python: str, target: str, packages: list[str], index_url: str | None = None) -> CommandJob:
    argv = [python, "-m", "pip", "install", "--disable-pip-version-check", "--upgrade", "--target", target, *packages]
    if index_url:
        argv += ["--extra-index-url", index_url]
    env = dict(os.environ)
    env.pop("PYTHONHOME", None)
    env["PYTHONNOUSERSITE"] = "1"
    return CommandJob(argv, env, kind="install")


def pose_text(poses: dict | None) -> str:
    """The camera corrections a model refined its poses with found, for the status line."""
    if not poses:
        return ""
    return f"; poses corrected by {poses['median_degrees']:.2f}° (largest {poses['max_degrees']:.2f}°)"


def job_status_text(state: dict) -> str:
    """'cancelled at step 57', 'finished at step 67 (continued from step 57)'."""
    text = f"{state['status']} at step {state.get('step', 0)}"
    if state.get("resumed_from") is not None:
        text += f" (continued from step {state['resumed_from']})"
    if state["status"] == "cancelled":
        text += "; Train continues it"
    if state.get("barely_trained") and state["status"] == "finished":
        text += "; barely trained: the budget ended before a light field is more than a blur (Train trains it further)"
    if state.get("losses"):
        text += "; with the multi-view losses (few photos)"
    if state.get("appearance") is not None:
        text += f"; a colour transform per photo (exposures differ by {state['appearance']:.2f} stops)"
    if state.get("pose_check") is False:  # (refined: pose_text shows the corrections)
        text += "; camera poses checked, not refined"
    if state.get("field_restart"):
        text += "; camera poses far off: restarted with smoother geometry at the pose check"
    if state.get("start_kept"):
        text += f"; the {state['start_kept']} of two random starts kept (few photos: the better fit)"
    # (the pass limit said last is the last member's: compared with its steps where there are members)
    last_step = state.get("last_member_step") or state.get("step", 0)
    if state["status"] == "finished" and state.get("pass_limit") and last_step >= state["pass_limit"]:
        text += "; stopped before the time was up: more training would only memorise so few photos"
    return text + pose_text(state.get("poses"))

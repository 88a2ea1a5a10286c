"""Where neulf_core runs: in Blender's own Python when torch and pycolmap import there (the
bpy module in a venv, or a Blender whose Python has them), else in a worker process of the
interpreter chosen in the preferences.  Both routes call neulf_core.worker.Service."""

from __future__ import annotations

import atexit
import importlib
import shutil
import tempfile
from pathlib import Path

from ..neulf_core.errors import as_user_error
from .jobs import WorkerClient, core_environment

_in_process = None        # Service, False (unavailable), or None (not tried)
_worker: WorkerClient | None = None
_worker_key = None
_scratch: Path | None = None  # the worker's folder for arrays in transit, removed with it


def in_process_service():
    """The in-process Service, or None when torch/pycolmap do not import in this Python."""
    global _in_process
    if _in_process is None:
        try:
            for module in ("torch", "pycolmap", "PIL", "av"):  # (what the core imports as it trains and renders)
                importlib.import_module(module)
            from ..neulf_core.worker import Service
        except Exception:  # ImportError, or a broken torch install raising anything
            _in_process = False
        else:
            _in_process = Service()
    return _in_process or None


class Core:
    """Calls a Service operation in-process or in the worker, with one signature."""

    def __init__(self, python: str, extra_paths=(), device: str | None = None, mode: str = "AUTO"):
        self.python, self.extra_paths, self.device, self.mode = python, tuple(extra_paths), device, mode

    @property
    def in_process(self) -> bool:
        return self.mode != "WORKER" and in_process_service() is not None

    @property
    def where(self) -> str:
        return "in Blender" if self.in_process else f"worker ({self.python})"

    def call(self, op: str, *, on_progress=None, should_stop=None, **args):
        if self.in_process:
            service = in_process_service()
            service.device = self.device
            if op == "render":
                if on_progress is not None or should_stop is not None:
                    def report(fraction):
                        if on_progress is not None:
                            on_progress(fraction)
                        if should_stop is not None and should_stop():
                            raise InterruptedError("cancelled")
                    args["on_progress"] = report
            try:
                return getattr(service, op)(**args)
            except (ImportError, MemoryError, RuntimeError) as exc:  # (said as the worker says them)
                user_error = as_user_error(exc)
                if user_error is None:
                    raise
                raise user_error from None
        return self._client().call(op, on_progress=on_progress, should_stop=should_stop, **args)

    def _client(self) -> WorkerClient:
        global _worker, _worker_key, _scratch
        key = (self.python, self.extra_paths, self.device)
        if _worker is None or _worker_key != key:
            shutdown()
            _scratch = Path(tempfile.mkdtemp(prefix="neulf_worker_"))
            _worker = WorkerClient(self.python, _scratch, core_environment(self.extra_paths), self.device)
            _worker_key = key
        return _worker


def shutdown() -> None:
    """Ends the worker and removes its scratch folder (a render cancelled mid-answer can leave
    an array there). Also run at exit: Blender does not unregister add-ons when it quits."""
    global _worker, _scratch
    if _worker is not None:
        _worker.close()
        _worker = None
    if _scratch is not None:
        shutil.rmtree(_scratch, ignore_errors=True)
        _scratch = None


atexit.register(shutdown)

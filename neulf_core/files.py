"""Writing a file so that a reader never sees half of it and a crash never loses the last good
one: the bytes go to a new file beside it, which then replaces it in one step.  numpy-free and
torch-free, so the EXR writer can use it in Blender's own Python.
"""

from __future__ import annotations

import os
import secrets
from pathlib import Path


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write `data` to `path` through a temporary file in the same folder.  The file gets the
    permissions any file the user writes gets (0666 less the umask): tempfile.mkstemp's 0600 made
    models and renders unreadable to the user's group, a render farm or a second account."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp")
    descriptor = os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    try:
        with os.fdopen(descriptor, "wb") as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(temporary, path)
    except OSError as exc:
        temporary.unlink(missing_ok=True)
        if exc.filename is None:  # (a write's error names no file: the message would name none)
            raise OSError(exc.errno, exc.strerror, str(path)) from exc
        raise
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise

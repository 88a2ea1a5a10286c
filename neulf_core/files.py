"""Writing a file so that a reader never sees half of it and a crash never loses the last good
one: the bytes go to a new file beside it, which then replaces it in one step.  numpy-free and
torch-free, so the EXR writer can use it in Blender's own Python.
"""

from __future__ import annotations

import errno
import os
import secrets
from pathlib import Path

from .errors import NeulfError


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write `data` to `path` through a temporary file in the same folder.  The file gets the
    permissions any file the user writes gets (0666 less the umask): tempfile.mkstemp's 0600 made
    models and renders unreadable to the user's group, a render farm or a second account."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    refuse_a_folder_in_the_way(path)
    temporary = path.with_name(temporary_name(path.name))
    try:
        # (Made inside the try: a Ctrl-C or SIGTERM is raised as soon as os.open returns, and made
        # before it the temporary was left behind.  Its name is this call's own, so removing it
        # where os.open failed removes nothing of anyone else's.)
        descriptor = os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        with os.fdopen(descriptor, "wb") as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(temporary, path)
    except OSError as exc:
        temporary.unlink(missing_ok=True)
        refuse_a_folder_in_the_way(path)  # (made since the check above)
        if exc.filename is None:  # (a write's error names no file: the message would name none)
            raise OSError(exc.errno, exc.strerror, str(path)) from exc
        raise
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise


def refuse_a_folder_in_the_way(path: Path) -> None:
    """Refuse to write `path` where a folder of that name stands: the replace then failed naming
    only the hidden temporary (".model.pt.6558.65dbfbca.tmp: Is a directory"), not the file the
    user knows.  The folder is never deleted: it may hold the user's work."""
    if path.is_dir():
        raise NeulfError(f"cannot write {path}: a folder of that name is in the way; move or rename the folder, "
                         "then try again.")


def temporary_name(name: str) -> str:
    """The name `atomic_write_bytes` writes a file called `name` under first, beside it."""
    return f".{name}.{os.getpid()}.{secrets.token_hex(4)}.tmp"


def refuse_a_path_too_long(folder: Path, longest: Path) -> None:
    """Refuse, in one line and before any work, a folder whose path leaves no room for the
    longest path a run writes inside it (`longest`, relative to it).  A checkpoint's temporary
    name is longer than anything a training makes before its first checkpoint, which then
    failed ("File name too long"), the run's work lost.  The limit is on the whole path (260
    characters on Windows without long paths, 4096 bytes on Linux), so a file named as long as
    `longest` is made in `folder` itself and removed."""
    folder, length = Path(folder), len(str(longest))
    probe = folder / ("." + "n" * max(1, length - 5) + ".tmp")  # (.tmp: a run killed here leaves what training removes)
    try:
        os.close(os.open(probe, os.O_WRONLY | os.O_CREAT, 0o666))
    except OSError as exc:
        # ENOENT: Windows' answer for a path over MAX_PATH; `folder` itself exists (it holds the lock)
        if exc.errno not in (errno.ENAMETOOLONG, errno.ENOENT):
            raise
        raise NeulfError(f"the model folder's path is too long: {folder} ({len(str(folder))} characters) leaves no room "
                         f"for the files training writes inside it (such as {longest}, {length} characters more); "
                         "choose a shorter --out folder.") from None
    probe.unlink()

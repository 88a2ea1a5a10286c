"""Where a benchmark's reference scenes are not there: one line each, and exit 0 before any work.

The scenes are in ../shared/data, which a user's fresh checkout does not have, and there tests
and benchmarks skip cleanly instead of failing (../shared/data/README.md).  A script checks the
folders a run needs right after its arguments are read, before it renders, trains or starts a
worker, so that a skip costs nothing and writes nothing.
"""

from __future__ import annotations

import sys
from pathlib import Path

DOCS = Path(__file__).resolve().parents[1] / "docs"


def missing(folder, option: str | None = "--scene") -> bool:
    """Whether `folder` (None: the run needs none) is not there; says so, naming the option that
    gives it (None: a folder no option moves)."""
    if folder is None or Path(folder).expanduser().exists():
        return False
    hint = f"; give the folder with {option}" if option else ""
    print(f"skip: {folder} not found (the reference scenes are in ../shared/data{hint})", flush=True)
    return True


def skip_unless_present(*folders, option: str = "--scene") -> None:
    """Exit 0 where any of `folders` is not there (a line for each one missing)."""
    if [folder for folder in folders if missing(folder, option)]:
        sys.exit(0)


def present(folders: dict, option: str | dict, rewrites: str | Path | None = None) -> list:
    """The keys of `folders` (name -> the folder it needs, None for none) whose folder is there,
    with a skip line for each other one (`option`: the one that gives the folders, or name ->
    option).  Exits 0 where none is left, and where some are missing and the run would rewrite
    `rewrites`, a file committed under docs/, as a whole: it would lose their rows there (a run
    that keeps the rows of what it did not run passes None)."""
    options = option if isinstance(option, dict) else dict.fromkeys(folders, option)
    gone: dict[str, bool] = {}  # folder -> missing, each said once (several configurations share CanClip)
    for name, folder in folders.items():
        if str(folder) not in gone:
            gone[str(folder)] = missing(folder, options.get(name))
    kept = [name for name, folder in folders.items() if not gone[str(folder)]]
    if not kept:
        print("skip: none of the scenes asked for is here; nothing was run or written", flush=True)
        sys.exit(0)
    if len(kept) < len(folders) and rewrites is not None and committed(Path(rewrites)):
        print(f"skip: writing {rewrites} without {', '.join(name for name in folders if name not in kept)} would "
              f"drop their rows; give their folders, or write a part elsewhere. Nothing was written.",
              flush=True)
        sys.exit(0)
    return kept


def committed(path: Path) -> bool:
    """Whether `path` is a file under the repository's docs/ (the results it keeps)."""
    path = path.expanduser().resolve()
    return path.is_file() and DOCS in path.parents

"""What a training call computes from the photos before its first step, kept for the next
run inside the same call.

One `train()` call can run `_train` several times over the same photos: a model's members,
the better of two starts (the first start, the second, then the kept one trained on), each
building the same training rays and the same depth teacher's sweep.  Inside
`kept_while_training()` each result is kept in a named slot with the key of its inputs
(`inputs_key`), and a later run asking that slot for the same key gets it without computing
it again; asking with another key lets the old result go first, so at most one result a slot
is held.  Leaving the outermost `kept_while_training()` lets everything go.  Outside it,
every call computes.
"""

from __future__ import annotations

import hashlib
import json
from contextlib import contextmanager
from typing import Callable, TypeVar

import numpy as np

T = TypeVar("T")

_entries: dict[str, tuple[str, object]] = {}  # slot -> (inputs key, result)
_depth = [0]  # kept_while_training() calls under way in this process (nested: 0 or 1 in practice)


@contextmanager
def kept_while_training():
    """Within it, `kept` keeps one result a slot for the next call with the same inputs."""
    _depth[0] += 1
    try:
        yield
    finally:
        _depth[0] -= 1
        if not _depth[0]:
            _entries.clear()


def kept(slot: str, key: str, compute: Callable[[], T]) -> T:
    """`compute()`, or inside kept_while_training the result kept in `slot` for `key`.  The
    result is shared, not copied: callers that change it in place copy it first."""
    if not _depth[0]:
        return compute()
    entry = _entries.get(slot)
    if entry is not None and entry[0] == key:
        return entry[1]
    _entries.pop(slot, None)  # the old result may be freed before the new one is built
    result = compute()
    _entries[slot] = (key, result)
    return result


def inputs_key(views, *more) -> str:
    """What a result computed from `views`' photos depends on: each photo's name, file (path,
    size, time written), camera and pose; and `more` (JSON-able: the slab's dict, scales...)."""
    parts = []
    for view in views:
        path = view.image_path
        stat = path.stat() if path is not None and path.is_file() else None
        camera = view.camera
        parts.append([view.name, str(path), stat and [stat.st_size, stat.st_mtime_ns],
                      [str(camera.model), int(camera.width), int(camera.height)],
                      np.asarray(camera.params, dtype=np.float64).tobytes().hex(),
                      np.asarray(view.R, dtype=np.float64).tobytes().hex(),
                      np.asarray(view.t, dtype=np.float64).tobytes().hex()])
    text = json.dumps([parts, list(more)], sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()

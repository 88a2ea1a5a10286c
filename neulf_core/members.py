"""Members: several light fields of one scene, trained apart and rendered as the mean of
their colours (an ensemble, `train --members N`).

Why: two runs of the default that differ only in their seed get the photos right alike and
the new viewpoints wrong differently -- where a silhouette's depth step or an edge falls, to
within a pixel (docs/SEED_SCATTER.md, "Where in the picture the seeds differ") -- so the mean
of their renders is nearer the truth than either, and two such means differ less than two
runs do.  Measured on the stability study's configurations (benchmarks/members.py,
docs/MEMBERS.md): two members of 1000 steps each against one run of 2000 steps, the same
training steps in all.  Where one run has stopped gaining from more steps (the project's
Cycles scenes, a capture of few photos) the two members are better and about twice as
steady; where it still gains (CanClip's full capture) the one run is better.  Each member
renders, so a frame costs as many field queries as there are members.

Layout: the model folder is member 1 -- a complete model by itself, trained first, with the
run's seed, so everything that reads a model folder reads it -- and member k > 1 trains in
MEMBERS_DIR/<k> inside it with seed + (k - 1) x MEMBER_SEED_OFFSET.  Each trains with the
budget's k-th share (steps split evenly, or minutes / N) through the ordinary trainer (its
pass limit, its starts, its checkpoints).  STATE_NAME lists the members that have finished;
the renderer (render.LightField.load) averages member 1 and those, so a model renders all
along, and a run cancelled or killed resumes in the member it was training.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path
from typing import Callable

from .errors import NeulfError

STATE_NAME = "members.json"
MEMBERS_DIR = "members"
MEMBER_SEED_OFFSET = 1000
MAX_MEMBERS = 8


def member_dir(model_dir: Path, member: int) -> Path:
    """Member `member` (1-based) of the model in `model_dir`: the folder itself for the first."""
    return Path(model_dir) if member == 1 else Path(model_dir) / MEMBERS_DIR / str(member)


def member_seed(seed: int, member: int) -> int:
    return seed + (member - 1) * MEMBER_SEED_OFFSET


def member_budget(config, count: int, member: int):
    """(steps, minutes) of one member: the budget split evenly (the first members take a steps
    budget's remainder)."""
    steps = None
    if config.steps:
        steps = config.steps // count + (1 if member <= config.steps % count else 0)
        if steps < 1:
            raise NeulfError(f"{config.steps} steps cannot be shared by {count} members; give at least one step each.")
    minutes = config.minutes / count if config.minutes else None
    return steps, minutes


def read_state(model_dir: Path) -> dict | None:
    try:
        state = json.loads((Path(model_dir) / STATE_NAME).read_text())
    except (OSError, ValueError):
        return None
    return state if isinstance(state, dict) and isinstance(state.get("count"), int) else None


def finished_members(model_dir: Path) -> list[int]:
    """The members after the first that finished training (what the renderer averages in)."""
    state = read_state(model_dir)
    return [int(m) for m in state.get("finished", []) if int(m) > 1] if state else []


def _write_state(model_dir: Path, state: dict) -> None:
    from .checkpoint import atomic_write_bytes

    atomic_write_bytes(Path(model_dir) / STATE_NAME, json.dumps(state, indent=2).encode())


def member_count(config, model_dir: Path, resume: bool) -> int:
    """How many members: as asked (`config.members`), or a resumed model's own count."""
    asked = config.members
    if asked is not None and not 1 <= asked <= MAX_MEMBERS:
        raise NeulfError(f"--members takes 1 to {MAX_MEMBERS}, not {asked}.")
    state = read_state(model_dir) if resume else None
    if state is None and not (resume and (Path(model_dir) / "checkpoint.pt").is_file()):
        return asked or 1  # a new model
    count = state["count"] if state else 1  # a model trained before: its own count
    if asked is not None and asked != count:
        raise NeulfError(f"{model_dir} was trained with {count} member{'s' if count > 1 else ''}; resume it with "
                         f"--members {count} (or leave --members out), or train a new model into another --out folder.")
    return count


def work_done(model_dir: str | Path) -> tuple[int, float]:
    """(steps, seconds) trained so far in all the members together (what a budget counts),
    from their model.json files; (0, 0.0) for a folder without a model."""
    model_dir = Path(model_dir)
    state = read_state(model_dir)
    folders = [member_dir(model_dir, m) for m in range(1, (state["count"] if state else 1) + 1)]
    steps, seconds = 0, 0.0
    for folder in folders:
        try:
            progress = json.loads((folder / "model.json").read_text()).get("progress", {})
        except (OSError, ValueError):
            continue
        steps += int(progress.get("step", 0))
        seconds += float(progress.get("elapsed", 0.0))
    return steps, seconds


class _MemberProgress:
    """Forwards one member's events with the fraction rescaled into the whole run's; a member
    that is not the last says it finished as a stage, not as the end of training."""

    def __init__(self, progress, member: int, count: int):
        self.progress, self.member, self.count = progress, member, count

    def __call__(self, event: dict) -> None:
        if self.progress is None:
            return
        kind = event.get("event")
        if "fraction" in event:
            event = {**event, "fraction": (self.member - 1 + float(event["fraction"])) / self.count}
        if kind == "finished" and self.member < self.count:
            event = {"event": "stage", "message": f"member {self.member} of {self.count} finished "
                                                  f"(step {event.get('step')})", "member": self.member}
        self.progress({**event, "member": self.member, "members": self.count})


def train_members(train_one: Callable, scene, model_dir: Path, config, images_dir, resume: bool,
                  progress, should_stop):
    """`train_one(scene, model_dir, config, images_dir, resume, progress, should_stop)` trains
    one model (starts.train_two_starts over train._train); this trains the members one after
    another (module docstring).  Called under the model folder's training lock."""
    from .checkpoint import checkpoint_path, remove_stale_temporaries
    from .scene import Scene, load_scene

    model_dir = Path(model_dir)
    count = member_count(config, model_dir, resume)
    state = read_state(model_dir) if resume else None
    if count == 1 and state is None:
        return train_one(scene, model_dir, replace(config, members=None), images_dir, resume, progress, should_stop)
    if not isinstance(scene, Scene):
        scene = load_scene(scene, images_dir)  # once for all the members
    if state is None:
        if not checkpoint_path(model_dir).is_file():  # members left by a model deleted since
            shutil.rmtree(model_dir / MEMBERS_DIR, ignore_errors=True)
        state = {"count": count, "seed": config.seed, "finished": []}
        model_dir.mkdir(parents=True, exist_ok=True)
        _write_state(model_dir, state)
    result = None
    for member in range(1, count + 1):
        folder = member_dir(model_dir, member)
        folder.mkdir(parents=True, exist_ok=True)
        remove_stale_temporaries(folder)
        steps, minutes = member_budget(config, count, member)
        member_config = replace(config, seed=member_seed(state["seed"], member), steps=steps, minutes=minutes,
                                members=None)
        # Member 1 is the folder the user named: resumed only when asked; the others whenever
        # they hold a checkpoint (a run of this model stopped while training them).
        member_resume = resume if member == 1 else checkpoint_path(folder).is_file()
        result = train_one(scene, folder, member_config, images_dir, member_resume,
                           _MemberProgress(progress, member, count), should_stop)
        if result.status != "finished":
            return replace(result, model_dir=model_dir)  # cancelled: --resume continues this member
        if member > 1 and member not in state["finished"]:
            state = {**state, "finished": sorted(state["finished"] + [member])}
            _write_state(model_dir, state)
    return replace(result, model_dir=model_dir, val_psnr=None)  # (the last member's alone would mislead)


"""The better of two starts: with few photos, train a second random start part-way and keep
the one that fits the photos better.

Why: with few photos one run in three can settle in a worse basin that no later step leaves
(CanClip's 6 photos, trained to their pass limit of 2374 steps: the pliers' tip drawn at the
background's depth, one held-out view 33.9-34.5 dB against 35.9-36.2).  Neither the random
start nor the ray order decides it alone, but the training loss tells the basins apart by
step 600-1000 (docs/STABILITY.md, thirty-seventh session).  So two starts (seeds s and
s + SECOND_START_SEED_OFFSET) train to DECISION_SHARE of the pass limit; the one whose
training loss over its last LOSS_WINDOW steps is lower trains on to the end, the other is
deleted.  Measured on CanClip's 6 photos, eight seeds: 35.15 +- 0.215 dB (sd) -> 35.27 +-
0.065, at 42 % more steps.  At the study's 1000 steps (the choice at step 420) it gained
nothing, so it runs only where the pass limit ends training and the budget pays for the
second start's steps on top of it:

- a steps budget: at least the pass limit plus the decision step (the steps asked for are
  the work done, the discarded start's included); one with fewer steps to spare past the pass
  limit, down to SHORTEST_DECISION_SHARE of it, makes the choice at the steps it spares;
- a minutes budget: the first start's time to the decision step, projected over the pass
  limit plus a second start, fits in the minutes (the user's few-photo capture then trains
  inside the time it was given, which the pass limit would otherwise leave unused).

Not while the poses are refined (the pose check's verdict, or --refine-poses): the training
loss then also measures how well each start's poses fit the few photos, and eight seeds on
four such configurations gained nothing on average from the choice (+0.01 dB over the 19
seeds it changed, fitted held-out poses; docs/SEED_SCATTER.md), so the first start trains on
alone and the second start's steps are saved.  `two_starts=True` still forces it.  (A verdict
that comes after the decision step -- an unsure first look decided at the second, or a pass
limit so short that the choice comes before step 100 -- leaves the choice as it was made.)

The state between the steps lives in STATE_NAME in the model folder, so a run cancelled or
killed at any point resumes where it was: the first start's checkpoint is the model folder's
own (a model to render from all along), the second start's lives in SECOND_START_DIR inside
it until the choice.
"""

from __future__ import annotations

import json
import math
import os
import shutil
from dataclasses import replace
from pathlib import Path
from typing import Callable

from .checkpoint import (CHECKPOINT_NAME, METADATA_NAME, MODEL_NAME, checkpoint_path,
                         remove_stale_temporaries)
from .errors import NeulfError
from .files import atomic_write_bytes
from .model_files import read_metadata
from .scene import Scene, load_scene

STATE_NAME = "starts.json"
SECOND_START_DIR = "second_start"
SECOND_START_SEED_OFFSET = 100
# Where the two starts are compared, as a share of the pass limit's steps: the measured
# choice was at step 1000 of 2374 (the basins apart by 600-1000).
DECISION_SHARE = 0.42
# A steps budget short of that still pays for two starts when its steps past the pass limit
# reach this share of it: the choice is then made there.  Measured: CanClip's 6 photos at
# 3000 steps, the choice at step 626 of 2374, eight seeds 35.27 +- 0.078 dB, the same as at
# step 998 (docs/SEED_SCATTER.md).
SHORTEST_DECISION_SHARE = 0.26
# The training loss is compared as a mean over this many last steps (one step's loss is a
# random batch's, noisier than the two basins' difference).
LOSS_WINDOW = 200


def decision_step(pass_limit: int, steps: int | None = None) -> int:
    """The step at which the two starts are compared: DECISION_SHARE of the pass limit, or
    earlier where a steps budget has fewer steps to spare past the pass limit."""
    step = max(1, math.ceil(DECISION_SHARE * pass_limit))
    return min(step, steps - pass_limit) if steps and steps > pass_limit else step


def steps_budget_allows(steps: int | None, pass_limit: int) -> bool:
    """A steps budget pays for two starts when it covers the pass limit plus the second
    start's steps to a decision at SHORTEST_DECISION_SHARE of the pass limit or later."""
    return bool(steps) and steps - pass_limit >= max(1, math.ceil(SHORTEST_DECISION_SHARE * pass_limit))


def minutes_budget_allows(minutes: float | None, seconds_to_decision: float, pass_limit: int) -> bool:
    """A minutes budget pays for two starts when the first start's pace to the decision step,
    carried over the pass limit plus the second start's steps, fits in it."""
    if not minutes or seconds_to_decision <= 0:
        return False
    projected = seconds_to_decision * (pass_limit + decision_step(pass_limit)) / decision_step(pass_limit)
    return projected <= 60.0 * minutes


def chosen_start(first_loss: float, second_loss: float) -> str:
    """'first' or 'second': the lower training loss (a tie keeps the first)."""
    return "second" if second_loss < first_loss else "first"


def _read_state(model_dir: Path) -> dict | None:
    """starts.json, or None where there is none (a model of one start).  One that cannot be read,
    or lacks what its stage needs, is refused in words (a list had stopped in an AttributeError,
    a missing seed in a KeyError); deleting it continues the model the folder holds as one start."""
    path = model_dir / STATE_NAME
    try:
        state = json.loads(path.read_text())
    except (FileNotFoundError, NotADirectoryError):  # (none; or a model file given, not its folder)
        return None
    except (OSError, ValueError) as exc:
        problem = exc.strerror if isinstance(exc, OSError) else "it is not JSON"
    else:
        problem = _state_problem(state)
    if problem:
        raise NeulfError(f"{path} is damaged ({problem}); delete it to train on the start the model folder holds "
                         "(train --resume), or restore it from a backup.")
    return state


# What each stage of two starts reads from the state (train_two_starts and the functions it calls).
NEEDED = {"first": {"seed": int, "second_seed": int},
          "second": {"seed": int, "second_seed": int, "pass_limit": int, "decision_step": int, "first_loss": float},
          "moving": {"seed": int, "second_seed": int, "pass_limit": int, "kept": str},
          "decided": {}}


def _state_problem(state) -> str | None:
    """What is wrong with starts.json's contents, in words; None if nothing."""
    if not isinstance(state, dict):
        return "it is not a JSON object"
    if state.get("stage") not in NEEDED:
        return f'"stage" is {state.get("stage")!r}, not one of {", ".join(NEEDED)}'
    for key, kind in NEEDED[state["stage"]].items():
        value = state.get(key)
        if isinstance(value, bool) or not isinstance(value, (int, float) if kind is float else kind):
            return f'its stage {state["stage"]!r} needs "{key}", and it is {value!r}'
    if state["stage"] == "moving" and state["kept"] not in ("first", "second"):
        return f'"kept" is {state["kept"]!r}, not "first" or "second"'
    return None


def _write_state(model_dir: Path, state: dict) -> None:
    atomic_write_bytes(model_dir / STATE_NAME, json.dumps(state, indent=2).encode())


class _Watch:
    """Follows one start's progress events: the pass limit it announces, its step, its
    elapsed time and its recent training losses; forwards the events with the fraction
    rescaled into the whole run's (the pass limit plus the second start's steps)."""

    def __init__(self, progress, stage: str, known_limit: int | None, user_stop=lambda: False,
                 steps: int | None = None, decision: int | None = None, refining_poses: bool = False):
        self.progress, self.stage, self.user_stop = progress, stage, user_stop
        self.pass_limit, self.steps, self.known_decision = known_limit, steps, decision
        self.two_starts = stage != "first" and decision is not None  # the first start learns it at its first step
        self.step, self.elapsed = 0, 0.0
        self.losses: list[float] = []
        self.refining_poses = refining_poses  # the pose check's verdict: the poses are off and being refined
        self.members = 1  # members by rule on a minutes budget (members.py): this run trains 1/members of it
        self.on_checkpoint = None  # (step, the loss window) at each checkpoint of this start: _keep_losses

    def overall(self, fraction: float) -> float:
        if not (self.pass_limit and self.two_starts):
            return fraction
        limit, decision = self.pass_limit, self.decision()
        done_before = decision if self.stage != "first" else 0
        return min(1.0, (done_before + fraction * limit) / (limit + decision))

    def decision(self) -> int:
        return self.known_decision or decision_step(self.pass_limit, self.steps)

    def __call__(self, event: dict) -> None:
        kind = event.get("event")
        if kind == "passes":
            self.pass_limit = int(event["steps"])
        if kind == "pose_check":
            self.refining_poses = bool(event.get("refining"))
        if kind == "members":
            self.members = max(1, int(event["count"]))
        if kind == "checkpoint" and self.on_checkpoint is not None:
            self.on_checkpoint(int(event["step"]), list(self.losses))
        if kind in ("step", "validate"):
            self.step = int(event["step"])
            self.elapsed = float(event.get("elapsed", self.elapsed))
            if event.get("loss") is not None and math.isfinite(event["loss"]):
                self.losses = (self.losses + [float(event["loss"])])[-LOSS_WINDOW:]
        if self.progress is None or self._not_the_models(kind, event):
            return
        if "fraction" in event:
            event = {**event, "fraction": self.overall(event["fraction"])}
        if self.stage == "second":
            event = {**event, "start": 2}
        self.progress(event)

    def _not_the_models(self, kind: str, event: dict) -> bool:
        """A start stopped at the decision step is paused, not cancelled (only the user
        cancels); the second start's own start, checkpoints, pass limit and members verdict
        are not the model's; and the kept start says the pass limit again when it resumes."""
        if kind == "cancelled":  # (after the choice a stop is the user's)
            return self.stage != "rest" and self.two_starts and not self.user_stop()
        if kind == "passes":  # said once, by the first start
            return self.stage != "first"
        # (nor its members rule's verdict: the kept start's decides, members.train_members)
        return self.stage == "second" and (kind in ("start", "checkpoint", "finished", "members")
                                           or event.get("verdict") == "members")

    def mean_loss(self) -> float:
        return sum(self.losses) / len(self.losses) if self.losses else math.inf


def train_two_starts(train_one: Callable, scene, model_dir: Path, config, images_dir, resume: bool,
                     progress, should_stop):
    """`train_one(scene, model_dir, config, images_dir, resume, progress, should_stop,
    record)` is train._train; this runs it once, or as the better of two starts (module
    docstring).  Called under the model folder's training lock."""
    has_model = checkpoint_path(model_dir).is_file()
    state = _read_state(model_dir) if resume and has_model else None
    if has_model and (not resume or state is None or state.get("stage") == "decided"):
        # a model trained with one start, or whose start is chosen: continue it (train_one
        # refuses a model folder in use without resume)
        return train_one(scene, model_dir, config, images_dir, resume, progress, should_stop, _record(state))
    if not isinstance(scene, Scene):
        scene = load_scene(scene, images_dir)
    second_dir = model_dir / SECOND_START_DIR
    if state is None:
        shutil.rmtree(second_dir, ignore_errors=True)  # a discarded start left by a model deleted since
        state = {"stage": "first", "seed": config.seed, "second_seed": config.seed + SECOND_START_SEED_OFFSET}

    user_stop = should_stop or (lambda: False)
    if state["stage"] == "first":
        state = _first_start(train_one, scene, model_dir, config, images_dir, has_model, progress, user_stop, state)
        if not isinstance(state, dict):
            return state  # one start, or stopped before the choice: its result
    if state["stage"] == "second":
        state = _second_start(train_one, scene, second_dir, config, images_dir, progress, user_stop, state)
        if not isinstance(state, dict):
            return replace(state, model_dir=model_dir)  # stopped: resumes the second start
    if state["stage"] == "moving":
        _move_model(second_dir, model_dir)
        state = {**state, "stage": "decided"}
        _write_state(model_dir, state)
    shutil.rmtree(second_dir, ignore_errors=True)
    kept_seed = state["seed"] if state["kept"] == "first" else state["second_seed"]
    _emit_stage(progress, f"kept the {state['kept']} start (seed {kept_seed}); training it on", kept=state["kept"])
    return train_one(scene, model_dir, config, images_dir, True, _Watch(progress, "rest", state["pass_limit"], user_stop,
                                                                           decision=state.get("decision_step")),
                     should_stop, _record(state))


def _keep_losses(watch: _Watch, stage: str, model_dir: Path, folder: Path, state: dict, written) -> None:
    """The start's loss window goes into the state with each of its checkpoints (while `written()`:
    the state file exists), and comes back when the start resumes from that checkpoint: a start
    stopped or killed had compared the mean of only the steps after its resumption, lower losses
    than a whole window's, so the choice leant to the start that was resumed."""
    saved = state.get(f"{stage}_losses")
    if saved and checkpoint_path(folder).is_file() and read_metadata(folder).get("progress", {}).get("step") == saved["step"]:
        watch.losses = [float(loss) for loss in saved["losses"]]

    def keep(step: int, losses: list[float]) -> None:
        if written():
            state[f"{stage}_losses"] = {"step": step, "losses": losses}
            _write_state(model_dir, state)
    watch.on_checkpoint = keep


def _first_start(train_one, scene, model_dir: Path, config, images_dir, resume: bool, progress, user_stop, state: dict):
    """The first start, in the model folder: to the decision step where two starts are
    planned (the state then says what the second needs), else to the end (its result)."""
    watch = _Watch(progress, "first", state.get("pass_limit"), user_stop, steps=config.steps,
                   refining_poses=bool(state.get("refining_poses")))  # (a resumed run may not hear it again)
    _keep_losses(watch, "first", model_dir, model_dir, state, lambda: "pass_limit" in state)

    def stop_first() -> bool:
        if watch.refining_poses and "pass_limit" in state and not state.get("refining_poses"):
            state["refining_poses"] = True  # one start from here on, a resumed run too
            _write_state(model_dir, state)
            if config.two_starts is None:
                _emit_stage(progress, "the poses are being refined: one start (the training loss would also "
                                      "measure how well each start's poses fit)")
        planned = watch.two_starts = _two_starts_planned(config, watch)
        if planned and "pass_limit" not in state:  # a cancel from here on resumes with two starts
            state["pass_limit"] = watch.pass_limit
            _write_state(model_dir, state)
        return user_stop() or (planned and watch.step >= watch.decision())

    result = train_one(scene, model_dir, config, images_dir, resume, watch, stop_first, None)
    if "pass_limit" not in state or user_stop():
        return result  # one start; or stopped by the user before the choice (STATE_NAME resumes it)
    if result.status == "finished":  # the budget ended before the decision step, or one start was decided on
        why = "the poses are being refined" if _refining_rules_out(config, watch) else "the budget ended first"
        _write_state(model_dir, {**state, "stage": "decided", "kept": "first", "why": why})
        return result
    first_loss = watch.mean_loss() if watch.losses else _last_logged_loss(result)
    if not (steps_budget_allows(config.steps, watch.pass_limit)
            or minutes_budget_allows(config.minutes / watch.members if config.minutes else None, watch.elapsed,
                                     watch.pass_limit)
            or config.two_starts):
        state = {**state, "stage": "decided", "kept": "first", "first_loss": first_loss,
                 "why": "the minutes do not pay for a second start"}
    else:
        state = {**state, "stage": "second", "decision_step": watch.decision(),
                 "first_loss": first_loss, "first_seconds": round(watch.elapsed, 2)}
    _write_state(model_dir, state)
    return state


def _second_start(train_one, scene, second_dir: Path, config, images_dir, progress, user_stop, state: dict):
    """The second start, in its own folder, to the decision step; the state then says which
    start is kept (or its result, when stopped before)."""
    _emit_stage(progress, f"a second start (seed {state['second_seed']}) to step {state['decision_step']}: "
                          "the one that fits the photos better trains on")
    watch = _Watch(progress, "second", state["pass_limit"], user_stop, decision=state["decision_step"])
    second_dir.mkdir(exist_ok=True)
    remove_stale_temporaries(second_dir)
    _keep_losses(watch, "second", second_dir.parent, second_dir, state, lambda: True)
    result = train_one(scene, second_dir, replace(config, seed=state["second_seed"]), images_dir,
                       checkpoint_path(second_dir).is_file(), watch,
                       lambda: user_stop() or watch.step >= state["decision_step"], None)
    if user_stop() or result.step < state["decision_step"]:
        return result
    second_loss = watch.mean_loss() if watch.losses else _last_logged_loss(result)
    kept = chosen_start(state["first_loss"], second_loss)
    state = {**state, "stage": "moving" if kept == "second" else "decided", "kept": kept,
             "second_loss": second_loss, "second_seconds": round(watch.elapsed, 2)}
    _write_state(second_dir.parent, state)
    return state


def _last_logged_loss(result) -> float:
    """A start resumed exactly at the decision step logged no steps of its own: its last
    validation record's training loss stands in."""
    losses = [r["loss"] for r in result.history if r.get("loss") is not None]
    return float(losses[-1]) if losses else math.inf


def _two_starts_planned(config, watch: _Watch) -> bool:
    """Whether the first start stops at the decision step: the pass limit ends training
    (announced), two starts are not turned off, and a steps budget pays for them or a
    minutes budget may (decided at the decision step from the pace; two_starts=True: always)."""
    if not watch.pass_limit or config.two_starts is False or _refining_rules_out(config, watch):
        return False
    if config.steps and not config.two_starts:
        return steps_budget_allows(config.steps, watch.pass_limit)
    return True


def _refining_rules_out(config, watch: _Watch) -> bool:
    """Whether the rule (two_starts None) trains one start because the poses are refined:
    asked for (refine_poses=True), or the pose check found them off (module docstring)."""
    return config.two_starts is None and (config.refine_poses is True or watch.refining_poses)


def _move_model(source: Path, target: Path) -> None:
    """The second start's files replace the first's (checkpoint first: render_path takes the
    newer file should this stop half-way; a rerun moves what is left)."""
    for name in (CHECKPOINT_NAME, MODEL_NAME, METADATA_NAME):
        if (source / name).is_file():
            os.replace(source / name, target / name)


def _record(state: dict | None) -> dict | None:
    """What the model's metadata says about its starts."""
    if not state:
        return None
    keys = ("kept", "seed", "second_seed", "decision_step", "first_loss", "second_loss", "first_seconds",
            "second_seconds", "why")
    return {"starts": {k: state[k] for k in keys if k in state}}


def _emit_stage(progress, message: str, **fields) -> None:
    if progress is not None:
        progress({"event": "stage", "message": message, **fields})

"""Members: several light fields of one scene, trained apart and rendered as the mean of
their colours (an ensemble, `train --members N`).

Why: two runs of the default that differ only in their seed get the photos right alike and
the new viewpoints wrong differently -- where a silhouette's depth step or an edge falls, to
within a pixel (docs/SEED_SCATTER.md, "Where in the picture the seeds differ") -- so the mean
of their renders is nearer the truth than either, and two such means differ less than two
runs do.  Measured on the stability study's configurations (benchmarks/members.py,
docs/MEMBERS.md): two members of 1000 steps each against one run of 2000 steps, the same
training steps in all.  Where one run has stopped gaining from more steps (the project's
Cycles scenes, a capture of few photos) the two members are better and mostly steadier;
where it still gains (CanClip's full capture) the one run is better.  Each member
renders, so a frame costs as many field queries as there are members.

Layout: the model folder is member 1 -- a complete model by itself, trained first, with the
run's seed, so everything that reads a model folder reads it -- and member k > 1 trains in
MEMBERS_DIR/<k> inside it with seed + (k - 1) x MEMBER_SEED_OFFSET.  Each trains with the
budget's k-th share (minutes / N; of a steps budget 1/N of the steps, or, where they split the
batch -- the default on a CPU, default_split -- all the steps with 1/N of the rays a step;
a minutes budget's first member switches to its share of the rays at the step where the rule
decides, train.BatchSwitch) through the ordinary trainer (its
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
from .model_files import CHECKPOINT_NAME, read_metadata

STATE_NAME = "members.json"
MEMBERS_DIR = "members"
MEMBER_SEED_OFFSET = 1000
MAX_MEMBERS = 8
# The rule (`members` None): two members where the budget passes over the training pixels at
# least MEMBERS_PASSES times, else one.  Measured with the same steps either way
# (benchmarks/members.py, docs/MEMBERS.md): at 61-213 passes two members were better in 24 of
# 24 runs (+0.11 dB on CanClip's 6 photos to +0.73 on the shiny scene), at 10-42 passes one run
# was as good or better (CanClip's full capture -0.87 dB at 10 passes, -0.34 at 19, +0.01 at 39;
# the Cycles scenes at 30 passes -0.11 to +0.08).  Two, not more: each member renders, and a third
# added +0.07 to +0.11 dB over two at 183-253 passes (NVIDIA H200, docs/members_h200/MEMBERS.md) for
# 1.44 times the frame time.
MEMBERS_PASSES = 60.0
RULE_MEMBERS = 2
# Members that share the batch (the default on a CPU, DEFAULT_SPLIT_ON_CPU below) do not halve
# each field's steps, so they pay from fewer passes: two from BATCH_MEMBERS_PASSES.  The
# sixty-second session's study of two members of half the batch at every budget (1000 steps,
# three seeds, AMD EPYC; docs/MEMBERS.md, docs/stability_members_batch.csv against
# docs/stability_members_steps_base.csv): each of the 16 configurations at 30-43 passes gained
# (+0.02 to +0.44 dB), while at 19 passes and fewer it was mixed (CanClip's 20 photos +0.19 at 13,
# its 13 -0.07 at 19, its 26 -0.29 to +0.21 at 10 by pose noise) or lost (HCI -0.41 to -0.46 at
# 2-7).  The real captures at the size the README trains them, minutes budgets side by side
# (sixty-fifth session, two seeds, benchmarks/side_by_side.py; docs/members_real_*.csv): fern,
# CanClip and Statue gained at every budget, +0.07 to +0.38 dB at 1.5 minutes (6.5-7.7 passes as
# the rule counts them; under the 0.3 dB the default's sizes count as a hair, for 1.8 times the
# frame time), +0.22 to +0.98 at 2.5 (10.8-13.3 passes), +0.39 to +0.57 at 4 (19.4-22.0) and
# +0.18 to +1.34 at 7 (25.1-39.8).  So two from 12 passes: above the study's mixed 10 and the
# product's 1.5 minutes.  Not counted: the multi-view losses' rays, which do not halve with the
# batch -- CanClip's 26 photos with them forced on (never its default) lost 0.49-0.58 dB at 15-16
# passes, each member making about half the one member's steps.  Deep scenes of at most 10 photos,
# where the default does train with them, gained with them forced on at 11-24 passes (sixty-sixth
# session, four seeds): fern's 8 +0.31 dB and 4 +0.27, the shiny scene's 7 +0.44 (12 of 12 pairs
# up), the Lambertian scene's 7 -0.09 (1 of 4; docs/MEMBERS.md, "the deep scenes' band").  All but
# fern's 8 at budgets of 13 s, where the two members overran it (14.4-19.1 s) and which now keep
# one (share_spent).
BATCH_MEMBERS_PASSES = 12.0
# A minutes budget learns its passes from the step rate of member 1: the median time of its
# steps after RATE_FROM_STEP up to RATE_DECISION_STEP; its share of the minutes is set there.
# After the pose check (step 100, or 200 after an unsure first look), whose refinement -- and
# the multi-view losses that stop at its verdict for 11 to 20 photos -- slow the first steps:
# the synthetic shiny scene's 14 photos at 1 minute ran 2144 steps a minute over steps 10-30,
# 1531 over 30-100 and 2621 over 110-300 (AMD EPYC, fifty-third session).  Timed over steps
# 10-30 (until then) the rule read 65 passes for a run that made 78, and near its 60 gave one
# member or two by the noise of those 20 steps: the study's 1-minute shiny runs with one
# member scored 30.15-30.18 dB, with two 30.64-30.78.  The mean time of steps 110-160 still
# gave one of four seeds one member (30.09 dB): a shared machine's hiccups land on a few steps.
RATE_FROM_STEP = 110
RATE_DECISION_STEP = 210
# How members share a budget (TrainConfig.members_split).  "steps": each trains 1/N of the steps
# with the preset's batch (the rule above was measured so).  "batch": each trains all the steps
# with 1/N of the rays a step -- on a CPU, where a step's time grows with its rays, about 1/N of
# the time, so the members together see the rays of one run in about its time -- and the rule
# then trains RULE_MEMBERS at any budget.  Measured on the stability study's jobs, 1000 steps,
# eight seeds, AMD EPYC, two members of 4096 rays x 1000 steps against one run of 8192 x 1000
# (docs/MEMBERS.md, docs/SEED_SCATTER.md, sixty-first session): the mean up in 14 of 15
# configurations (the synthetic scene's 10 photos 31.08 +- 0.171 -> 31.41 +- 0.084 dB, shiny
# 30.30 +- 0.122 -> 30.70 +- 0.064, CanClip 36.37 +- 0.071 -> 36.42 +- 0.054), down on CanClip at
# 1 degree of pose noise (-0.23); one run of 4096 rays gave 31.14 +- 0.127 at 1000 steps and 31.12
# +- 0.187 at 2000, so the gain is the mean of two fields, not the smaller batch.  Not the default at every budget:
# the whole stability study trained with it as the default (sixty-second session, docs/MEMBERS.md)
# kept 28 of 36 configurations' three seeds inside 0.2 dB against 29, and lost 0.41-0.46 dB on HCI,
# whose fields lose 0.9 dB with half the rays where the mean of two gets back 0.44.
SPLITS = ("steps", "batch")
# The default's split (members_split None) where it trains several members: the batch on a CPU,
# the steps elsewhere.  On a CPU a step of half the batch takes 0.5-0.75 of the time, so two
# members of half the batch make more steps in the same minutes than two of the whole batch
# and half the minutes each.  Where the rule gives two members (at least MEMBERS_PASSES) the
# second field's frame time and size are paid either way, and the batch split gained at equal
# time: the stability study's jobs at 1 minute, four seeds, AMD EPYC, 2 cores (docs/MEMBERS.md,
# sixty-third session): 25 of 28 pairs up, +0.15 dB on average -- the synthetic scene's 10
# photos 31.31 +- 0.091 -> 31.50 +- 0.040, shiny 30.71 -> 30.98, CanClip's 6 photos 35.56 ->
# 35.78, fern's 4 photos 21.79 -> 21.85; at the study's 1000 steps its seven such
# configurations -0.06 to +0.23 dB.  Built so (sixty-fourth session: a minutes budget's first
# member switches at RATE_DECISION_STEP), the study's 1-minute runs it changes, paired seed by
# seed: the default's configurations 15 of 18 pairs up, -0.13 to +0.35 dB.  On a GPU a step's
# time hardly grows with its rays (an H200's step is bound by kernel launches, README), so half
# the batch would buy few more steps: the steps split stays there, as the H200 measured it
# (docs/members_h200/MEMBERS.md).  Below the split's pass threshold (passes_for_members: 12 for
# the batch split, MEMBERS_PASSES for the steps split) the default trains one member (the batch
# split asked for at every budget lost on HCI, above).
DEFAULT_SPLIT_ON_CPU = "batch"


def passes_for_members(split: str) -> float:
    """The passes from which the rule trains RULE_MEMBERS members that share the budget so."""
    return BATCH_MEMBERS_PASSES if split == "batch" else MEMBERS_PASSES


def members_by_rule(passes: float | None, split: str = "steps") -> int | None:
    """The rule's member count for a budget of `passes` over the training pixels (None: not
    known yet -- a minutes budget before the step rate is measured), for members that would
    share it by `split`.  (Members asked to split the batch train RULE_MEMBERS at any budget.)"""
    if passes is None:
        return None
    return RULE_MEMBERS if passes >= passes_for_members(split) else 1


def share_spent(minutes: float | None, count: int, elapsed: float) -> bool:
    """Whether a minutes budget's first member, deciding on `count` members after `elapsed`
    seconds, has already trained longer than its share: the second would then take its whole
    share on top, past the budget (the study's 7-photo synthetic scenes at 0.22 minutes, whose
    rate is timed by step 210, trained 14.4-19.1 s for 13.2; docs/MEMBERS.md).  So one member."""
    return bool(minutes) and count > 1 and elapsed >= 60.0 * minutes / count


def default_split(device_type: str) -> str:
    """How the default's members share a budget on a device of this type ("cpu", "cuda", "mps")."""
    return DEFAULT_SPLIT_ON_CPU if device_type == "cpu" else "steps"


def member_split(config, model_dir: Path | None = None, device_type: str = "cpu") -> str:
    """How the members of this run share its budget: a model's own split when it has members
    already (members.json; models before the choice existed split the steps), else as asked
    (`config.members_split`; None: the default's on this device type, default_split)."""
    state = read_state(model_dir) if model_dir is not None else None
    if state is not None:
        return state.get("split", "steps")
    split = getattr(config, "members_split", None) or default_split(device_type)
    if split not in SPLITS:
        raise NeulfError(f"--members-split takes {' or '.join(SPLITS)}, not {split!r}.")
    return split


def member_dir(model_dir: Path, member: int) -> Path:
    """Member `member` (1-based) of the model in `model_dir`: the folder itself for the first."""
    return Path(model_dir) if member == 1 else Path(model_dir) / MEMBERS_DIR / str(member)


def member_folders(model_dir: Path, state: dict | None) -> list[Path]:
    """The folder of each member members.json (`state`, None for one member) counts, the first first."""
    return [member_dir(model_dir, member) for member in range(1, (state["count"] if state else 1) + 1)]


def member_seed(seed: int, member: int) -> int:
    return seed + (member - 1) * MEMBER_SEED_OFFSET


def member_budget(config, count: int, member: int, split: str = "steps"):
    """(steps, minutes, batch size) of one member: a minutes budget split evenly; a steps
    budget split evenly (the first members take the remainder) with the preset's batch, or, when
    the members split the batch, all the steps each with 1/count of the batch (batch size None:
    the preset's)."""
    minutes = config.minutes / count if config.minutes else None
    if split == "batch":
        from .presets import get_preset

        whole = config.batch_size or get_preset(config.preset).batch_size
        if whole < count:
            raise NeulfError(f"a batch of {whole} rays cannot be shared by {count} members.")
        return config.steps, minutes, whole // count
    steps = None
    if config.steps:
        steps = config.steps // count + (1 if member <= config.steps % count else 0)
        if steps < 1:
            raise NeulfError(f"{config.steps} steps cannot be shared by {count} members; give at least one step each.")
    return steps, minutes, config.batch_size


def _first_members_options(model_dir: Path, config, scene, count: int) -> tuple:
    """(options, batch size) of a later member that a resume starts: the first member's
    options (split, scale, preset, ...) with this run's budget, as the first member itself
    resumes, and the batch the first member ended with (its whole batch before a minutes
    budget's switch to its share).  Started from the options the resume was given, a second
    member had trained on the first one's held-out photos (--holdout-every 0) and the ensemble
    failed at render ("another light slab")."""
    from .checkpoint import load_checkpoint
    from .train import config_for_resume

    saved = load_checkpoint(model_dir)
    first = config_for_resume(saved, config, scene)
    switch = (saved.get("members_rule") or {}).get("batch_switch")
    return first, int(switch["before"]) // count if switch else first.batch_size


def read_state(model_dir: Path) -> dict | None:
    """members.json, or None where there is none (a model of one member).  One that cannot be
    read or holds other types is refused in words: read as none it had rendered and resumed the
    first member alone without a word, and "finished": ["two"] had stopped in a ValueError."""
    path = Path(model_dir) / STATE_NAME
    try:
        state = json.loads(path.read_text())
    except (FileNotFoundError, NotADirectoryError):  # (none; or a model file given, not its folder)
        return None
    except (OSError, ValueError) as exc:
        problem = exc.strerror if isinstance(exc, OSError) else "it is not JSON"
        raise NeulfError(f"cannot read {path} ({problem}); {_STATE_REMEDY}") from None
    problem = _state_problem(state)
    if problem:
        raise NeulfError(f"{path} is damaged ({problem}); {_STATE_REMEDY}")
    return state


# What to do about a members.json that cannot be read (it lists the members after the first that finished).
_STATE_REMEDY = ('restore it from a backup, or write it again as {"count": N, "seed": SEED, "split": "batch" or '
                 '"steps", "finished": [the members after the first that finished, such as 2]}.')


def _state_problem(state) -> str | None:
    """What is wrong with members.json's contents, in words; None if nothing."""
    if not isinstance(state, dict):
        return "it is not a JSON object"
    count, seed, finished = state.get("count"), state.get("seed"), state.get("finished", [])
    if not _is_int(count) or not 1 <= count <= MAX_MEMBERS:
        return f'"count" is {count!r}, not a number of members from 1 to {MAX_MEMBERS}'
    if not _is_int(seed):
        return f'"seed" is {seed!r}, not a whole number'
    if state.get("split", "steps") not in SPLITS:
        return f'"split" is {state.get("split")!r}, not {" or ".join(map(repr, SPLITS))}'
    if not isinstance(finished, list) or not all(_is_int(m) and 2 <= m <= count for m in finished):
        return f'"finished" is {finished!r}, not a list of member numbers from 2 to {count}'
    return None


def _is_int(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def finished_members(model_dir: Path) -> list[int]:
    """The members after the first that finished training (what the renderer averages in)."""
    state = read_state(model_dir)
    return [int(m) for m in state.get("finished", []) if int(m) > 1] if state else []


def _start_state(model_dir: Path, count: int, seed: int, split: str = "steps") -> dict:
    state = {"count": count, "seed": seed, "split": split, "finished": []}
    Path(model_dir).mkdir(parents=True, exist_ok=True)
    _write_state(model_dir, state)
    return state


def _write_state(model_dir: Path, state: dict) -> None:
    from .files import atomic_write_bytes

    atomic_write_bytes(Path(model_dir) / STATE_NAME, json.dumps(state, indent=2).encode())


def member_count(config, model_dir: Path, resume: bool) -> int | None:
    """How many members: as asked (`config.members`), or a resumed model's own count; None:
    the rule's, for a new model (or one whose first member has not decided it yet)."""
    asked = config.members
    if asked is not None and not 1 <= asked <= MAX_MEMBERS:
        raise NeulfError(f"--members takes 1 to {MAX_MEMBERS}, not {asked}.")
    state = read_state(model_dir) if resume else None
    if state is None and not (resume and (Path(model_dir) / CHECKPOINT_NAME).is_file()):
        return asked  # a new model
    if state is None and asked is None and _rule_pending(model_dir):
        return None  # stopped before the first member had measured its step rate
    count = state["count"] if state else 1  # a model trained before: its own count
    if asked is not None and asked != count:
        raise NeulfError(f"{model_dir} was trained with {count} member{'s' if count > 1 else ''}; resume it with "
                         f"--members {count} (or leave --members out), or train a new model into another --out folder.")
    return count


def members_progress(model_dir: str | Path) -> list[tuple[int, float]]:
    """(steps, seconds) each member has trained so far, from their model.json files (a member
    not started yet: none); [] for a folder without a model."""
    model_dir = Path(model_dir)
    state = read_state(model_dir)
    done = []
    for folder in member_folders(model_dir, state):
        meta = read_metadata(folder)
        if not meta:
            continue  # (a member not started yet)
        progress = meta.get("progress") or {}
        try:
            done.append((int(progress.get("step", 0)), float(progress.get("elapsed", 0.0))))
        except (AttributeError, TypeError, ValueError):
            continue  # (no model.json, or one damaged: its member's work is not counted)
    return done


def work_done(model_dir: str | Path) -> tuple[int, float]:
    """(steps, seconds) trained so far in all the members together, from their model.json
    files; (0, 0.0) for a folder without a model."""
    done = members_progress(model_dir)
    return sum(steps for steps, _ in done), sum(seconds for _, seconds in done)


def budget_done(model_dir: str | Path) -> tuple[int, float]:
    """(steps, seconds) of the budget used so far, in the units a budget counts: the seconds of
    all the members; the steps of all of them where they split the steps, of the first where they
    split the batch (each trains all the steps).  What Blender's Train adds its budget to when it
    continues a model, and the step the end of training reports."""
    return _budget_of(members_progress(model_dir), read_state(Path(model_dir)))


def _budget_of(done: list[tuple[int, float]], state: dict | None) -> tuple[int, float]:
    """budget_done from the members' progress and members.json, already read."""
    seconds = sum(seconds for _, seconds in done)
    if state is not None and state.get("split") == "batch":
        return (done[0][0] if done else 0), seconds
    return sum(steps for steps, _ in done), seconds


def _rule_pending(model_dir: Path) -> bool:
    """Whether the model's first member trains under the rule and has not decided it (a
    minutes budget stopped before the step rate was measured)."""
    meta = read_metadata(model_dir)
    return bool(meta) and (meta.get("train_config") or {}).get("members", 1) is None and "members_rule" not in meta


def training_pixels(scene, config) -> int:
    """The training views' pixels at the training scale (what a pass goes over)."""
    from .scene import scaled_size, split_views
    from .rules import training_scale

    train_views, _ = split_views(scene, config.holdout_every, config.exclude)
    scale = training_scale(scene.views, config)
    return sum(w * h for w, h in (scaled_size(view.size, scale) for view in train_views))


def _decide_upfront(scene, config, progress, split: str) -> int | None:
    """The rule's count where the budget says it before training: a steps budget, or members
    asked to split the batch (two at any budget)."""
    asked_batch = getattr(config, "members_split", None) == "batch"
    if config.minutes and not asked_batch:
        return None  # learnt from the step rate in the first member (train._train)
    from .presets import get_preset
    from .rules import budget_passes

    if asked_batch:  # two at any budget: no passes to count
        count = RULE_MEMBERS
        if progress is not None:
            progress({"event": "stage", "message": f"{count} members, each with 1/{count} of the rays a step "
                                                   "(--members 1 for one)", "members": count})
        return count
    batch = config.batch_size or get_preset(config.preset).batch_size
    passes = budget_passes(config, batch, training_pixels(scene, config))
    count = members_by_rule(passes, split)
    if count > 1 and progress is not None:
        progress({"event": "stage", "message": f"{count} members: the budget passes over the training pixels "
                                               f"{passes:.0f} times (at least {passes_for_members(split):.0f}; "
                                               "--members 1 for one)"
                                               f"{share_words(split, count)}", "members": count})
    return count


def share_words(split: str, count: int) -> str:
    """How the members share the budget, for the message that announces them."""
    if split == "batch":
        return f", each all the steps with 1/{count} of the rays a step"
    return f", each 1/{count} of the budget"


class _MemberProgress:
    """Forwards one member's events with the fraction rescaled into the whole run's; a member
    that is not the last says it finished as a stage, not as the end of training."""

    def __init__(self, progress, member: int, count: int, on_decided=None, model_dir: Path | None = None):
        self.progress, self.member, self.count, self.on_decided = progress, member, count, on_decided
        self.model_dir = model_dir

    def __call__(self, event: dict) -> None:
        kind = event.get("event")
        if kind == "members" and self.on_decided is not None:  # the rule, decided in the first member
            self.count = int(event["count"])
            self.on_decided(self.count, event.get("split", "steps"))
        if self.progress is None:
            return
        if "fraction" in event:
            event = {**event, "fraction": (self.member - 1 + float(event["fraction"])) / self.count}
        if kind == "finished" and self.member < self.count:
            event = {"event": "stage", "message": f"member {self.member} of {self.count} finished "
                                                  f"(step {event.get('step')})", "member": self.member}
        elif kind == "finished" and self.count > 1 and self.model_dir is not None:
            # The model's end: the budget's steps and all the members' time, in the folder the user
            # named (a member's own validation PSNR is not the mean's, so none is said).
            done, state = members_progress(self.model_dir), read_state(self.model_dir)
            steps, seconds = _budget_of(done, state)
            event = {**event, "step": steps, "elapsed": seconds, "val_psnr": None, "model_dir": str(self.model_dir),
                     "member_steps": [member_steps for member_steps, _ in done],
                     "members_split": (state or {}).get("split", "steps")}
        self.progress({**event, "member": self.member, "members": self.count})


def _members_rule(model_dir: Path) -> dict:
    """model.json's `members_rule`: the first member's verdict on a minutes budget ({} for none)."""
    return read_metadata(model_dir).get("members_rule") or {}


def _state_as_decided(model_dir: Path, seed: int, rule: dict | None = None) -> dict | None:
    """members.json as the first member decided it on a minutes budget (`rule`: model.json's
    `members_rule`, read when not given), or None for one member.  Where two starts each timed
    their own pace, the one kept may have decided otherwise than the one whose verdict was written."""
    rule = _members_rule(model_dir) if rule is None else rule
    state = read_state(model_dir)
    count = int(rule.get("count", state["count"] if state else 1))
    if count <= 1:
        (Path(model_dir) / STATE_NAME).unlink(missing_ok=True)
        return None
    split = rule.get("split", "steps") if rule else state.get("split", "steps")
    if state is None or state["count"] != count or state.get("split", "steps") != split:
        state = _start_state(model_dir, count, state["seed"] if state else seed, split)
    return state


def train_members(train_one: Callable, scene, model_dir: Path, config, images_dir, resume: bool,
                  progress, should_stop):
    """`train_one(scene, model_dir, config, images_dir, resume, progress, should_stop)` trains
    one model (starts.train_two_starts over train._train); this trains the members one after
    another (module docstring).  Called under the model folder's training lock."""
    from .checkpoint import checkpoint_path, remove_stale_temporaries
    from .scene import Scene, load_scene

    from .device import pick_device

    model_dir = Path(model_dir)
    if not checkpoint_path(model_dir).is_file():  # a new model: what an older one's members left is not its own
        (model_dir / STATE_NAME).unlink(missing_ok=True)
        shutil.rmtree(model_dir / MEMBERS_DIR, ignore_errors=True)
    rule = _members_rule(model_dir) if resume else {}
    if rule:  # (of two starts the kept one's verdict, which members.json may not say yet: _state_as_decided)
        _state_as_decided(model_dir, config.seed, rule)
    count = member_count(config, model_dir, resume)
    state = read_state(model_dir) if resume else None
    device_type = pick_device(config.device).type
    if not isinstance(scene, Scene):
        scene = load_scene(scene, images_dir)  # once for all the members
    if count is None and not (resume and checkpoint_path(model_dir).is_file()):
        count = _decide_upfront(scene, config, progress, member_split(config, None, device_type))
    if count is not None and count == 1 and state is None:
        return train_one(scene, model_dir, replace(config, members=1), images_dir, resume, progress, should_stop)
    first_done = False
    if count is None:  # a minutes budget: the first member learns its passes from its step rate
        def on_decided(found: int, split: str) -> None:
            if found > 1:  # from here on a stop resumes as an ensemble
                _start_state(model_dir, found, config.seed, split)

        result = train_one(scene, model_dir, replace(config, members=None), images_dir, resume,
                           _MemberProgress(progress, 1, 1, on_decided), should_stop)
        state = _state_as_decided(model_dir, config.seed) if result.status == "finished" else None
        if state is None:
            return replace(result, model_dir=model_dir)  # one member, or stopped: --resume goes on
        count, first_done = state["count"], True
    split = member_split(config, model_dir if state is not None else None, device_type)
    if state is None:
        state = _start_state(model_dir, count, config.seed, split)
    for member in range(2 if first_done else 1, count + 1):
        folder = member_dir(model_dir, member)
        folder.mkdir(parents=True, exist_ok=True)
        remove_stale_temporaries(folder)
        steps, minutes, batch = member_budget(config, count, member, split)
        options = config
        if member > 1 and resume and not checkpoint_path(folder).is_file():
            options, batch = _first_members_options(model_dir, config, scene, count)
        # A member after the first follows the first one's verdict on the poses
        # (pose_check.first_members_poses): the corrections it refined, fixed, or none and no check
        # of its own.  Each refining its own settles the scene in a frame of its own (the
        # corrections' depth-like part wanders with the seed, poses.py) and their mean blurs
        # the frames.  CanClip's 6 photos with pose noise, 3000 steps, three seeds, held-out
        # PSNR with each held-out pose fitted (docs/STABILITY.md, forty-second session): own
        # corrections -> the first's at 0.25 degrees 34.77 +- 0.12 -> 35.29 +- 0.11 dB, at 1
        # degree 30.23 -> 31.35, at 2 degrees 23.46 -> 23.76; refining on from the first's
        # corrections instead (1 degree, seed 0) 31.20 against 32.06 with them fixed.
        member_config = replace(options, seed=member_seed(state["seed"], member), steps=steps, minutes=minutes,
                                batch_size=batch, members=count, members_split=split,  # (a resume may not say it)
                                poses_from=str(model_dir) if member > 1 else None)
        # Member 1 is the folder the user named: resumed only when asked; the others whenever
        # they hold a checkpoint (a run of this model stopped while training them).
        member_resume = resume if member == 1 else checkpoint_path(folder).is_file()
        result = train_one(scene, folder, member_config, images_dir, member_resume,
                           _MemberProgress(progress, member, count, model_dir=model_dir), should_stop)
        if result.status != "finished":
            return replace(result, model_dir=model_dir)  # cancelled: --resume continues this member
        if member > 1 and member not in state["finished"]:
            state = {**state, "finished": sorted(state["finished"] + [member])}
            _write_state(model_dir, state)
    return replace(result, model_dir=model_dir, val_psnr=None)  # (the last member's alone would mislead)


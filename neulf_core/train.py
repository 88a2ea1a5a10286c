"""Training a light field: random ray batches, photometric loss, checkpoints, resume, cancel.

`train(...)` is the one entry point used by the CLI, the benchmark and the Blender worker.
It reports through a `progress` callback (plain dicts; see `progress.py` for the bar and
JSON-lines printers) and stops early, after saving, when `should_stop()` returns True.
What the default decides where an option is left open is `rules.py`; what it decides about
the camera poses (the pose check, the far-off restart) is `pose_check.py`.
"""

from __future__ import annotations

import math
import numbers
import time
from collections import Counter
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from . import __version__
from .appearance import (ViewAppearance, appearance_by_default, blank_photos, exposure_difference,
                         photo_exposures)
from .checkpoint import (CHECKPOINT_NAME, MODEL_NAME, TRAINING_STATE_KEY, checkpoint_path, damaged_checkpoint,
                         load_checkpoint, remove_stale_temporaries, save_checkpoint, saved_scene_record)
from .clock import StepClock, running_time, watching_for_continue
from .consistency import SlabGeometry, camera_neighbours, multiview_losses
from .dataset import RaySet, kept_rayset, mean_colour, rows_at
from .device import describe_device, keep_freed_cpu_memory, pick_device
from .errors import NeulfError
from .files import refuse_a_path_too_long, temporary_name
from .fields import build_field, count_parameters, make_config
from .fields.disparity import slab_geometry, texture_size_for
from .interrupt import ctrl_c_stops, stops_at_once
from .lock import training_lock
from .memo import kept, kept_while_training
from .members import RATE_DECISION_STEP as MEMBERS_RATE_DECISION_STEP, RATE_FROM_STEP as MEMBERS_RATE_FROM_STEP, \
    member_budget, member_split, members_by_rule, passes_for_members, share_spent, share_words
from . import pose_check, rules
from . import poses as poses_module
from .poses import DEPTH_LIKE_GAUGE, PoseRefinement
from .progress import emit as _emit
from .paths import rig_has_baseline
from .resume_options import fields_set, kept_message, kept_on_resume
from .model_files import METADATA_NAME, foreign_metadata, read_metadata
from .saved_config import type_problem, upgraded
from .presets import APPEARANCE_ADAM_BETA2, APPEARANCE_GEOMETRY, DEFAULT_PRESET, get_preset
from .scene import Scene, load_scene, scaled_size, split_views
from .slab import Slab, fit_slab, wide_views
from .trained_scene import (camera_record, changed_cameras, changed_photos_note, images_dir_as_trained,
                            other_reconstruction, photo_digests, trained_photo_size)
from .teacher import strong_pull, sweep_depth_targets, sweep_photo_scale, teacher_fade, teacher_loss, teacher_weight
from .point_depth import point_depth_loss, point_depth_targets

VALIDATION_RAYS = 1 << 16
# The paper's loss weights: L = L_p + 0.5 L_mp + 0.1 L_d.
MULTIVIEW_WEIGHT, DEPTH_WEIGHT = 0.5, 0.1
# Adam's step for the pose corrections (radians, and shares of the camera spacing), decayed
# with the field's learning rate; they move from the first step (poses.py says in which part
# first).
POSE_LR = 3e-4


# Rays per step that get the multi-view losses: 512 of the 8192 (a step costs ~1.4 times one
# without the losses, against ~2.1 times with 2048).  Their weight is per ray, so fewer rays
# pull as hard, only noisier, and the steps saved buy more training.  Equal time, side by side,
# seeds 0 / 1 (docs/DEPTH.md, "The default"): 1024 rays against 2048 at 1 minute, the synthetic
# scene's 14 / 4 views +0.10 / +0.01, +0.16 / +0.21 dB, fern's 17 -0.05 / +0.11; 512 against
# 1024, +0.07 / +0.24, +0.11 / +0.13, +0.03 / -0.05; at 5 minutes (14 views, seed 0) 1024
# against 2048 +0.34 dB, 512 against 1024 +0.01.
CONSISTENCY_RAYS = 512


@dataclass
class TrainConfig:
    preset: str = DEFAULT_PRESET
    steps: int | None = None            # stop after this many steps in total ...
    minutes: float | None = None        # ... or after this much training time in total
    scale: float | None = None          # image scale to train at (None: default_scale)
    holdout_every: int = 8
    exclude: list[str] | None = None    # held-out view names (instead of every 8th)
    seed: int = 0
    batch_size: int | None = None       # default: the preset's
    checkpoint_seconds: float = 60.0
    validate_seconds: float = 10.0
    st_depth: float | None = None       # slab placement overrides (slab-axis depths, scene units)
    uv_depth: float = 0.0
    near: float | None = None
    far: float | None = None
    field_overrides: dict = field(default_factory=dict)
    device: str | None = None
    consistency: bool | str | None = None  # the paper's multi-view losses L_mp, L_d (None: the preset's default;
                                        # LOSSES_UNTIL_POSES_RIGHT: on until the pose check finds the poses right)
    consistency_rays: int = CONSISTENCY_RAYS  # rays per step that get them (each costs K more field queries)
    neighbours: int = 5                 # K nearest training cameras
    appearance: bool | None = None      # learn a per-photo colour transform (exposure, white balance; None: on when
                                        # neighbouring photos differ in exposure, appearance.EXPOSURE_DIFFERENCE_STOPS)
    teacher: bool | None = None         # pull early depth toward the classic plane sweep's (None: the preset's default)
    point_depth: bool | None = None     # pull the keypoints' rays toward their SfM points' depth (point_depth.py;
                                        # None: the preset's default, where the model keeps tracks)
    refine_poses: bool | None = None    # learn a small rotation and shift of each training camera (poses.py; None:
                                        # refine from the start, and keep refining after POSE_CHECK_STEP steps only
                                        # where the corrections say the poses are off)
    coarse_to_fine: bool | None = None  # fade the finer geometry scales in (None: on for at most 13 training views)
    back_surface: bool | None = None    # a second surface behind each ray's first (DisparityConfig.back_surface;
                                        # None: on for deep scenes, default_back_surface)
    max_passes: float | None = None     # stop after this many passes over the training pixels (None: the
                                        # default, FEW_PHOTOS_MAX_PASSES for few photos; 0: no limit)
    two_starts: bool | None = None      # the better of two starts where the pass limit ends training (starts.py;
                                        # None: when the budget pays for the second start; False: never)
    pixel_jitter: float = 0.0           # each training ray at a random point of a square this many pixels wide
                                        # around its pixel centre (dataset.py; 0: off, the default: real photos
                                        # lose, docs/TRAINING.md; 1: anywhere in its pixel)
    members: int | None = None          # light fields trained apart, rendered as their mean (members.py;
                                        # None: the rule -- 2 where the budget passes over the training
                                        # pixels at least 12 times on a CPU (the batch split), 60 on a GPU,
                                        # else 1 -- or a resumed model's count);
                                        # they share the budget
    members_split: str | None = None    # how members share it (members.SPLITS): "steps" -- each 1/N of the
                                        # steps -- or "batch": each all the steps with 1/N of the rays a step,
                                        # two members then at any budget (about one run's time on a CPU);
                                        # None: the rule's count, sharing the batch on a CPU and the steps
                                        # elsewhere (members.default_split)
    poses_from: str | None = None       # a model folder whose refined camera poses this run trains with, fixed
                                        # (members.py: a member after the first, in the first one's frame;
                                        # None: its own, or none)

    def budget_fraction(self, step: int, elapsed: float) -> float:
        """How far through its budget training is; whichever budget (steps or minutes) ends
        first sets the pace of the schedules."""
        fractions = []
        if self.steps:
            fractions.append(step / self.steps)
        if self.minutes:
            fractions.append(elapsed / (60.0 * self.minutes))
        return min(1.0, max(fractions)) if fractions else 0.0


@dataclass
class TrainResult:
    model_dir: Path
    status: str            # "finished" or "cancelled"
    step: int
    elapsed: float
    val_psnr: float | None
    history: list[dict]


def _seed_everything(seed: int) -> torch.Generator:
    torch.manual_seed(seed)
    np.random.seed(seed)
    generator = torch.Generator()
    generator.manual_seed(seed)
    return generator


def _angular_resolution(n_views: int) -> int:
    """Angular cells per axis: about the number of cameras along one axis of the rig, plus
    margin; more cells than that are never observed (docs/BENCHMARKS.md)."""
    return int(min(16, max(4, round(2 * math.sqrt(n_views)))))


def _build_field(preset_name: str, overrides: dict, train_views, slab: Slab, scale: float, appearance: bool = False,
                 coarse_to_fine: bool | None = None, back_surface: bool | None = None):
    n_train_views = len(train_views)
    preset = get_preset(preset_name)
    options = dict(preset.field_config)
    if preset.field == "planes" and "angular_res" not in overrides:
        options["angular_res"] = _angular_resolution(n_train_views)
    if preset.field == "disparity":
        if abs(slab.z_uv) > 1e-9:
            raise NeulfError("the fast field's shear assumes the uv plane through the camera rig (uv depth 0).")
        options.update(slab_geometry(slab))
        if "texture_size" not in overrides:
            options["texture_size"] = texture_size_for(scaled_size(max(v.size for v in train_views), scale))
        options["geometry_layers"] = rules.default_depth_layers(slab, n_train_views)
        use_ramp = coarse_to_fine if coarse_to_fine is not None else rules.default_coarse_to_fine(n_train_views)
        options["geometry_coarse_to_fine"] = rules.COARSE_TO_FINE if use_ramp else 0.0
        options["depth_detail_reads"] = rules.default_depth_detail_reads(n_train_views)
        options["back_surface"] = rules.default_back_surface(slab) if back_surface is None else back_surface
        options["tv_weight"] = rules.default_geometry_tv(n_train_views)
        if appearance:
            options.update(APPEARANCE_GEOMETRY)
    options.update(overrides)
    if preset.field == "disparity" and options.get("geometry_layers") and "depth_detail_shift" not in overrides:
        # The depth detail only where there are no depth layers: both give a depth edge a place
        # that stays put as the camera moves, and with the layers the detail measured nothing at
        # equal training time (1.5 minutes at the 20x benchmark's setting, side by side, seeds
        # 0 / 1: CanClip's 26 views +0.14 / -0.00 dB, Statue -0.16 / -0.07; HCI's 70 at 1000
        # steps, three seeds, -0.01), while without them it gained (fern +0.11 / +0.19 dB,
        # LPIPS 0.268 -> 0.257 / 0.264 -> 0.256; docs/BENCHMARKS.md, "Depth detail").
        options["depth_detail_shift"] = 0
    config = make_config(preset.field, options)
    return build_field(preset.field, config), preset


def _view_appearance(n_views: int, exposures: np.ndarray, resumed: dict | None) -> ViewAppearance:
    """The per-photo colour transforms: a resumed run's as saved (in the colour space it was
    trained in: runs saved before the linear-light transform have no flag), a new run's
    starting from the photos' measured exposures."""
    if resumed and resumed.get("appearance"):
        appearance = ViewAppearance(n_views, linear_light=bool(resumed.get("appearance_linear_light")))
        appearance.load_state_dict(resumed["appearance"])
        return appearance
    appearance = ViewAppearance(n_views)
    appearance.start_from_exposures(exposures)
    return appearance


def _optimizer(field_module, lr: float, beta2: float, appearance: ViewAppearance | None = None,
               poses: PoseRefinement | None = None) -> torch.optim.Optimizer:
    groups = field_module.param_groups(lr) if hasattr(field_module, "param_groups") else [{"params": field_module.parameters(), "lr": lr}]
    if appearance is not None:
        groups.append({"params": list(appearance.parameters()), "lr": lr, "name": "appearance"})
    # (the pose corrections, which the default's check may drop, leave the field's eps alone)
    eps = 1e-15 if len(groups) > 1 else 1e-8
    if poses is not None:
        groups.append({"params": list(poses.parameters()), "lr": POSE_LR, "name": "poses"})
    for group in groups:
        group["initial_lr"] = group["lr"]
        group["params"] = list(group["params"])  # (a generator would be spent by a first try)
    try:  # Adam's fused kernel: the same update, one kernel per step instead of a dozen small ops per tensor
        return torch.optim.Adam(groups, betas=(0.9, beta2), eps=eps, fused=True)
    except (RuntimeError, TypeError, ValueError):  # a torch or device without it (CPU before torch 2.4)
        return torch.optim.Adam(groups, betas=(0.9, beta2), eps=eps)


def learning_rate_factor(preset, fraction: float, epochs: float = 0.0) -> float:
    """The learning rate over its initial value, `fraction` of the way through the budget
    (`epochs`: training rays seen over the training set's size, for the paper's schedule)."""
    if preset.lr_decay_per_epoch is not None:
        return preset.lr_decay_per_epoch ** epochs
    if preset.lr_schedule == "cosine":
        final = preset.lr_final_ratio
        return final + (1.0 - final) * 0.5 * (1.0 + math.cos(math.pi * min(1.0, max(0.0, fraction))))
    return preset.lr_final_ratio ** fraction


def _set_learning_rate(optimizer, preset, rays_seen: int, n_rays: int, fraction: float, lr_scale: float) -> float:
    factor = learning_rate_factor(preset, fraction, rays_seen / max(1, n_rays))
    for group in optimizer.param_groups:
        group["lr"] = group["initial_lr"] * factor * lr_scale
    return preset.lr * factor * lr_scale  # the field's base rate (the groups are multiples of it)


@torch.no_grad()
def ray_sample_psnr(field_module, rays: RaySet, chunk: int = 1 << 15) -> float:
    """PSNR of the pooled squared error over a sample of held-out rays: the "val" training logs
    (and the Blender panel shows).  Not eval's score, the mean of whole views' PSNRs (pooled over
    views, a PSNR comes out below that mean), which autosize.mean_view_psnr computes for the size search."""
    field_module.eval()
    total, count = 0.0, 0
    for start in range(0, len(rays), chunk):
        index = torch.arange(start, min(start + chunk, len(rays)), device=rays.rgb.device)
        uvst, target = rays.batch(index)
        rgb, _ = field_module(uvst)
        total += float(((rgb - target) ** 2).sum())
        count += target.numel()
    field_module.train()
    return -10.0 * math.log10(max(total / max(count, 1), 1e-12))


def train(scene: Scene | str | Path, model_dir: str | Path, config: TrainConfig, *, images_dir=None, resume: bool = False,
          progress: Callable[[dict], None] | None = None, should_stop: Callable[[], bool] | None = None,
          asked: dict[str, str] | None = None) -> TrainResult:
    """Train (or with `resume`, continue) the light field of `scene` into `model_dir`.

    `asked`: the TrainConfig fields the caller asked for, each by the name to call it (the
    command line's options); None: the fields `config` sets away from their defaults, by their
    own names.  A resumed model keeps its own values of these, and says which differed."""
    model_dir = Path(model_dir).expanduser()
    check_config(config)
    from .members import train_members  # (it trains the members, each as train_two_starts does)
    from .starts import train_two_starts  # (it runs _train, once or as two starts)

    def train_one(scene, folder, config, images_dir, resume, progress, should_stop):
        return train_two_starts(_train, scene, folder, config, images_dir, resume, progress, should_stop)

    with training_lock(model_dir), kept_while_training(), watching_for_continue(), \
            ctrl_c_stops(should_stop) as (stop, ctrl_c):
        with stops_at_once():  # (nothing is training yet: a stop need not wait for a step)
            refuse_a_path_too_long(model_dir, longest_path_written(config))
            remove_stale_temporaries(model_dir)
            refuse_a_model_without_its_checkpoint(model_dir, resume)
            if resume and not checkpoint_path(model_dir).is_file():
                say_nothing_to_resume(model_dir, progress)
            elif resume:
                say_what_resume_keeps(model_dir, config, asked, progress)
            if resume and not isinstance(scene, Scene):  # the photos it trained on (LLFF: images_N/)
                images_dir = images_dir_as_trained(scene, images_dir, saved_scene_record(model_dir))
            scene = scene if isinstance(scene, Scene) else load_scene(scene, images_dir)
            config = rules.with_default_scale(scene, config, model_dir, resume, progress)
        result = train_members(train_one, scene, model_dir, config, images_dir, resume, progress, stop)
        warning = barely_trained_warning(result, config, model_dir)
        if warning:
            _emit(progress, event="warning", message=warning, barely_trained=True)
    if ctrl_c():
        raise KeyboardInterrupt  # (saved: the caller's Ctrl-C passed on)
    return result


# A minutes budget that ends this early leaves a blur: on a busy machine the plane sweep before
# the first step had taken a whole minute's budget, and CanClip "finished" at 0 steps, or at 30
# steps at 17.9 dB where the same minute trains 853 steps to 35.2 dB (a Blender audit, 2026-12-02).
FEW_STEPS = 200


def barely_trained_warning(result: TrainResult, config: TrainConfig, model_dir: Path) -> str | None:
    """What to say where a minutes budget finished with fewer than FEW_STEPS steps, else None."""
    if result.status != "finished" or config.minutes is None or result.step >= FEW_STEPS:
        return None
    sweep = read_metadata(model_dir).get("sweep_seconds") or 0.0
    spent = (f" ({sweep:.0f} s of it went to the plane sweep of the photos, before the first step)"
             if sweep >= 0.25 * config.minutes * 60 else "")
    return (f"the {config.minutes:g}-minute budget ended after only {result.step} steps{spent}: a light field this "
            "early renders a blur. Train it further: --resume with a larger --minutes (a busy machine makes each "
            "step slower).")


def longest_path_written(config: TrainConfig) -> Path:
    """The longest path, relative to the model folder, a training writes: a checkpoint's
    temporary (files.atomic_write_bytes) in the last member's second start, where the run can
    have members and two starts."""
    from .members import MAX_MEMBERS, MEMBERS_DIR
    from .starts import SECOND_START_DIR

    folder = Path()
    if config.members != 1:
        folder = folder / MEMBERS_DIR / str(MAX_MEMBERS)
    if config.two_starts is not False:
        folder = folder / SECOND_START_DIR
    return folder / temporary_name(CHECKPOINT_NAME)


def say_nothing_to_resume(model_dir: Path, progress) -> None:
    _emit(progress, event="warning", message=f"{model_dir} holds no model to resume yet: training a new one.")


def say_what_resume_keeps(model_dir: Path, config: TrainConfig, asked: dict[str, str] | None, progress) -> None:
    """The options asked for that the resumed model keeps as it has them (they had been dropped
    without a word from Python)."""
    names = asked if asked is not None else {name: name for name in fields_set(config)}
    kept = kept_on_resume(model_dir, config, names)
    if kept:
        _emit(progress, event="warning", message=(
            f"resuming continues the model as it was trained, so these options keep the model's own values: "
            f"{kept_message(kept, names)}; to train with them, train into a new model folder."))


def _train(scene, model_dir: Path, config: TrainConfig, images_dir, resume: bool, progress, should_stop,
           record: dict | None = None) -> TrainResult:
    """One training run into `model_dir`; `record`: entries for the model's metadata (how its
    start was chosen)."""
    with stops_at_once():  # setting up (the photos' rays, the plane sweep) writes nothing: a stop ends it at once
        run = TrainingRun(scene, model_dir, config, images_dir, resume, progress, record)
    with stops_at_once(False):  # ... while the steps and the last checkpoint finish what they do
        try:
            run.train_until_done(should_stop)
        except KeyboardInterrupt:  # a Python caller's Ctrl-C (the CLI and Blender stop through should_stop):
            run.status = "cancelled"  # saved as a cancel is, so resuming loses nothing, then passed on
            run.finish()
            raise
        return run.finish()


# Options of the fast field alone (the disparity field of the fast and auto presets), by their
# TrainConfig field and command-line flag.
FAST_FIELD_ONLY = {"coarse_to_fine": "--coarse-to-fine", "back_surface": "--back-surface"}


def check_config(config: TrainConfig) -> None:
    """Refuse, in one line naming the option (TrainConfig field and CLI flag), values the run
    could not use: a negative budget trained forever, a NaN one "finished" untrained, a negative
    batch failed deep in torch.  The CLI's parser refuses most of them first."""
    if not isinstance(config, TrainConfig):
        raise NeulfError(f"config must be a TrainConfig (neulf_core.train.TrainConfig), not {type(config).__name__}.")
    if not config.steps and not config.minutes:
        raise NeulfError("give a training budget: --steps N or --minutes M (TrainConfig(steps=...) or minutes=...).")
    _check_number(config.steps, "steps", "--steps", whole=True, lowest=1)
    _check_number(config.minutes, "minutes", "--minutes", above_zero=True)
    if config.scale is not None and not (_is_number(config.scale) and 0 < config.scale <= 1):
        raise NeulfError(f"--scale {config.scale} is out of range: give a value above 0 and at most 1 (1: the photos' "
                         "own size; above it, training would enlarge the photos, which adds no detail and costs "
                         "scale² more time and memory).")
    _check_number(config.batch_size, "batch_size", "--batch-size", whole=True, lowest=1)
    _check_number(config.holdout_every, "holdout_every", "--holdout-every", whole=True, lowest=0)
    _check_number(config.seed, "seed", "--seed", whole=True, lowest=0)
    _check_number(config.checkpoint_seconds, "checkpoint_seconds", "--checkpoint-seconds", lowest=0)  # (0: every step)
    _check_number(config.validate_seconds, "validate_seconds", "--validate-seconds", lowest=0)
    _check_number(config.max_passes, "max_passes", "--max-passes", lowest=0)
    _check_number(config.pixel_jitter, "pixel_jitter", "--pixel-jitter", lowest=0)
    if get_preset(config.preset).field != "disparity":  # (said, not dropped: the other fields have no such option)
        given = [f"{flag} (TrainConfig.{name})" for name, flag in FAST_FIELD_ONLY.items() if getattr(config, name) is not None]
        if "geometry_layers" in (config.field_overrides or {}):
            given.append("--depth-layers (TrainConfig.field_overrides['geometry_layers'])")
        if given:
            raise NeulfError(f"{', '.join(given)}: an option of the fast field (the fast and auto presets), which the "
                             f"preset '{config.preset}' does not train; leave it out, or choose the fast preset.")


def _is_number(value) -> bool:
    """A finite real number, numpy's included (a sweep's np.int64 steps), not True/False."""
    return (isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_))
            and math.isfinite(float(value)))


def _check_number(value, field_name: str, flag: str, *, whole: bool = False, lowest: float = 0,
                  above_zero: bool = False) -> None:
    """None passes (the default's rule); anything else must be a finite number (whole where
    `whole`) of at least `lowest`, or above 0 where `above_zero`."""
    if value is None:
        return
    fits = _is_number(value) and (not whole or float(value).is_integer()) and (
        value > 0 if above_zero else value >= lowest)
    if not fits:
        wanted = "above 0" if above_zero else f"at least {lowest:g}"
        raise NeulfError(f"{flag} (TrainConfig.{field_name}) must be a {'whole' if whole else 'finite'} number "
                         f"{wanted}, not {value!r} ({type(value).__name__}).")


def refuse_a_model_without_its_checkpoint(model_dir: Path, resume: bool) -> None:
    """A folder with model.pt but no checkpoint.pt holds a trained model whose training state was
    deleted (model.pt is all rendering needs): it can be neither resumed nor trained over.  (A
    new training had replaced it without a word, keeping its old second member beside the new
    first one.)  Nor is a folder whose model.json is another program's, which training would
    replace."""
    model_dir = Path(model_dir)
    if checkpoint_path(model_dir).is_file():
        return
    if foreign_metadata(model_dir):
        raise NeulfError(f"{model_dir} holds a {METADATA_NAME} that no NeuLF training wrote (another program's, or "
                         "damaged), which training would replace: train into another --out folder, or move that file "
                         "away.")
    if not (model_dir / MODEL_NAME).is_file():
        return
    raise NeulfError(f"{model_dir} holds a trained model ({MODEL_NAME}) without its {CHECKPOINT_NAME}, which "
                     f"{'resuming needs' if resume else 'a new training would replace'}: train into another --out "
                     f"folder, or delete {MODEL_NAME} there to start again.")


def refuse_to_overwrite(model_dir: Path, resume: bool) -> None:
    """A new training (no `resume`) into a folder that holds a model is refused, as is either into
    one holding only its render file."""
    refuse_a_model_without_its_checkpoint(model_dir, resume)
    if not resume and checkpoint_path(model_dir).is_file():
        raise NeulfError(f"{model_dir} already holds a trained model; pass --resume to continue it, or choose another --out.")


def _resumed_checkpoint(model_dir: Path, config: TrainConfig, resume: bool) -> dict | None:
    """The checkpoint a resumed run continues (None for a new one); refuses to overwrite a model."""
    refuse_to_overwrite(model_dir, resume)
    if not (resume and checkpoint_path(model_dir).is_file()):
        return None
    payload = load_checkpoint(model_dir)
    payload["train_config"] = upgraded(payload["train_config"])
    problem = type_problem(payload["train_config"], TrainConfig)
    if problem:
        raise damaged_checkpoint(checkpoint_path(model_dir), problem)
    return payload


class NonFiniteGuard:
    """A NaN/inf step is skipped; three in a row halve the learning rate (reported)."""

    def __init__(self):
        self.lr_scale, self.in_a_row, self.skipped = 1.0, 0, 0

    def skip(self, step: int, progress) -> None:
        self.skipped += 1
        self.in_a_row += 1
        if self.in_a_row >= 3:
            self.lr_scale *= 0.5
            self.in_a_row = 0
            _emit(progress, event="warning", message=f"non-finite loss at step {step}: learning rate lowered to x{self.lr_scale:g}")

    def passed(self) -> None:
        self.in_a_row = 0

    def report(self, progress) -> None:
        if self.skipped:
            _emit(progress, event="warning", message=f"{self.skipped} training steps had a non-finite loss and were skipped")


class TrainingRun:
    """One training run, from its inputs to its last checkpoint.

    Setting up follows a fixed order -- the random draws (rays held out for validation, the
    field's start, the ray order) come in the same sequence for the same seed, so a resumed
    run trains on to the same weights as one never stopped.  The loop then takes a step at a
    time, between steps making the decisions the defaults wait for (the pose check, the far-off
    restart, the multi-view losses and the members rule at the measured step rate)."""

    def __init__(self, scene, model_dir: Path, config: TrainConfig, images_dir, resume: bool, progress,
                 record: dict | None = None):
        self.model_dir, self.progress = model_dir, progress
        resumed = _resumed_checkpoint(model_dir, config, resume)
        if not isinstance(scene, Scene):
            scene = load_scene(scene, images_dir)
        if config.scale is None:  # (train() has decided it: a direct call)
            config = rules.with_default_scale(scene, config)
        asked = config
        if resumed is not None:
            config = config_for_resume(resumed, config, scene)
        self.train_views, self.held_views = split_views(scene, config.holdout_every, config.exclude)
        self.device = pick_device(config.device)
        if self.device.type == "cpu":
            # The back surface's colour batch (2 x 8192 rays x 128 hidden floats, 8 MB a buffer) lets
            # glibc hand its freed buffers back, and in 4 of 14 runs it then page-faulted them in
            # again every step: 2.3 M faults and 4.2 s of system time in 400 steps, 45-47 instead
            # of 36-43 ms a step (fern at 252x189, one thread; docs/BENCHMARKS.md).
            keep_freed_cpu_memory()
        self.generator = _seed_everything(config.seed)
        self.slab = Slab.from_dict(resumed["slab"]) if resumed else fit_slab(
            scene, self.train_views, scale=config.scale, st_depth=config.st_depth, uv_depth=config.uv_depth,
            near=config.near, far=config.far)
        _emit(progress, event="start", scene=str(scene.root), views=len(scene.views), train_views=len(self.train_views),
              held_out=[v.name for v in self.held_views], device=describe_device(self.device), preset=config.preset,
              notes=scene.notes)
        self.no_baseline = not has_baseline(self.train_views, self.slab)
        self.photo_digests = photo_digests(scene.views)
        if resumed:
            note = changed_photos_note(scene.views, resumed["scene"], "training goes on with them as they are now; "
                                       "for a model of the new photos, train into another --out folder.")
            if note:
                _emit(progress, event="warning", message=note)
        if not resumed:
            _say_wide_views(self.slab, self.train_views, config.scale, progress)
            if self.no_baseline:
                message = ("the training photos were all taken from one place (a tripod panorama, or one photo many "
                           "times): with no camera movement between them there is no parallax, so the light field "
                           "learns no depth and renders views only from that place; take the photos from positions "
                           "a little apart for a light field to fly through")
                kept("no baseline warning", message, lambda: _emit(progress, event="warning", message=message))
        masks, sweep_photos = self._load_rays(config, resumed)
        config = self._decide_appearance(config)
        self._make_field(config, resumed)
        self._set_batch(config, asked, resumed)
        config = self._set_up_poses(config, resumed)
        self._set_up_losses(config, resumed)
        self.config = config
        beta2 = APPEARANCE_ADAM_BETA2 if self.appearance is not None else self.preset.adam_beta2
        self.optimizer = _optimizer(self.field_module, self.preset.lr, beta2, self.appearance, self.poses)
        self.step, self.elapsed, self.history = 0, 0.0, []
        self.teacher, teacher_seconds = _teacher_inputs(self.train_views, self.slab, config, self.preset, self.device,
                                                        resumed, progress, masks, sweep_photos)
        self.elapsed += teacher_seconds  # the sweep is part of the training time it saves
        self.sweep_seconds = teacher_seconds or (resumed or {}).get("sweep_seconds", 0.0)
        self.strong = strong_pull(len(self.train_views), config.appearance)
        self.point_depth = _point_depth_inputs(self.train_views, self.slab, config, self.preset, self.device,
                                               self.fixed_poses is not None, masks)
        if resumed:
            self.optimizer.load_state_dict(resumed["optimizer"])
            self.step, self.elapsed = resumed["progress"]["step"], resumed["progress"]["elapsed"]
            self.history = list(resumed["progress"]["history"])
            _restore_rng(resumed.get("rng"), self.generator)
        self.meta = self._metadata(scene, resumed, record)
        # (a run resumed past the check step has decided: its saved field config says how smooth)
        self.restart_pending = (self.poses is not None and self.step < poses_module.POSE_CHECK_STEP and not self.slab.is_deep
                                and hasattr(self.field_module, "smooth_geometry"))
        self._set_budget()
        self.val = self.history[-1]["val_psnr"] if self.history else None
        self.status, self.lr, self.loss_value = "finished", None, float("nan")
        self.guard = NonFiniteGuard()

    # ------------------------------------------------------------------ setting up

    def _load_rays(self, config: TrainConfig, resumed: dict | None) -> tuple[list, list | None]:
        """The training rays (on the device) and a sample of the held-out ones for validation;
        returns each training view's representable pixels (for the depth targets) and the
        sweep's smaller photos, which come from the same decode as the training ones."""
        _emit(self.progress, event="loading", message="building training rays")
        masks = []
        sweeps = _teacher_wanted(self.train_views, config, get_preset(config.preset), resumed)
        sweep_photos = [] if sweeps else None
        train_rays = kept_rayset(
            "training rays", self.train_views, self.slab, config.scale, pixel_steps=config.pixel_jitter > 0, masks=masks,
            on_view=lambda i, n, v: _emit(self.progress, event="loading", message=f"rays of {v.name}", done=i + 1, total=n),
            photos_at=sweep_photo_scale(self.train_views, config.scale, self.slab) if sweeps else None,
            photos=sweep_photos)
        self.train_rays = train_rays.to(self.device)
        self.n_rays = len(self.train_rays)
        self.val_rays = (kept_rayset("held-out rays", self.held_views, self.slab, config.scale)
                         .subset(VALIDATION_RAYS, self.generator).to(self.device) if self.held_views else None)
        return masks, sweep_photos

    def _decide_appearance(self, config: TrainConfig) -> TrainConfig:
        """Per-photo colour transforms by the default's rule: where neighbouring photos'
        exposures differ."""
        self.exposures = photo_exposures(self.train_rays.rgb, self.train_rays.view_index, len(self.train_views))
        _say_blank_photos(self.train_views, blank_photos(self.train_rays.rgb, self.train_rays.view_index,
                                                         len(self.train_views)), self.progress)
        self.exposure_stops = exposure_difference(self.exposures, np.stack([v.center for v in self.train_views]))
        self.exposures_differ = appearance_by_default(self.exposure_stops)
        if config.appearance is None:
            config = replace(config, appearance=self.exposures_differ)
            if config.appearance:
                rules.announce_default_appearance(self.progress, len(self.train_views), self.exposure_stops)
        return config

    def _make_field(self, config: TrainConfig, resumed: dict | None) -> None:
        if resumed:
            # The field exactly as saved: a default that changed since (channels, depth layers)
            # must not change the shape of a model being continued.
            self.preset = get_preset(config.preset)
            self.field_module = build_field(resumed["field"], make_config(resumed["field"], resumed["field_config"]))
            self.field_module.load_state_dict(resumed.get(TRAINING_STATE_KEY) or resumed["state_dict"])
        else:
            self.field_module, self.preset = _build_field(config.preset, config.field_overrides, self.train_views,
                                                          self.slab, config.scale, config.appearance,
                                                          config.coarse_to_fine, config.back_surface)
        if not resumed:
            rules.announce_field_choices(
                self.progress, self.preset.field, dict(self.field_module.config.__dict__),
                {"coarse_to_fine": config.coarse_to_fine, "back_surface": config.back_surface, "teacher": config.teacher,
                 **{name: True for name in config.field_overrides}},
                _teacher_wanted(self.train_views, config, self.preset, None))
        self.field_module.to(self.device).train()
        self.appearance = (_view_appearance(len(self.train_views), self.exposures, resumed).to(self.device)
                           if config.appearance else None)

    def _set_batch(self, config: TrainConfig, asked: TrainConfig, resumed: dict | None) -> None:
        """The rays a step and the pass limit in steps; a first member whose rule split the
        batch part-way (BatchSwitch) goes on with its share."""
        batch = config.batch_size or self.preset.batch_size
        self.switch = BatchSwitch.of((resumed or {}).get("members_rule")) or _switch_on_resume(asked, resumed, batch)
        self.step_limit = rules.pass_step_limit(config, self.field_module.field_name, len(self.train_views), self.n_rays,
                                          self.switch.before if self.switch else batch)
        self.batch = batch
        if self.switch:
            self.batch = self.switch.batch
            self.step_limit = self.switch.steps_for(self.step_limit, self.batch) if self.step_limit else None

    def _set_up_poses(self, config: TrainConfig, resumed: dict | None) -> TrainConfig:
        """The camera corrections: a later member's fixed ones (the first member's), this run's
        own to refine, or none; and whether the default's pose check is still to come."""
        config, self.fixed_poses, found_right = pose_check.first_members_poses(config, resumed, self.slab, self.train_views,
                                                                     self.device)
        self.poses_found_right = found_right or (resumed or {}).get("pose_check", {}).get("refining") is False
        if config.refine_poses is None and not pose_check.check_possible(config, self.preset, self.step_limit, resumed):
            config = replace(config, refine_poses=False)
        if config.refine_poses is None and self.no_baseline:  # (the check would read the missing parallax as pose error)
            config = replace(config, refine_poses=False)
        self.pose_check_pending = config.refine_poses is None
        self.poses = (PoseRefinement(self.slab, np.stack([v.center for v in self.train_views])).to(self.device)
                      if config.refine_poses is not False else None)
        if self.poses is not None and resumed and resumed.get("poses"):
            self.poses.load_state_dict(resumed["poses"])
        return config

    def _set_up_losses(self, config: TrainConfig, resumed: dict | None) -> None:
        """The paper's multi-view losses: asked for, the preset's, or the default's rule (which
        may wait for the measured step rate, LOSSES_DECISION_STEP); stopped where the pose check
        has found the poses right."""
        rule = config.consistency if config.consistency is not None else self.preset.consistency
        self.losses_stopped_at = (resumed or {}).get("multiview_losses_until_step")  # (by the pose check's verdict)
        self.losses_pending = False
        if rule is None:
            # A resumed model keeps what it was trained with (models saved before the rule: off;
            # None: saved before the run had decided, which it then does as a new one).
            saved = resumed.get("multiview_losses", False) if resumed else None
            if saved is not None:  # (on until the pose check's verdict: so it stays)
                saved = resumed.get("multiview_losses_rule") if saved and resumed.get("multiview_losses_rule") else bool(saved)
            rule = saved if saved is not None else rules.default_consistency(self.slab, self.train_views, config)
            self.losses_pending = rule is None
        if self.losses_stopped_at is None and rules.losses_stop_at_pose_check(rule, bool(config.appearance),
                                                                         self.poses_found_right):
            self.losses_stopped_at = 0  # a later member: the first one's check found the poses right
        if config.consistency is None and self.preset.consistency is None and rule and self.losses_stopped_at is None:
            rules.announce_default_losses(self.progress, len(self.train_views))
        self.losses_rule = rule
        self.consistency = (_consistency_inputs(self.train_views, self.slab, config, self.device)
                            if rule and self.losses_stopped_at is None else None)

    def _metadata(self, scene: Scene, resumed: dict | None, record: dict | None) -> dict:
        """What model.json and the checkpoint say about the run besides its weights: the
        scene, the field, the config and each decision a default made."""
        config, rule = self.config, self.losses_rule
        meta = {
            "neulf_core_version": __version__,
            "field": self.field_module.field_name,
            "field_config": self.field_module.field_config,
            "parameters": count_parameters(self.field_module),
            "slab": self.slab.to_dict(),
            "scene": {
                "root": str(Path(scene.root).absolute()), "kind": scene.kind, "fingerprint": scene.fingerprint(),
                "views": [v.name for v in scene.views], "train": [v.name for v in self.train_views],
                "held_out": [v.name for v in self.held_views], "scale": config.scale,
                # the photos read (folder and sizes): eval, render and resume read the same ones
                "images": scene.images_record(), "photo_sizes": {v.name: list(v.size) for v in scene.views},
                "cameras": {v.name: camera_record(v) for v in scene.views},  # (checked on resume and render)
                "photo_digests": self.photo_digests,  # (eval and resume notice photos replaced since)
                "mean_colour": mean_colour(self.train_rays).tolist(),
            },
            "train_config": asdict(config),
            # What the default decided, when train_config.consistency is None (None: not yet).
            "multiview_losses": None if self.losses_pending else bool(rule),
            **({"multiview_losses_rule": rule} if rule == rules.LOSSES_UNTIL_POSES_RIGHT else {}),
            **({"multiview_losses_until_step": self.losses_stopped_at} if self.losses_stopped_at is not None else {}),
            # How far neighbouring photos' exposures differ (stops), and whether that turns the
            # per-photo colour transform on by default (train_config.appearance says what ran).
            "exposure_difference_stops": round(self.exposure_stops, 4),
            "appearance_default": self.exposures_differ,
            "rig": _rig(self.train_views, config.scale),
        }
        if self.sweep_seconds:
            meta["sweep_seconds"] = round(self.sweep_seconds, 2)  # (of the budget: barely_trained_warning says it)
        if self.point_depth is not None:
            meta["point_depth"] = {"rays": int(self.point_depth[1].sum())}
            _emit(self.progress, event="stage", message=f"depth from the model's points: {meta['point_depth']['rays']} "
                  "keypoint rays pulled toward their points' depth (--no-point-depth turns it off)")
        if resumed and resumed.get("pose_check"):
            meta["pose_check"] = resumed["pose_check"]  # the verdict of the run being continued
        for made_once in ("field_restart", "far_off_check"):  # (the far-off check's record and verdict)
            if resumed and resumed.get(made_once):
                meta[made_once] = resumed[made_once]
        if resumed and resumed.get("members_rule"):
            meta["members_rule"] = resumed["members_rule"]
        switch = self.switch
        if switch and "batch_switch" not in meta.get("members_rule", {}):  # (decided while this run was stopped)
            meta["members_rule"] = {**meta.get("members_rule", {}), "count": switch.count, "split": "batch",
                                    "batch_switch": {"step": switch.step, "before": switch.before}}
        if config.poses_from:
            meta["poses_from"] = {"model": config.poses_from, "refined": self.fixed_poses is not None,
                                  **(self.fixed_poses.summary() if self.fixed_poses is not None else {})}
        meta.update(record or {})
        return meta

    def _set_budget(self) -> None:
        """The budget the loop runs to: the pass limit is a tighter step budget (the saved
        config keeps the one asked for); members by rule on a minutes budget (members.py) are
        decided from the step rate, and then this run -- the first member -- trains its share."""
        config = self.config
        rules.announce_pass_limit(self.progress, config, self.field_module.field_name, len(self.train_views),
                            self.step_limit, self.step)
        self.budget = (replace(config, steps=min(config.steps or self.step_limit, self.step_limit))
                       if self.step_limit else config)
        self.members_pending = config.members is None and "members_rule" not in self.meta
        if config.members is None and "members_rule" in self.meta:
            rule = self.meta["members_rule"]
            self.budget = _members_share(config, self.budget, rule["count"], rule.get("split", "steps"))

    # ------------------------------------------------------------------ training

    def budget_fraction(self) -> float:
        return self.budget.budget_fraction(self.step, self.elapsed)

    def train_until_done(self, should_stop) -> None:
        """Steps until the budget is spent or `should_stop()` says so (then status "cancelled")."""
        step_clock = StepClock()  # (time the process stood stopped, Ctrl-Z, is left out: clock.py)
        start_time = running_time()
        last_checkpoint = last_validation = start_time
        elapsed_before = self.elapsed
        self.first_step, self.rate_mark = self.step, self.elapsed
        self.members_step_seconds, self.last_elapsed = [], self.elapsed
        while self.budget_fraction() < 1.0:
            if should_stop is not None and should_stop():
                self.status = "cancelled"
                break
            if not self._take_step():
                continue
            step_clock.tick()
            now = running_time()
            self.elapsed = elapsed_before + (now - start_time)
            self._decide_at_measured_rate()
            if now - last_validation >= self.config.validate_seconds or self.budget_fraction() >= 1.0:
                self._validate()
                last_validation = running_time()
                start_time += last_validation - now  # validation time does not count against the budget
                now = last_validation
            else:
                _emit(self.progress, event="step", step=self.step, elapsed=self.elapsed, loss=self.loss_value,
                      fraction=self.budget_fraction(), lr=self.lr)
            if now - last_checkpoint >= self.config.checkpoint_seconds:
                self.save("training")
                last_checkpoint = running_time()

    def _take_step(self) -> bool:
        """One optimiser step on a random batch of rays; False where its loss was not finite
        (the step skipped: NonFiniteGuard)."""
        config, fraction = self.config, self.budget_fraction()
        rays_seen = self.step * self.batch + (self.switch.extra_rays(self.batch) if self.switch else 0)
        self.lr = _set_learning_rate(self.optimizer, self.preset, rays_seen, self.n_rays, fraction, self.guard.lr_scale)
        if hasattr(self.field_module, "set_training_progress"):
            self.field_module.set_training_progress(fraction)
        index = torch.randint(self.n_rays, (self.batch,), generator=self.generator).to(self.device)
        uvst, target = self.train_rays.batch(index, self.generator, config.pixel_jitter)
        view_index = rows_at(self.train_rays.view_index, index).long()
        pull = teacher_weight(fraction, len(self.train_views), strong=self.strong) if self.teacher is not None else 0.0
        depth_teacher = (rows_at(self.teacher[0], index), rows_at(self.teacher[1], index), pull) if pull > 0 else None
        depth_points = (rows_at(self.point_depth[0], index), rows_at(self.point_depth[1], index)) \
            if self.point_depth is not None else None
        self._look_at_poses(fraction)
        consistency = self.consistency
        corrected = self.poses if self.poses is not None else self.fixed_poses
        if corrected is not None:
            uvst = corrected(uvst, view_index)
            if consistency is not None:
                # The neighbours' rays leave from where the corrected cameras stand.
                consistency = (consistency[0], consistency[1].with_centres(corrected.corrected_centres()))
        loss, objective = _objective(self.field_module, uvst, target, view_index, self.appearance, consistency, config,
                                     depth_teacher, depth_points)
        self.optimizer.zero_grad(set_to_none=True)
        if not torch.isfinite(objective):
            self.guard.skip(self.step, self.progress)
            self.step += 1
            return False
        self.guard.passed()
        objective.backward()
        self.optimizer.step()
        self.step += 1
        self.loss_value = float(loss.detach())
        return True

    def _look_at_poses(self, fraction: float) -> None:
        """The pose check's record halfway, its verdict (which may stop the multi-view losses
        and the pull toward the points placed through the poses) and the far-off restart."""
        step, meta = self.step, self.meta
        if (self.pose_check_pending and poses_module.POSE_CHECK_STEP // 2 <= step < poses_module.POSE_CHECK_STEP
                and "halfway_degrees" not in meta.get("pose_check", {})):
            meta["pose_check"] = {"halfway_step": step, "halfway_degrees": round(self.poses.own_part_degrees(), 4)}
        if self.pose_check_pending and step >= pose_check.next_look_step(meta):
            self.poses, self.pose_check_pending = pose_check.verdict(self.poses, self.optimizer, meta, self.progress, step)
            self.poses_found_right = meta.get("pose_check", {}).get("refining") is False
            if self.consistency is not None and rules.losses_stop_at_pose_check(self.losses_rule, bool(self.config.appearance),
                                                                          self.poses_found_right):
                _stop_losses(meta, self.progress, step, len(self.train_views))
                self.consistency = None
            if self.poses is not None and not self.pose_check_pending and self.point_depth is not None:
                self.point_depth = None  # the poses are off: so are the points placed through them
                meta["point_depth"]["dropped_at_step"] = step
                _emit(self.progress, event="stage", message="the poses are off, and so are the points placed through "
                      "them: no longer pulling toward their depth")
        if self.restart_pending and step >= poses_module.POSE_CHECK_STEP:
            self.restart_pending = False
            if self.poses is not None:
                pose_check.restart_for_far_off_poses(self.field_module, self.optimizer, self.poses, meta, self.progress, step,
                                           self.config.seed, fraction=fraction, n_train_views=len(self.train_views))
        if self.poses is not None:
            self.poses.set_training_progress(fraction)

    def _decide_at_measured_rate(self) -> None:
        """The decisions a minutes budget takes at the step rate the run measures: the members
        rule (MEMBERS_RATE_DECISION_STEP) and the default's multi-view losses (LOSSES_DECISION_STEP)."""
        steps_taken, elapsed = self.step - self.first_step, self.elapsed
        if self.losses_pending and steps_taken == rules.LOSSES_RATE_FROM_STEP:
            self.rate_mark = elapsed
        if self.members_pending and steps_taken > MEMBERS_RATE_FROM_STEP:
            self.members_step_seconds.append(elapsed - self.last_elapsed)
        self.last_elapsed = elapsed
        if self.members_pending and steps_taken >= MEMBERS_RATE_DECISION_STEP:
            self.members_pending = False
            self._decide_members()
        if self.losses_pending and steps_taken >= rules.LOSSES_DECISION_STEP:
            self.losses_pending = False
            self.losses_rule, self.consistency = _decide_losses_at_measured_rate(
                self.slab, self.train_views, self.config, elapsed - self.rate_mark, self.device, self.meta, self.progress)
            if self.consistency is not None and rules.losses_stop_at_pose_check(self.losses_rule, bool(self.config.appearance),
                                                                          self.poses_found_right):
                # (the check came before: a resumed run, or a later member's first one)
                _stop_losses(self.meta, self.progress, self.step, len(self.train_views))
                self.consistency = None

    def _decide_members(self) -> None:
        config = self.config
        self.budget = _decide_members_at_measured_rate(config, self.budget, self.batch, self.n_rays,
                                                       self.members_step_seconds, self.meta, self.progress,
                                                       self.device.type, self.step, self.elapsed)
        self.switch = BatchSwitch.of(self.meta["members_rule"])
        if self.switch:  # from the next step on, this member's share of the batch
            self.batch = self.switch.batch
            if self.step_limit:
                self.step_limit = self.switch.steps_for(self.step_limit, self.batch)
                self.budget = replace(self.budget, steps=min(config.steps or self.step_limit, self.step_limit))
                rules.announce_pass_limit(self.progress, config, self.field_module.field_name, len(self.train_views),
                                    self.step_limit, self.step)

    def _validate(self) -> None:
        self.val = ray_sample_psnr(self.field_module, self.val_rays) if self.val_rays is not None else None
        record = {"step": self.step, "elapsed": round(self.elapsed, 2), "loss": self.loss_value,
                  "train_psnr": -10 * math.log10(max(self.loss_value, 1e-12)), "val_psnr": self.val, "lr": self.lr}
        self.history.append(record)
        _emit(self.progress, event="validate", fraction=self.budget_fraction(), **record)

    def save(self, status: str, before_fill: dict | None = None) -> None:
        """A checkpoint of the run as it is (atomic: checkpoint.save_checkpoint); `before_fill`:
        the weights a resumed run trains on, where the saved ones are filled for rendering."""
        appearance, poses = self.appearance, self.poses
        payload = {**self.meta, "state_dict": self.field_module.state_dict(), "optimizer": self.optimizer.state_dict(),
                   **({TRAINING_STATE_KEY: before_fill} if before_fill is not None else {}),
                   "appearance": appearance.state_dict() if appearance is not None else None,
                   "appearance_linear_light": appearance.linear_light if appearance is not None else None,
                   "poses": poses.state_dict() if poses is not None else None,
                   "rng": {"torch": torch.get_rng_state(), "generator": self.generator.get_state()},
                   "progress": {"step": self.step, "elapsed": self.elapsed, "status": status, "val_psnr": self.val,
                                "history": self.history}}
        path = save_checkpoint(self.model_dir, payload)
        _emit(self.progress, event="checkpoint", path=str(path), step=self.step)

    # ------------------------------------------------------------------ the end

    def finish(self) -> TrainResult:
        """The checks a budget ended before, the record of the corrections, the fill of unseen
        texels, and the last checkpoint."""
        meta, progress, status = self.meta, self.progress, self.status
        self.guard.report(progress)
        if self.pose_check_pending and status == "finished":  # the budget ended before the check (a short --minutes)
            self.poses, self.pose_check_pending = pose_check.verdict(self.poses, self.optimizer, meta, progress, self.step,
                                                              last=True)
        if self.losses_pending and status == "finished":  # ... or before the rate was measured: too short for them
            meta["multiview_losses"] = False
        if self.poses is not None and not self.pose_check_pending:  # (stopped before the check: provisional, not reported)
            meta["pose_corrections"] = self.poses.summary()
            _emit(progress, event="poses", **meta["pose_corrections"])
            meta["pose_corrections"]["depth_like"] = DEPTH_LIKE_GAUGE  # (the study re-runs rows refined otherwise)
        # The fill is for rendering: training resumes from the weights before it, since texels
        # unseen now may be read once the geometry moves (a paused run then trains on exactly
        # as an uninterrupted one: a cancel, or the better of two starts' pause at its choice).
        seconds, before_fill = _fill_unseen(self.field_module, self.train_rays) if self.step > 0 else (0.0, None)
        self.elapsed += seconds
        self.save(status, before_fill)
        _emit(progress, event=status, step=self.step, elapsed=self.elapsed, val_psnr=self.val,
              model_dir=str(self.model_dir))
        return TrainResult(self.model_dir, status, self.step, self.elapsed, self.val, self.history)


def _fill_unseen(field_module, train_rays: RaySet, chunk: int = 1 << 15) -> tuple[float, dict | None]:
    """Texels no training ray reads take their seen neighbours' features (fields that have
    texels; DisparityField.fill_unseen_texels).  Returns the seconds it took, part of the
    training time, and the weights before the fill (None where the field has no texels)."""
    if not hasattr(field_module, "fill_unseen_texels"):
        return 0.0, None
    started = time.monotonic()
    before = {k: v.detach().clone() for k, v in field_module.state_dict().items()}
    field_module.fill_unseen_texels(train_rays.uvst[i:i + chunk].float() for i in range(0, len(train_rays), chunk))
    return time.monotonic() - started, before


def _decide_losses_at_measured_rate(slab: Slab, train_views, config: TrainConfig, seconds: float, device, meta: dict,
                                    progress):
    """The default's multi-view losses for a minutes budget, once the first steps have been
    timed (`seconds` for the steps LOSSES_RATE_FROM_STEP to LOSSES_DECISION_STEP): the rule's
    verdict and the consistency inputs from now on, or None.  Recorded in the model's metadata."""
    steps_per_minute = rules.measured_steps_per_minute(seconds)
    rule = rules.default_consistency(slab, train_views, config, steps_per_minute)
    meta["multiview_losses"] = bool(rule)
    if rule == rules.LOSSES_UNTIL_POSES_RIGHT:
        meta["multiview_losses_rule"] = rule
    meta["losses_steps_per_minute"] = round(steps_per_minute)
    if not rule:
        return rule, None
    rules.announce_default_losses(progress, len(train_views))
    return rule, _consistency_inputs(train_views, slab, config, device)


def _stop_losses(meta: dict, progress, step: int, n_train_views: int) -> None:
    """Record and say that training goes on without the losses from `step`."""
    meta["multiview_losses_until_step"] = step
    _emit(progress, event="stage", message=f"{n_train_views} photos whose poses agree: training on without the "
          "multi-view losses, which pay with up to 10 photos or where poses or colours are refined (docs/STABILITY.md)")


def _members_share(config: TrainConfig, budget: TrainConfig, count: int, split: str = "steps") -> TrainConfig:
    """The first member's share of the budget once the rule has decided on `count` members
    (a pass limit stays each member's own)."""
    if count <= 1:
        return budget
    steps, minutes, _ = member_budget(config, count, 1, split)
    return replace(budget, minutes=minutes, steps=min(budget.steps, steps) if steps else budget.steps)


@dataclass(frozen=True)
class BatchSwitch:
    """A first member whose minutes budget decided on members that split the batch (members.py):
    it trained `step` steps of `before` rays, and goes on with 1/`count` of them a step.  Its
    pass limit still counts rays, and so does the paper's schedule."""
    step: int
    before: int
    count: int

    @classmethod
    def of(cls, rule: dict | None) -> "BatchSwitch | None":
        switch = (rule or {}).get("batch_switch")
        return cls(int(switch["step"]), int(switch["before"]), int(rule["count"])) if switch else None

    @property
    def batch(self) -> int:
        return self.before // self.count

    def extra_rays(self, batch: int) -> int:
        """The rays the steps before the switch saw beyond `batch` a step."""
        return self.step * (self.before - batch)

    def steps_for(self, step_limit: int, batch: int) -> int:
        """The pass limit of `step_limit` steps of the whole batch, in steps of this member's."""
        return self.step + math.ceil(max(0, step_limit - self.step) * self.before / batch)


def _switch_on_resume(asked: TrainConfig, resumed: dict | None, saved_batch: int) -> BatchSwitch | None:
    """A member resumed as one of members that split the batch (`asked`, from members.py) from a
    checkpoint that trained with the whole batch and recorded no switch: the rule decided while
    it was stopped (the first member killed between its decision and its next checkpoint, or a
    second start stopped before its own decision).  It goes on with its share from here."""
    if resumed is None or (asked.members or 1) < 2 or asked.members_split != "batch" or not asked.batch_size:
        return None
    if asked.batch_size >= saved_batch:
        return None  # (it trained with its share from the start)
    return BatchSwitch(int(resumed["progress"]["step"]), saved_batch, int(asked.members))


def _decide_members_at_measured_rate(config: TrainConfig, budget: TrainConfig, batch: int, n_rays: int,
                                     step_seconds: list[float], meta: dict, progress, device_type: str,
                                     step: int, elapsed: float) -> TrainConfig:
    """The members rule on a minutes budget: the passes the budget makes at the rate of the
    steps after MEMBERS_RATE_FROM_STEP up to MEMBERS_RATE_DECISION_STEP decide the count
    (members.py).  Their median time, since a shared machine's hiccups land on a few steps.
    Members that split the batch (the default on a CPU, members.default_split): this one goes on
    with its share of the rays a step (meta's `batch_switch`, BatchSwitch).  A budget so short
    that this member has used its share by `elapsed` seconds stays one member (share_spent)."""
    rate = 60.0 / max(float(np.median(step_seconds)), 1e-9)
    passes = rules.budget_passes(config, batch, n_rays, rate)
    split = member_split(config, None, device_type)
    count = members_by_rule(passes, split)
    spent = share_spent(config.minutes, count, elapsed)
    if spent:
        count = 1
        _emit(progress, event="stage", verdict="members",
              message=f"one member: the budget passes over the training pixels {passes:.0f} times, but its first "
                      f"{elapsed:.0f} s were more than a member's share of the minutes (give more minutes for two)")
    split = split if count > 1 else "steps"
    meta["members_rule"] = {"count": count, "passes": round(passes, 1), "steps_per_minute": round(rate, 1),
                            **({"split": split} if count > 1 else {}), **({"share_spent": True} if spent else {})}
    if split == "batch":
        meta["members_rule"]["batch_switch"] = {"step": step, "before": batch}
    _emit(progress, event="members", count=count, passes=round(passes, 1), split=split)
    if count > 1:
        _emit(progress, event="stage", verdict="members",
              message=f"{count} members: the budget passes over the training pixels {passes:.0f} times at this "
                      f"pace (at least {passes_for_members(split):.0f}; --members 1 for one){share_words(split, count)}")
    return _members_share(config, budget, count, split)


def _consistency_inputs(train_views, slab: Slab, config: TrainConfig, device):
    if len(train_views) < 2:
        raise NeulfError("the multi-view losses need at least two training views; train with consistency off.")
    neighbours = camera_neighbours(np.stack([v.center for v in train_views]), slab, config.neighbours)
    return SlabGeometry(slab, device), neighbours.to(device)


def _teacher_wanted(train_views, config: TrainConfig, preset, resumed) -> bool:
    """Whether this run sweeps: the teacher on, two photos at least, and a resumed run still in
    the part of the budget the teacher acts in."""
    wanted = preset.teacher if config.teacher is None else config.teacher
    if not wanted or len(train_views) < 2:
        return False
    return not (resumed and config.budget_fraction(resumed["progress"]["step"], resumed["progress"]["elapsed"])
                >= teacher_fade(len(train_views)))


def _teacher_inputs(train_views, slab: Slab, config: TrainConfig, preset, device, resumed, progress, masks=None,
                    photos=None):
    """The plane sweep's depth per training ray (teacher.py), and the seconds it took; None
    when off (_teacher_wanted).  `masks`: build_rayset's, each view's representable pixels;
    `photos`: the photos at the sweep's scale, read with the training ones."""
    if not _teacher_wanted(train_views, config, preset, resumed):
        return None, 0.0
    started = time.monotonic()
    targets = sweep_depth_targets(train_views, slab, config.scale, device,
                                  on_view=lambda i, n, v: _emit(progress, event="loading", message=f"sweep depth of {v.name}",
                                                                 done=i + 1, total=n), representable=masks, photos=photos)
    return targets, (0.0 if resumed else time.monotonic() - started)


def _point_depth_inputs(train_views, slab: Slab, config: TrainConfig, preset, device, poses_corrected: bool,
                        masks=None):
    """The SfM points' depth per training ray (point_depth.py) and its mask, on `device`; None
    when off or where no training ray sees a point the training photos triangulate (model.json
    records how many rays have one: "point_depth").
    Off by default where the poses are refined from the start (`--refine-poses`, or a resumed
    run whose pose check kept refining) or trained with a first member's corrections
    (`poses_corrected`): the points are placed through the poses as the model gives them, and
    where those are off, so are the points' depths, which would hold the field against the
    corrections.  The trainer drops them too where the pose check finds the poses off: the
    stability study's CanClip, 6 photos with 0.25 degrees of noise, 29.64 -> 28.99 dB with the
    points kept on (docs/STABILITY.md, forty-fifth session)."""
    wanted = preset.point_depth if config.point_depth is None else config.point_depth
    if config.point_depth is None and (config.refine_poses is True or poses_corrected):
        wanted = False
    targets = point_depth_targets(train_views, slab, config.scale, masks) if wanted else None
    return None if targets is None else (targets[0].to(device), targets[1].to(device))


def _objective(field_module, uvst, target, view_index, appearance, consistency, config: TrainConfig, depth_teacher=None,
               depth_points=None):
    """(photometric loss L_p, everything minimised): L_p + regularisers + 0.5 L_mp + 0.1 L_d
    (+ the fading pull toward the plane sweep's depth, + the pull toward the SfM points')."""
    rgb, unit = field_module(uvst)
    seen = appearance(rgb, view_index) if appearance is not None else rgb
    loss = torch.mean((seen - target) ** 2)
    objective = loss + field_module.regularisation() if hasattr(field_module, "regularisation") else loss
    if appearance is not None:
        objective = objective + appearance.regularisation()
    if consistency is not None:
        geometry, neighbours = consistency
        m = config.consistency_rays
        # The photo's colour is compared with the neighbours' colours as photo k would see them.
        as_seen = (lambda colours, views: appearance(colours, views)) if appearance is not None else None
        loss_mp, loss_d = multiview_losses(field_module, geometry, neighbours, uvst[:m], target[:m], unit[:m],
                                           view_index[:m], as_seen)
        objective = objective + MULTIVIEW_WEIGHT * loss_mp + DEPTH_WEIGHT * loss_d
    if depth_teacher is not None:
        unit_target, confidence, weight = depth_teacher
        objective = objective + weight * teacher_loss(unit, unit_target, confidence)
    if depth_points is not None:
        objective = objective + point_depth_loss(unit, *depth_points)
    return loss, objective


def _rig(views, scale: float) -> dict:
    """Camera centres and a representative pinhole for camera paths (path_camera_view)."""
    camera = path_camera_view(views).scaled_camera(scale)
    return {"centres": [v.center.tolist() for v in views], "K": camera.calibration_matrix().tolist(),
            "width": int(camera.width), "height": int(camera.height)}


def has_baseline(views, slab: Slab) -> bool:
    """Whether the training cameras stand apart (paths.rig_has_baseline)."""
    return rig_has_baseline(slab, np.stack([view.center for view in views]))


def _say_blank_photos(views, blank: list[int], progress) -> None:
    """Name the training photos that are one flat colour, once a training call."""
    if not blank:
        return
    names = [views[i].name for i in blank]
    shown = ", ".join(names[:3]) + (" ..." if len(names) > 3 else "")
    message = (f"{len(names)} training photo(s) are almost one flat colour ({shown}: a lens cap, a blank frame?): the "
               "light field learns what they show from where they stand, which spoils the views near them; hold them "
               "out of training with --exclude (which names every view held out)")
    kept("blank photos warning", ",".join(names), lambda: _emit(progress, event="warning", views=names, message=message))


def _say_wide_views(slab: Slab, views, scale: float, progress) -> None:
    """Name the training photos that see far wider than the others (slab.wide_views), once a
    training call (the auto preset's candidates and a model's members ask again).  A note, not
    a warning: on a real capture such a photo helps (benchmarks/wide_photo.py, below)."""
    wide = wide_views(slab, views, scale)
    if not wide:
        return
    shown = ", ".join(f"{name} ({ratio:.1f}x)" for name, ratio in wide[:3]) + (" ..." if len(wide) > 3 else "")
    # CanClip with every photo cropped but one (2.2x and 3.4x as wide), 1000 steps, two seeds,
    # AMD EPYC (docs/BENCHMARKS.md, "One photo far wider than the others"): the held-out views
    # scored 31.29 / 30.03 dB with it, 30.36 / 29.73 with it held out, and a slab spanning only
    # the other photos (its rays outside left out) 31.01 at 2.2x.
    message = (f"{len(wide)} photo(s) see more than twice as wide as the median photo on the light slab: {shown} (a "
               "wider lens, a fisheye, or a camera turned away from the others). The light field spans what every "
               "photo sees, so the views beside the others' edges gain from them (one photo 2.2 times as wide as the "
               "others: held-out views +0.9 dB over holding it out); where one is a mistake (another scene, a "
               "fisheye read as a pinhole), hold it out with --exclude, which names every view held out.")
    kept("wide views note", ",".join(name for name, _ in wide),
         lambda: _emit(progress, event="stage", views=[name for name, _ in wide], message=message))


def path_camera_view(views):
    """The training view whose pinhole a camera path takes (the CLI's video; Blender's spiral takes
    the scene camera's lens): of the photos' most common size (portrait or landscape included),
    the one of median focal length.
    (The first view's had made a portrait video of a landscape capture with one portrait photo
    first, and a fisheye's focal length a 94° pinhole.)"""
    size, _ = Counter(view.size for view in views).most_common(1)[0]
    alike = sorted((view for view in views if view.size == size), key=lambda view: float(view.camera.focal_length_x))
    return alike[(len(alike) - 1) // 2]


def config_for_resume(payload: dict, config: TrainConfig, scene: Scene) -> TrainConfig:
    """Resuming keeps what defines the model (preset, split, scale, slab); the budget and the
    checkpoint interval may change."""
    saved = payload["scene"]
    if saved["fingerprint"] != scene.fingerprint():
        raise NeulfError(other_reconstruction(saved, scene, "resume it"))
    other = [(v, trained_photo_size(v, saved)) for v in scene.views if trained_photo_size(v, saved)]
    if other:
        view, (width, height) = other[0]
        raise NeulfError(
            f"the model trained on photos of another size ({view.name}: {width}x{height}, read now at "
            f"{view.size[0]}x{view.size[1]}{' from ' + str(scene.images_dir) if scene.images_dir else ''}); resume it "
            f"with --images naming the folder it trained on ({saved.get('images') or 'see model.json'}), or train a new "
            "model into another --out folder.")
    changed = changed_cameras(scene.views, saved)
    if changed:
        raise NeulfError(
            f"{len(changed)} view(s) ({', '.join(changed[:3])}{' ...' if len(changed) > 3 else ''}) have another camera "
            "(focal length, principal point, distortion or rotation) than the model trained with: resume it with the "
            "scene it trained on, or train a new model into another --out folder.")
    previous = TrainConfig(**{k: v for k, v in payload["train_config"].items() if k in TrainConfig.__dataclass_fields__})
    if "point_depth" not in payload["train_config"]:
        previous.point_depth = False  # trained before the SfM points' pull: resumes as it began
    previous.steps, previous.minutes = config.steps, config.minutes
    previous.checkpoint_seconds, previous.validate_seconds = config.checkpoint_seconds, config.validate_seconds
    previous.device = config.device
    previous.members = config.members  # a member's count comes with its share of the budget (members.py)
    previous.poses_from = config.poses_from  # ... and the first member's folder, wherever it now is
    if config.max_passes is not None:  # --max-passes 0 lets a model that stopped at the limit train on
        previous.max_passes = config.max_passes
    return previous


def _restore_rng(state: dict | None, generator: torch.Generator) -> None:
    if not state:
        return
    torch.set_rng_state(state["torch"])
    generator.set_state(state["generator"])

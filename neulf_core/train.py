"""Training a light field: random ray batches, photometric loss, checkpoints, resume, cancel.

`train(...)` is the one entry point used by the CLI, the benchmark and the Blender worker.
It reports through a `progress` callback (plain dicts; see `progress.py` for the bar and
JSON-lines printers) and stops early, after saving, when `should_stop()` returns True.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from . import __version__
from .appearance import ViewAppearance, appearance_by_default, exposure_difference, photo_exposures
from .checkpoint import (METADATA_NAME, TRAINING_STATE_KEY, checkpoint_path, load_checkpoint, remove_stale_temporaries,
                         save_checkpoint)
from .consistency import SlabGeometry, camera_neighbours, multiview_losses
from .dataset import RaySet, kept_rayset, mean_colour
from .device import describe_device, keep_freed_cpu_memory, pick_device
from .errors import NeulfError
from .fields import build_field, count_parameters, make_config
from .fields.disparity import DisparityConfig, slab_geometry, texture_size_for
from .lock import training_lock
from .memo import kept, kept_while_training
from .members import RATE_DECISION_STEP as MEMBERS_RATE_DECISION_STEP, RATE_FROM_STEP as MEMBERS_RATE_FROM_STEP, \
    member_budget, member_split, members_by_rule, passes_for_members, share_spent, share_words
from . import poses as poses_module
from .poses import DEPTH_LIKE_GAUGE, POSE_CHECK_STEP, POSE_SECOND_LOOK_STEP, PoseRefinement
from .presets import APPEARANCE_ADAM_BETA2, APPEARANCE_GEOMETRY, DEFAULT_PRESET, get_preset
from .scene import Scene, load_scene, scaled_size, split_views
from .slab import Slab, fit_slab
from .teacher import strong_pull, sweep_depth_targets, sweep_photo_scale, teacher_fade, teacher_loss, teacher_weight
from .point_depth import point_depth_loss, point_depth_targets

VALIDATION_RAYS = 1 << 16
# The paper's loss weights: L = L_p + 0.5 L_mp + 0.1 L_d.
MULTIVIEW_WEIGHT, DEPTH_WEIGHT = 0.5, 0.1
# Adam's step for the pose corrections (radians, and shares of the camera spacing), decayed
# with the field's learning rate; they move from the first step (poses.py says in which part
# first).
POSE_LR = 3e-4

# Poses far off on a shallow scene: at the pose check's step, where the corrections found so
# far (the check's statistic, PoseRefinement.own_part_degrees) reach FAR_OFF_POSE_DEGREES and
# the scene is not deep (Slab.is_deep), the field starts again from a new random start with
# its geometry (planes, and depth layers where on) FAR_OFF_GEOMETRY_TV times smoother, while the corrections keep what they
# have found.  Why: a field whose geometry may vary from camera to camera bends each photo's
# depth until the photo fits where its wrong pose puts it; the corrections stall (CanClip, 2
# degrees of noise, seed 0: 0.39 degrees left from step 500 on, and with the field frozen a
# training camera's pose fitted to its photo did not move) and the field settles with the
# scene's depth off relative to the cameras.  Smoother geometry keeps the depth where the
# photos agree, so a new camera -- here the held-out ones, whose poses are exact -- sees the
# scene where it is: they fit the restarted field within 0.05-0.25 degrees instead of
# 0.12-0.62.  What it gains is that frame, not sharpness: with each held-out camera's pose
# fitted to its photo first, the two score alike (seeds 0 / 1: 32.26 / 32.73 against 32.74 /
# 32.36 dB).  Smoother from the first step in every run cost right poses on the deep
# synthetic scene; from the check on without the restart, the bent field kept the loss.  The
# check's first 100 steps are the poses' largest moves.  Study, three seeds at 1000 steps
# (docs/STABILITY.md, "far-off poses"): CanClip 0.5 / 1 / 2 degrees 33.23 / 30.12 / 25.12 ->
# 33.25 / 31.46 / 28.69 dB, the spread at 2 degrees 1.56 -> 0.20 dB; Statue 1 / 2 degrees
# -0.27 / +0.71 dB, HCI +0.51 / +2.40 (three seeds each, outside the study).
# Not on deep scenes, whose geometry must vary with the viewpoint (the synthetic scene at
# 0.5 / 1 / 2 degrees: -0.68 / -0.48 / +0.46 dB), nor under 0.4 degrees (0.25 degrees of
# noise measures 0.22-0.25), where the refinement already recovers nearly everything and
# the smoother geometry cost the synthetic scene 0.54 dB.
# Since the fifty-fifth session the bar is FAR_OFF_POSE_DEGREES only with at most
# COARSE_TO_FINE_MAX_VIEWS photos (the sparse captures, which also train coarse to fine) or a
# field whose first steps nothing held, and MANY_PHOTOS_FAR_OFF_POSE_DEGREES where more photos
# trained with the SfM points' depth pulling until the check (the default's pose check;
# point_depth.py): there the points and each photo's neighbours hold the field's depth, the
# corrections do not stall at moderate error, and the restart only threw away the first
# steps and smoothed depth the photos agreed on.  1000 steps, the study's jobs and noise
# (/tmp/w/resid.py, not committed; residual: the corrections' median distance from what the
# noise needs, in its observable part):
# - CanClip's 26 photos, 0.5 degrees (statistic 0.45-0.47): restarted 34.21 dB, range 0.83
#   over seeds 0-5, against 34.66, range 0.35, trained on; residual 0.083-0.089 against
#   0.082-0.086 degrees; 0.75 degrees 33.32 against 33.56 (seeds 0-2); at 1 degree (0.90) the
#   restart wins, 32.16 against 31.98 with a range of 1.02; CanClip's 20 photos at 0.5 degrees
#   (0.46-0.47) 29.96 against 30.09, residual alike (0.10); HCI's 70 at 0.5 degrees 41.65
#   against 41.85;
# - the same 26 photos at 0.5 degrees with `--refine-poses` (no points from the first step):
#   restarted 34.38, range 0.09, trained on 34.16, range 1.23;
# - CanClip's 13 photos, 0.5 degrees (0.52): restarted 27.22 against 27.09, residual 0.059-0.067
#   against 0.079-0.083; its 6 at 0.25 degrees (0.51-0.53): 29.15, range 0.10 (seeds 0-5),
#   against 29.20, range 0.25, residual 0.054-0.059 against 0.080-0.098.  With few photos the
#   restart helps the corrections find the poses, so there the bar stays.
FAR_OFF_POSE_DEGREES = 0.4
MANY_PHOTOS_FAR_OFF_POSE_DEGREES = 0.6
FAR_OFF_GEOMETRY_TV = 10.0
# Where the bar is MANY_PHOTOS_FAR_OFF_POSE_DEGREES (more photos, the points held their first
# steps), only the geometry starts again: the texture and the colour decoder keep what the first
# steps learned, which the photos' agreement made usable, and the new start's draw decides less.
# With fewer photos that texture is not: everything starts again.  Measured (fifty-sixth session,
# `python benchmarks/study_probe.py --scene canclip --pose-degrees 1 --seeds 0-7 --patch ...`,
# 1000 steps): CanClip's 26 photos at 1 degree 32.11 +- 0.27 (sd) -> 32.54 +- 0.21 dB, with the
# held-out poses fitted 35.59 -> 35.57 (seeds 0-2); at 2 degrees (seeds 0-2) 29.45 -> 29.80 dB,
# fitted 34.54 -> 34.99, its range 0.25 -> 0.12.  CanClip's 6 photos at 1 degree lost 0.92 dB with
# the texture kept (22.98 -> 22.06), at 0.5 degrees level (26.00 -> 26.00).
# The geometry is the depth layers too (DisparityField.GEOMETRY_PARAMETERS): since the
# fifty-seventh session they start again with the planes, and their smoothness rises with the
# planes' (DisparityField.smooth_geometry).  Kept, they carried what they had learned under the
# far-off poses: CanClip's 26 photos at 1 degree, seed 0, drew the pliers' tip at the
# background's depth in the held-out img009 (-1.66 dB there).  Same probe, seeds 0-7: 32.54 +-
# 0.215 (sd) -> 32.77 +- 0.09 dB; 2 degrees (seeds 0-3) 29.80 -> 29.81; the layers started
# again alone 32.71 +- 0.15 (seeds 0-3), smoother alone 32.63 +- 0.22.
# ... and with at most FEW_PHOTOS_TEXTURE_MAX_VIEWS photos, the restarted field's texture
# sharpens coarse to fine: its finer levels fade in over the next FEW_PHOTOS_TEXTURE_COARSE_TO_FINE
# of the budget (DisparityConfig.texture_coarse_to_fine), as BARF fades in its encoding.  With
# few photos the refinement did not find the poses against a sharp texture (CanClip's 6 photos,
# 1 degree: each camera's own turn 0.73-0.77 degrees left of about 0.95); against the blurred
# one it does (0.21-0.27, fading from the first step on a patched copy).  Study, three seeds
# at 1000 steps, from the restart on (docs/STABILITY.md, twenty-first session): held-out PSNR
# with their poses fitted at 0.25 / 0.5 / 1 / 2 degrees 33.10 / 31.90 / 26.94 / 23.80 ->
# 32.73 / 32.51 / 31.62 / 23.88 dB, as given 28.73 / 25.35 / 20.85 / 17.38 -> 29.83 / 24.85 /
# 21.95 / 18.28.  From the first step it cost right poses 0.7 dB, and all 26 photos at 1 degree
# 0.7 dB fitted, hence only here.
FEW_PHOTOS_TEXTURE_MAX_VIEWS = 6
FEW_PHOTOS_TEXTURE_COARSE_TO_FINE = 0.6


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
                                        # pixels at least 60 times, else 1 -- or a resumed model's count);
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


def _emit(progress, **event):
    if progress is not None:
        progress(event)


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


# Depth layers (DisparityConfig.geometry_layers) by default where they were measured to help:
# scenes of a shallow depth range -- HCI (far/near 2.6 in slab units) +1.2 dB and a third less
# disparity error, Statue (2.0) +0.45 dB, CanClip (1.7) +0.08 dB -- but not deep ones
# (Slab.is_deep), where layers spread over the whole range sit far apart: fern (4.6)
# -0.25 dB, the synthetic scene (3.3) -0.5 dB (docs/DEPTH.md).
# With few photos the layers overfit: CanClip at 240x135, 1000 steps, 3 seeds, with / without
# layers: 26 views +0.15 dB, 20 views -0.03, 13 views -0.47, 6 views -1.03 (docs/STABILITY.md).
# From 18 views on they help again where the rig is dense: 18 views, with / without, HCI at
# 256x256 +1.42 dB (3 seeds), CanClip +0.08 dB (2 seeds); nothing was measured from 14 to 17.
DEFAULT_DEPTH_LAYERS = 8
DEPTH_LAYERS_MIN_VIEWS = 18


def default_depth_layers(slab: Slab, n_train_views: int) -> int:
    return 0 if slab.is_deep or n_train_views < DEPTH_LAYERS_MIN_VIEWS else DEFAULT_DEPTH_LAYERS


# A back surface (DisparityConfig.back_surface) for deep scenes.  It costs about 1.4 times the
# time a training step and 1.5 times a render.  AMD EPYC, fiftieth session (docs/STABILITY.md):
# the stability study's synthetic configurations (far/near 3.3; 1000 steps, three seeds) +0.02
# to +0.36 dB on 14 of 17; at the product's 1.5 minutes, side by side: fern (4.6) +0.02 ± 0.04
# dB over four seeds, Statue (2.0) +0.48 ± 0.12 over three, CanClip (1.7) -0.13 ± 0.05 over two;
# at 45 s HCI (2.6) -0.51 (one seed).  No depth-range rule parts Statue from HCI, so shallow
# captures keep one surface unless asked (`train --back-surface`).
def default_back_surface(slab: Slab) -> bool:
    return slab.is_deep


# The paper's multi-view losses (consistency.py) cost time per step (~1.4 times with
# CONSISTENCY_RAYS), so they are on by default only where they were measured to pay for it at
# equal training time (two runs side by side, seeds 0 / 1, the fast field;
# `benchmarks/stability.py`'s losses study and docs/DEPTH.md): deep scenes with up to 20
# photos.  At 1 minute on a 2-core CPU (2048 rays then): the project's synthetic scene with 4 /
# 7 / 14 training views +1.10 / +1.07 / +0.39 dB, fern at 252x189 with 4 / 8 / 17 views +0.75 /
# +0.58 / +0.19 dB; the synthetic scene on a denser 8x8 rig with 20 / 28 views, 512 rays,
# -0.09 / +0.13 and -0.28 / -0.25 dB (56 views, 2048 rays: -0.07 / -0.33).  The gains grow
# with the budget: at the Blender panel's 5 minutes (seed 0, 2048 rays) 14 views +0.94 dB,
# fern's 17 +0.69, 20 views +0.28, 28 views +0.02 -- without the losses, deep scenes overfit
# as training goes on.  With many photos the field's shared texture already makes neighbouring
# rays agree; with few, the losses tie each ray's depth to the other photos.
# With the coarser geometry planes for every capture (forty-seventh session) they stopped paying
# in PSNR with 14-20 photos and right poses: at 1 minute, four seeds, the synthetic scene's 14
# -0.07 ± 0.08 dB (standard error), fern's 17 -0.13 ± 0.06; fern's 17 at the Blender panel's 5
# minutes -0.12 / -0.15 (seeds 0 / 1, `benchmarks/side_by_side.py`, docs/losses_fern_5min.csv).
# But they hold the field together where the photos disagree: the stability study without them
# for 14 photos (1000 steps, three seeds) lost 1.2 / 2.2 / 6.2 dB at 0.5° / 1° / 2° of pose
# noise (0.2 / 0.4 / 2.6 with the held-out poses fitted) and 5.8 dB on exposure-jittered photos
# as rendered (docs/STABILITY.md, forty-seventh session).  So the limit stays at 20.
CONSISTENCY_MAX_VIEWS = 20
# With 11 to 20 photos they stop where the pose check finds the poses right (and no colour
# transform per photo is learned): with the texture-feature blend of the back surface
# (fifty-second session) the synthetic scene's 14 right-posed photos lost with the losses at
# every budget measured, 1 minute, eight seeds, 31.18 off against 30.80 on (-0.38 dB); 5
# minutes, seeds 0 / 1, -0.27 dB; fern's 17 at 5 minutes -0.12 / -0.15 (forty-seventh).  The
# shiny scene's 14 gain from them (1000 steps +0.16 dB, 1 minute +0.14), and with this rule at
# 1 minute the synthetic 14 came out +0.18 dB and shiny -0.04 against the losses throughout
# (eight seeds each; fifty-third session, docs/STABILITY.md).  Where the photos disagree they hold the
# frame (above), so they train from the start and stay on where the check keeps refining the
# poses, where no check ran (--refine-poses / --no-refine-poses) and where exposures differ.
# Starting them only after the check instead cost 0.91 dB at 2 degrees of pose noise (27.94 ->
# 27.03, 1000 steps, three seeds; fifty-third session), and leaving them off with
# --no-refine-poses 0.5-1.2 dB under pose noise.  Up to 10 photos they gained with right poses
# too: fern's 8 / 4 +0.26 / +0.80 dB, the synthetic scene's 7 / 4 +0.13 / +1.29 (four seeds,
# 1 minute).
CONSISTENCY_ALWAYS_MAX_VIEWS = 10
LOSSES_UNTIL_POSES_RIGHT = "until-poses-right"  # TrainConfig.consistency: the rule's verdict for 11 to 20 photos
# ... and only when the budget passes over every training pixel often enough for the field
# to start overfitting what the losses hold.  Fern's 17 views at 504x378, seed 0, off / on side
# by side (PSNR, LPIPS): 1.5 minutes (~8 passes as counted below) 21.35 / 21.26 dB, LPIPS
# 0.267 / 0.296 (seed 1: -0.10 / +0.02 dB); 3 minutes (~15 passes) 21.25 / 21.39 dB, 0.262 /
# 0.272; 5 minutes (~25 passes) 21.01 / 21.46 dB, 0.266 / 0.256 -- without the losses fern
# gets worse as training goes on.  At 252x189 for 1 minute (~20 passes) +0.23 dB.  A minutes
# budget's passes depend on the machine, so they are counted at the rate the run measures:
# it trains its first LOSSES_DECISION_STEP steps without the losses, times the ones after
# LOSSES_RATE_FROM_STEP (the first warm up), and divides that rate by the losses' cost per
# step.  Counted at a fixed 2000 steps a minute (the rule until the twenty-fifth session, the
# Intel Xeon's rate) the AMD EPYC, at half that, turned them on for fern's 17 views at 1
# minute, where they cost 0.13 dB (9 passes; docs/STABILITY.md, the losses study).
LOSSES_MIN_PASSES = 20.0
LOSSES_RATE_FROM_STEP = 10
LOSSES_DECISION_STEP = 30
LOSSES_STEP_COST = 1.4   # time per step with the losses on / off (the losses study: 1.36-1.49)
# Shallow scenes (far/near at most 3): never by default since the forty-seventh session.  Until
# then on with at most 6 views and 80 passes: side by side, seeds 0 / 1, off -> on, at 240x135
# (seventeenth session) CanClip's 6 views at 0.5 / 1 / 2 minutes (~42 / 84 / 169 passes) -0.44 /
# -0.39, +0.42 / +0.09, +0.65 / +0.23 dB, Statue's +0.35 / +0.16, +0.59 / +0.40, +0.84 / -0.15.
# With today's field (its coarser geometry, the SfM points' depth) and the pass limit that stops
# few photos at 100 passes, at 1 minute (~90-100 passes), four seeds: CanClip's 6 -0.20 ± 0.03
# dB (standard error; the stability study's losses table), Statue's 6 -0.43 ± 0.13 (-0.56 /
# -0.15 / -0.27 / -0.73, the study's jobs at Statue's 25 %, scale 0.25; docs/STABILITY.md).
# With 12 or more photos they lost before as well (CanClip's 26 -0.35 now).


def budget_passes(config: TrainConfig, batch: int, train_pixels: int,
                  steps_per_minute: float | None = None) -> float | None:
    """How many times the budget (steps, or minutes at `steps_per_minute`) passes over the
    training pixels; whichever budget ends training first counts.  None: a minutes budget
    and no measured rate yet."""
    budgets = [config.steps] if config.steps else []
    if config.minutes:
        if steps_per_minute is None:
            return None
        budgets.append(config.minutes * steps_per_minute)
    return min(budgets, default=0) * batch / max(train_pixels, 1)


def losses_by_default(deep: bool, n_train_views: int, passes: float = math.inf) -> bool | str:
    """Whether the default trains with the multi-view losses: few photos of a deep scene and a
    budget that passes over them often enough (shallow scenes: never, see above); with 11 to 20
    photos LOSSES_UNTIL_POSES_RIGHT: on until the pose check finds the poses right."""
    if not (deep and 2 <= n_train_views <= CONSISTENCY_MAX_VIEWS and passes >= LOSSES_MIN_PASSES):
        return False
    return True if n_train_views <= CONSISTENCY_ALWAYS_MAX_VIEWS else LOSSES_UNTIL_POSES_RIGHT


def losses_stop_at_pose_check(rule: bool | str | None, colours_learned: bool, poses_found_right: bool) -> bool:
    """Whether a run training with the losses by `rule` goes on without them once the pose
    check has found the poses right: LOSSES_UNTIL_POSES_RIGHT, unless a colour transform per
    photo is learned (its drift is theirs to hold too)."""
    return rule == LOSSES_UNTIL_POSES_RIGHT and poses_found_right and not colours_learned


# Coarse to fine (DisparityConfig.geometry_coarse_to_fine): with few photos the finer geometry
# scales fade in over the first 80 % of the budget.  Measured at 1000 steps (fast field;
# docs/STABILITY.md): 6 of CanClip's views +0.42 dB, 4 / 7 of the synthetic scene's +0.32 /
# +0.26 (three seeds each), 4 of fern's +0.34 (one seed); with more photos it does nothing
# measurable (CanClip's 13 / 26 views +0.03 / -0.04 dB, the synthetic scene's 14 +0.10, three
# seeds each; CanClip's 20 +0.01, fern's 17 +0.10, seed 0): within the seed spread, so it stays
# off there and none of the benchmark scenes (17 to 26 training views) changes.  Ramps over 30 / 50 /
# 80 / 100 % of the budget at 6 of CanClip's views: +0.23 / +0.37 / +0.45 / +0.49 dB; the
# synthetic scene's 4: +0.30 / +0.49 / +0.54 / +0.50 (seed 0).  Fading the texture levels in
# as well helped 4 photos of the synthetic scene (+0.24 dB more) but not 4 of fern's (+0.04),
# and cost with 7 or 8 (-0.06 to -0.17) and on CanClip: not adopted.  With the back surface
# (deep scenes) the synthetic scene's 10 / 7 / 4 photos gain +0.15 / +0.00 / -0.05 dB (three
# seeds, fifty-first session): nothing either way there, and no cost in time, so the rule stands.
COARSE_TO_FINE = 0.8
COARSE_TO_FINE_MAX_VIEWS = 13


def default_coarse_to_fine(n_train_views: int) -> bool:
    return 2 <= n_train_views <= COARSE_TO_FINE_MAX_VIEWS


# The training scale where the user gives none: the largest 1/k (k = 1, 2, 3, ...) at which the
# largest photo has at most DEFAULT_SCALE_PIXELS pixels.  The fast field keeps about one texel
# per training pixel up to its texel budget (fields/disparity.MAX_TEXELS: photos of about
# 140,000 pixels), so larger photos make every pass, the sweep and the fill of unseen texels
# slower for detail its texture cannot hold.  CanClip in 1.5 minutes, one thread, two seeds
# (benchmarks/train_scale.py, docs/BENCHMARKS.md "The default training scale"): trained at 1/4
# / 1/2 / 1 of its 960x540, rendered at 480x270 34.34 / 36.08 / 35.30 dB and at the full
# 960x540 32.80 / 34.79 / 34.64: 1/2, which the rule picks, is best even at full size (3/4,
# 291,600 pixels, rendered the full size as 1/2 did, 34.78 dB, and its half size 0.4 dB
# worse).  The rule gives the scales the project's measurements chose by hand (CanClip's and
# Statue's 960x540 and HCI's 512x512 at 1/2, fern's 504x378 at 1), a 12-megapixel phone photo
# 1/8 (504x378) and a 3840x2160 one 1/7 (549x309): thirty of those (CanClip's photos upscaled)
# at scale 1 had not reached the first step after 5 minutes, at 17.7 GB of memory (the AMD
# EPYC, 2 cores).
DEFAULT_SCALE_PIXELS = 200_000


def default_scale(photo_size: tuple[int, int]) -> float:
    """1/k for the smallest k at which a photo of `photo_size` (width, height) has at most
    DEFAULT_SCALE_PIXELS pixels."""
    width, height = photo_size
    k = 1
    while math.prod(scaled_size((width, height), 1.0 / k)) > DEFAULT_SCALE_PIXELS:
        k += 1
    return 1.0 / k


# A scale asked for whose photos have more than this many times the default's pixels is trained
# as asked, with a warning: 30 photos of 3840x2160 at full size had not reached the first step
# after 5 minutes, at 17.7 GB (the AMD EPYC, docs/BENCHMARKS.md "The default training scale").
LARGE_SCALE_FACTOR = 4


def with_default_scale(scene: Scene, config: TrainConfig, model_dir: Path | None = None, resume: bool = False,
                       progress=None) -> TrainConfig:
    """`config` with a training scale: its own (with a warning where its photos are far larger
    than the default's); where it has none, a resumed model's (model.json in `model_dir`), else
    default_scale of the scene's largest photo, which the user is told."""
    if config.scale is not None:
        if not resume:
            _warn_large_scale(scene, config.scale, progress)
        return config
    saved = _saved_scale(model_dir) if resume and model_dir is not None else None
    if saved is not None:
        return replace(config, scale=saved)
    largest = largest_photo(scene.views)
    scale = default_scale(largest)
    if scale < 1.0:
        width, height = scaled_size(largest, scale)
        _emit(progress, event="stage", scale=scale,
              message=f"training at 1/{round(1 / scale)} of the photos' size ({width}x{height}; their full "
                      f"{largest[0]}x{largest[1]} with --scale 1: slower, for detail the model's texture cannot keep)")
    return replace(config, scale=scale)


def _warn_large_scale(scene: Scene, scale: float, progress) -> None:
    largest = largest_photo(scene.views)
    asked, default = scaled_size(largest, scale), scaled_size(largest, default_scale(largest))
    if math.prod(asked) <= LARGE_SCALE_FACTOR * DEFAULT_SCALE_PIXELS or math.prod(asked) <= math.prod(default):
        return
    rays = sum(math.prod(scaled_size(view.size, scale)) for view in scene.views)
    message = (f"scale {scale:g} trains on photos of {asked[0]}x{asked[1]} ({rays / 1e6:.0f} M pixels in all, "
               f"{math.prod(asked) / math.prod(default):.0f} times the default's): slow to start and to train, and "
               f"memory-hungry, for detail the model's texture cannot keep; the default scale (no --scale; Image "
               f"Scale 0 in Blender) trains at {default[0]}x{default[1]}")
    # Once a training call: the auto preset's candidates and model, a model's members, ask again.
    kept("large scale warning", message, lambda: _emit(progress, event="warning", scale=scale, message=message))


def largest_photo(views) -> tuple[int, int]:
    """(width, height) of the photo of the most pixels, which default_scale sizes."""
    return max((view.size for view in views), key=math.prod)


def training_scale(views, config: TrainConfig) -> float:
    """The scale `config` trains at: its own, or the default rule's for these views (a scene's
    all: a run decides it before it splits them)."""
    return config.scale if config.scale is not None else default_scale(largest_photo(views))


def _saved_scale(model_dir: Path) -> float | None:
    """The scale a model in `model_dir` was trained at, or None (no model, or unreadable: the
    resume then says what is wrong)."""
    try:
        scale = json.loads((Path(model_dir) / METADATA_NAME).read_text())["train_config"]["scale"]
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return float(scale) if isinstance(scale, (int, float)) and scale > 0 else None


# Few photos (the same count as coarse to fine's): their planes' depth is furthest off, so the
# depth detail is read twice (DisparityConfig.depth_detail_reads), and their depth overfits, so
# the geometry's smoothness prior is stronger (FEW_VIEWS_GEOMETRY_TV).
FEW_PHOTOS_MAX_VIEWS = 13


def default_depth_detail_reads(n_train_views: int) -> int:
    return 2 if n_train_views <= FEW_PHOTOS_MAX_VIEWS else 1


# Few photos overfit their depth (the synthetic scene's 4 views at 2400 steps: training views
# at 36.6 dB, held-out 28.3): a three times stronger total-variation prior on the geometry
# planes there.  1000 steps, seeds 0 / 1 / 2, against 1e-3: the synthetic scene's 4 views
# +0.05 / +0.21 / +0.23 dB, its 7 -0.03 / +0.06 / +0.02, CanClip's 6 +0.01 / +0.23 / -0.02
# (docs/STABILITY.md); seeds 3 / 4, not used to choose it, +0.43 / +0.15 dB at 4 views.  The
# same count as coarse to fine's.
FEW_VIEWS_GEOMETRY_TV = 3e-3


def default_geometry_tv(n_train_views: int) -> float:
    """The geometry planes' total-variation weight for this many training views (above the
    few-photo count, the field's own: 1e-3)."""
    return FEW_VIEWS_GEOMETRY_TV if n_train_views <= FEW_PHOTOS_MAX_VIEWS else DisparityConfig.tv_weight


# Few photos overfit a long budget: their held-out views peak and then fall while the photos
# go on fitting.  Held-out PSNR at 500 / 1000 / 2400 / 5000 steps (the fast field, 8192-ray
# steps, mean of seeds 0 and 1; passes over the training pixels in brackets; docs/STABILITY.md,
# "few photos stop after 100 passes"): the synthetic scene's 4 views 28.66 (53) / 28.68 (107) /
# 28.56 (256) / 28.27 (533) dB, its 7 views 29.76 (30) / 30.15 (61) / 30.07 (146) / 29.82
# (305), fern's 4 at 252x189 21.12 (22) / 21.02 (43) / 20.84 (103) / 20.73 (215), fern's 8
# 22.55 / 22.55 / 22.47 / 22.30 (107), CanClip's 6 at 240x135 33.25 (21) / 34.20 (42) / 34.42
# (101) / 34.16 (211).  Where the fall starts differs with the scene (fern from ~20 passes,
# CanClip after ~100); 100 passes is where no capture measured was still gaining.  With the
# stop, at a 5000-step budget: the synthetic 4 views +0.41 / +0.52 dB, its 7 +0.21 / +0.29,
# CanClip's 6 +0.19 / +0.30, fern's 4 +0.09 / +0.16, in a fifth to a half of the time.  With
# many photos the held-out views keep gaining or hold (the synthetic scene's 14: 30.03 / 30.30
# / 30.32 dB at 1000 / 2400 / 5000 steps, three seeds), so there is no limit there.
FEW_PHOTOS_MAX_PASSES = 100.0


def default_max_passes(n_train_views: int) -> float:
    """The fast field's pass limit for this many training views (0: none)."""
    return FEW_PHOTOS_MAX_PASSES if n_train_views <= FEW_PHOTOS_MAX_VIEWS else 0.0


def max_passes(config: TrainConfig, field_name: str, n_train_views: int) -> float:
    """The passes `config` asks for, or the default where it leaves them open (measured on the
    fast field only: none for the others)."""
    if config.max_passes is not None:
        return config.max_passes
    return default_max_passes(n_train_views) if field_name == "disparity" else 0.0


def pass_step_limit(config: TrainConfig, field_name: str, n_train_views: int, train_pixels: int, batch: int) -> int | None:
    """The step at which training stops for passing over its photos often enough, or None."""
    passes = max_passes(config, field_name, n_train_views)
    return math.ceil(passes * train_pixels / batch) if passes > 0 else None


def announce_pass_limit(progress, config: TrainConfig, field_name: str, n_train_views: int, step_limit: int | None,
                        step: int = 0) -> None:
    """Tell the user when few photos will end training before the budget does (`step`: where a
    resumed model starts)."""
    if step_limit is None or (config.steps and config.steps <= step_limit):
        return
    passes = max_passes(config, field_name, n_train_views)
    why = (", since more only memorises so few photos (--max-passes 0 trains on; docs/STABILITY.md)"
           if passes == default_max_passes(n_train_views) else " (--max-passes 0 trains on)")
    when = (f"this model has passed over their pixels {passes:g} times already: training ends here" if step >= step_limit
            else f"training stops at step {step_limit} at the latest ({passes:g} passes over their pixels)")
    _emit(progress, event="passes", steps=step_limit, train_views=n_train_views,
          message=f"{n_train_views} photos: {when}{why}")


def budget_rays_per_step(config: TrainConfig) -> int:
    """The rays a step of the whole budget: the batch, times the members where they split it
    (members.py), so that a member decides what counts the budget's passes as one run of the
    budget would.  Members of half the batch that each counted their own passes dropped the
    multi-view losses for the synthetic scene's 14 photos (15 passes each, 30 together; the rule
    asks for 20), and with 2 degrees of pose noise scored 22.03 dB against one run's 27.96
    (seed 0, 1000 steps; sixty-first session)."""
    batch = config.batch_size or get_preset(config.preset).batch_size
    if (config.members_split or "steps") == "batch" and (config.members or 1) > 1:
        batch *= config.members
    return batch


def default_consistency(slab: Slab, train_views, config: TrainConfig,
                        steps_per_minute: float | None = None) -> bool | str | None:
    """Whether the default trains with the multi-view losses (losses_by_default); None: it
    depends on how many steps the minutes budget buys on this machine, which the run has not
    measured yet (`steps_per_minute`: its rate with the losses on)."""
    if not losses_by_default(slab.is_deep, len(train_views)):
        return False  # whatever the budget
    batch = budget_rays_per_step(config)
    scale = training_scale(train_views, config)
    pixels = sum(math.prod(scaled_size(v.size, scale)) for v in train_views)
    passes = budget_passes(config, batch, pixels, steps_per_minute)
    return None if passes is None else losses_by_default(slab.is_deep, len(train_views), passes)


def measured_steps_per_minute(seconds: float) -> float:
    """The rate with the losses on, from the seconds the steps LOSSES_RATE_FROM_STEP to
    LOSSES_DECISION_STEP took without them."""
    return 60.0 * (LOSSES_DECISION_STEP - LOSSES_RATE_FROM_STEP) / max(seconds, 1e-9) / LOSSES_STEP_COST


def announce_default_losses(progress, n_train_views: int) -> None:
    """Tell the user (CLI line, Blender status) that the default turned the losses on."""
    _emit(progress, event="losses", train_views=n_train_views,
          message=f"{n_train_views} photos: training with the paper's multi-view losses, "
          "about 1.4 times the time per step (--no-consistency turns them off; docs/DEPTH.md)")


def announce_default_appearance(progress, n_train_views: int, exposure_stops: float) -> None:
    """Tell the user (CLI line, Blender status) that the photos' exposures differ, so a colour
    transform per photo is learned."""
    _emit(progress, event="appearance", train_views=n_train_views, exposure_difference_stops=exposure_stops,
          message=f"neighbouring photos differ in exposure by {exposure_stops:.2f} stops: learning a colour "
          "transform per photo (--no-appearance turns it off; docs/STABILITY.md)")


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
        options["geometry_layers"] = default_depth_layers(slab, n_train_views)
        use_ramp = coarse_to_fine if coarse_to_fine is not None else default_coarse_to_fine(n_train_views)
        options["geometry_coarse_to_fine"] = COARSE_TO_FINE if use_ramp else 0.0
        options["depth_detail_reads"] = default_depth_detail_reads(n_train_views)
        options["back_surface"] = default_back_surface(slab) if back_surface is None else back_surface
        options["tv_weight"] = default_geometry_tv(n_train_views)
        if appearance:
            options.update(APPEARANCE_GEOMETRY)
    options.update(overrides)
    if options.get("geometry_layers") and "depth_detail_shift" not in overrides:
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
def validation_psnr(field_module, rays: RaySet, chunk: int = 1 << 15) -> float:
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
          progress: Callable[[dict], None] | None = None, should_stop: Callable[[], bool] | None = None) -> TrainResult:
    """Train (or with `resume`, continue) the light field of `scene` into `model_dir`."""
    model_dir = Path(model_dir).expanduser()
    if not config.steps and not config.minutes:
        raise NeulfError("give a training budget: --steps N or --minutes M.")
    from .members import train_members  # (it trains the members, each as train_two_starts does)
    from .starts import train_two_starts  # (it runs _train, once or as two starts)

    def train_one(scene, folder, config, images_dir, resume, progress, should_stop):
        return train_two_starts(_train, scene, folder, config, images_dir, resume, progress, should_stop)

    with training_lock(model_dir), kept_while_training():  # (members and starts read and sweep the photos once)
        remove_stale_temporaries(model_dir)
        scene = scene if isinstance(scene, Scene) else load_scene(scene, images_dir)
        config = with_default_scale(scene, config, model_dir, resume, progress)
        return train_members(train_one, scene, model_dir, config, images_dir, resume, progress, should_stop)


def _train(scene, model_dir: Path, config: TrainConfig, images_dir, resume: bool, progress, should_stop,
           record: dict | None = None) -> TrainResult:
    """One training run into `model_dir`; `record`: entries for the model's metadata (how its
    start was chosen)."""
    run = TrainingRun(scene, model_dir, config, images_dir, resume, progress, record)
    run.train_until_done(should_stop)
    return run.finish()


def _resumed_checkpoint(model_dir: Path, config: TrainConfig, resume: bool) -> dict | None:
    """The checkpoint a resumed run continues (None for a new one); refuses to overwrite a model."""
    if config.scale is not None and config.scale <= 0:
        raise NeulfError(f"--scale must be positive, not {config.scale}.")
    existing = checkpoint_path(model_dir).is_file()
    if existing and not resume:
        raise NeulfError(f"{model_dir} already holds a trained model; pass --resume to continue it, or choose another --out.")
    return load_checkpoint(model_dir) if (resume and existing) else None


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
            config = with_default_scale(scene, config)
        asked = config
        if resumed is not None:
            config = _config_for_resume(resumed, config, scene)
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
        self.restart_pending = (self.poses is not None and self.step < POSE_CHECK_STEP and not self.slab.is_deep
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
        self.exposure_stops = exposure_difference(self.exposures, np.stack([v.center for v in self.train_views]))
        self.exposures_differ = appearance_by_default(self.exposure_stops)
        if config.appearance is None:
            config = replace(config, appearance=self.exposures_differ)
            if config.appearance:
                announce_default_appearance(self.progress, len(self.train_views), self.exposure_stops)
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
        self.field_module.to(self.device).train()
        self.appearance = (_view_appearance(len(self.train_views), self.exposures, resumed).to(self.device)
                           if config.appearance else None)

    def _set_batch(self, config: TrainConfig, asked: TrainConfig, resumed: dict | None) -> None:
        """The rays a step and the pass limit in steps; a first member whose rule split the
        batch part-way (BatchSwitch) goes on with its share."""
        batch = config.batch_size or self.preset.batch_size
        self.switch = BatchSwitch.of((resumed or {}).get("members_rule")) or _switch_on_resume(asked, resumed, batch)
        self.step_limit = pass_step_limit(config, self.field_module.field_name, len(self.train_views), self.n_rays,
                                          self.switch.before if self.switch else batch)
        self.batch = batch
        if self.switch:
            self.batch = self.switch.batch
            self.step_limit = self.switch.steps_for(self.step_limit, self.batch) if self.step_limit else None

    def _set_up_poses(self, config: TrainConfig, resumed: dict | None) -> TrainConfig:
        """The camera corrections: a later member's fixed ones (the first member's), this run's
        own to refine, or none; and whether the default's pose check is still to come."""
        config, self.fixed_poses, found_right = _first_members_poses(config, resumed, self.slab, self.train_views,
                                                                     self.device)
        self.poses_found_right = found_right or (resumed or {}).get("pose_check", {}).get("refining") is False
        if config.refine_poses is None and not _pose_check_possible(config, self.preset, self.step_limit, resumed):
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
            rule = saved if saved is not None else default_consistency(self.slab, self.train_views, config)
            self.losses_pending = rule is None
        if self.losses_stopped_at is None and losses_stop_at_pose_check(rule, bool(config.appearance),
                                                                         self.poses_found_right):
            self.losses_stopped_at = 0  # a later member: the first one's check found the poses right
        if config.consistency is None and self.preset.consistency is None and rule and self.losses_stopped_at is None:
            announce_default_losses(self.progress, len(self.train_views))
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
                "root": str(scene.root), "kind": scene.kind, "fingerprint": scene.fingerprint(),
                "views": [v.name for v in scene.views], "train": [v.name for v in self.train_views],
                "held_out": [v.name for v in self.held_views], "scale": config.scale,
                "mean_colour": mean_colour(self.train_rays).tolist(),
            },
            "train_config": asdict(config),
            # What the default decided, when train_config.consistency is None (None: not yet).
            "multiview_losses": None if self.losses_pending else bool(rule),
            **({"multiview_losses_rule": rule} if rule == LOSSES_UNTIL_POSES_RIGHT else {}),
            **({"multiview_losses_until_step": self.losses_stopped_at} if self.losses_stopped_at is not None else {}),
            # How far neighbouring photos' exposures differ (stops), and whether that turns the
            # per-photo colour transform on by default (train_config.appearance says what ran).
            "exposure_difference_stops": round(self.exposure_stops, 4),
            "appearance_default": self.exposures_differ,
            "rig": _rig(self.train_views, config.scale),
        }
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
        announce_pass_limit(self.progress, config, self.field_module.field_name, len(self.train_views),
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
        start_time = time.monotonic()
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
            now = time.monotonic()
            self.elapsed = elapsed_before + (now - start_time)
            self._decide_at_measured_rate()
            if now - last_validation >= self.config.validate_seconds or self.budget_fraction() >= 1.0:
                self._validate()
                last_validation = time.monotonic()
                start_time += last_validation - now  # validation time does not count against the budget
                now = last_validation
            else:
                _emit(self.progress, event="step", step=self.step, elapsed=self.elapsed, loss=self.loss_value,
                      fraction=self.budget_fraction(), lr=self.lr)
            if now - last_checkpoint >= self.config.checkpoint_seconds:
                self.save("training")
                last_checkpoint = time.monotonic()

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
        view_index = self.train_rays.view_index[index].long()
        pull = teacher_weight(fraction, len(self.train_views), strong=self.strong) if self.teacher is not None else 0.0
        depth_teacher = (self.teacher[0][index], self.teacher[1][index], pull) if pull > 0 else None
        depth_points = (self.point_depth[0][index], self.point_depth[1][index]) if self.point_depth is not None else None
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
        if (self.pose_check_pending and POSE_CHECK_STEP // 2 <= step < POSE_CHECK_STEP
                and "halfway_degrees" not in meta.get("pose_check", {})):
            meta["pose_check"] = {"halfway_step": step, "halfway_degrees": round(self.poses.own_part_degrees(), 4)}
        if self.pose_check_pending and step >= _pose_look_step(meta):
            self.poses, self.pose_check_pending = _pose_check(self.poses, self.optimizer, meta, self.progress, step)
            self.poses_found_right = meta.get("pose_check", {}).get("refining") is False
            if self.consistency is not None and losses_stop_at_pose_check(self.losses_rule, bool(self.config.appearance),
                                                                          self.poses_found_right):
                _stop_losses(meta, self.progress, step, len(self.train_views))
                self.consistency = None
            if self.poses is not None and not self.pose_check_pending and self.point_depth is not None:
                self.point_depth = None  # the poses are off: so are the points placed through them
                meta["point_depth"]["dropped_at_step"] = step
                _emit(self.progress, event="stage", message="the poses are off, and so are the points placed through "
                      "them: no longer pulling toward their depth")
        if self.restart_pending and step >= POSE_CHECK_STEP:
            self.restart_pending = False
            if self.poses is not None:
                _restart_for_far_off_poses(self.field_module, self.optimizer, self.poses, meta, self.progress, step,
                                           self.config.seed, fraction=fraction, n_train_views=len(self.train_views))
        if self.poses is not None:
            self.poses.set_training_progress(fraction)

    def _decide_at_measured_rate(self) -> None:
        """The decisions a minutes budget takes at the step rate the run measures: the members
        rule (MEMBERS_RATE_DECISION_STEP) and the default's multi-view losses (LOSSES_DECISION_STEP)."""
        steps_taken, elapsed = self.step - self.first_step, self.elapsed
        if self.losses_pending and steps_taken == LOSSES_RATE_FROM_STEP:
            self.rate_mark = elapsed
        if self.members_pending and steps_taken > MEMBERS_RATE_FROM_STEP:
            self.members_step_seconds.append(elapsed - self.last_elapsed)
        self.last_elapsed = elapsed
        if self.members_pending and steps_taken >= MEMBERS_RATE_DECISION_STEP:
            self.members_pending = False
            self._decide_members()
        if self.losses_pending and steps_taken >= LOSSES_DECISION_STEP:
            self.losses_pending = False
            self.losses_rule, self.consistency = _decide_losses_at_measured_rate(
                self.slab, self.train_views, self.config, elapsed - self.rate_mark, self.device, self.meta, self.progress)
            if self.consistency is not None and losses_stop_at_pose_check(self.losses_rule, bool(self.config.appearance),
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
                announce_pass_limit(self.progress, config, self.field_module.field_name, len(self.train_views),
                                    self.step_limit, self.step)

    def _validate(self) -> None:
        self.val = validation_psnr(self.field_module, self.val_rays) if self.val_rays is not None else None
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
            self.poses, self.pose_check_pending = _pose_check(self.poses, self.optimizer, meta, progress, self.step,
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


def _first_members_poses(config: TrainConfig, resumed: dict | None, slab: Slab, train_views: list,
                         device) -> tuple[TrainConfig, PoseRefinement | None, bool]:
    """A member after the first (`config.poses_from`) follows the first member's verdict on the
    poses: its corrections, fixed, where it refined them; none, and no pose check of its own,
    where it did not (a check of its own could refine on a borderline capture, in a frame of its
    own).  Returns the config (refine_poses settled), the fixed corrections and whether the
    first member's check found the poses right (for the multi-view losses).  A member resumed
    with corrections of its own -- started before the corrections were shared -- goes on so, and
    its config no longer names the first member (poses_from None)."""
    if not config.poses_from:
        return config, None, False
    if resumed and resumed.get("poses"):
        return replace(config, poses_from=None), None, False
    return replace(config, refine_poses=False), *_poses_of(config.poses_from, slab, train_views, device)


def _poses_of(model_dir: str, slab: Slab, train_views: list, device) -> tuple[PoseRefinement | None, bool]:
    """The camera corrections another model of this scene refined (members.py's first
    member), fixed: None where it did not refine them; and whether its pose check found the
    poses right."""
    try:
        saved = load_checkpoint(Path(model_dir))
    except NeulfError as exc:
        raise NeulfError(f"a member after the first trains with the first one's pose corrections, and its checkpoint "
                         f"cannot be read: {exc}") from None
    found_right = saved.get("pose_check", {}).get("refining") is False
    if not saved.get("poses"):
        return None, found_right
    if saved["scene"]["train"] != [v.name for v in train_views] or saved["slab"] != slab.to_dict():
        raise NeulfError(f"{model_dir} was trained on other photos or another slab than this run; its pose "
                         "corrections do not apply (train the members again with a new --out folder).")
    poses = PoseRefinement(slab, np.stack([v.center for v in train_views]))
    poses.load_state_dict(saved["poses"])
    poses.set_training_progress(1.0)  # the corrections as the first model ended with them, rig-wide part too
    return poses.requires_grad_(False).to(device), found_right


def _pose_check_possible(config: TrainConfig, preset, step_limit: int | None, resumed: dict | None) -> bool:
    """Whether the default's pose check can run: a continued model whose checkpoint holds pose
    corrections has not decided yet (one without them has, or predates the check); a new one
    needs a preset that checks (not the published networks: presets.Preset.pose_check) and a
    budget long enough to reach the check and still train on (a minutes budget is taken to be;
    one that ends first is checked at its end).  `step_limit`: the pass limit."""
    if resumed is not None:
        return bool(resumed.get("poses"))
    if not preset.pose_check:
        return False
    steps = min(s for s in (config.steps, step_limit, math.inf) if s)
    return steps >= 2 * POSE_CHECK_STEP


def _pose_look_step(meta: dict) -> int:
    """The step of the pose check's next look: POSE_CHECK_STEP, or after an unsure first look
    POSE_SECOND_LOOK_STEP (poses.poses_look_off)."""
    return POSE_SECOND_LOOK_STEP if _first_look_unsure(meta.get("pose_check", {})) else POSE_CHECK_STEP


def _first_look_unsure(record: dict) -> bool:
    """Whether the pose check's record (model.json "pose_check") holds an unsure first look."""
    return "unsure_step" in record


def _pose_check(poses: PoseRefinement, optimizer, meta: dict, progress, step: int,
                last: bool = False) -> tuple[PoseRefinement | None, bool]:
    """The default's verdict on the poses (poses.py, poses_look_off): keep refining where
    the corrections found so far say the poses are off; elsewhere drop the corrections, which
    would only drift, and their optimizer state.  Returns the corrections (None once dropped)
    and whether the check is still pending: an unsure first look refines on and looks again
    (unless it is the `last` look, at the end of training: then unsure is right).  The record
    and verdict are saved with the model, so a resumed run keeps them."""
    found = poses.own_part_degrees()
    record = meta.get("pose_check", {})
    second_look = _first_look_unsure(record)
    keep = poses_module.poses_look_off(found, second_look)
    if keep is None and not last:
        meta["pose_check"] = {**record, "unsure_step": step, "unsure_degrees": round(found, 4)}
        _emit(progress, event="stage", message=f"the pose corrections are small but not negligible (median "
              f"{found:.3f} deg after {step} steps): refining on, looking again after {POSE_SECOND_LOOK_STEP} steps")
        return poses, True
    keep = bool(keep)
    halfway = record.get("halfway_degrees")  # for the record: whether the corrections were still growing
    meta["train_config"]["refine_poses"] = keep
    meta["pose_check"] = {**record, "step": step, "median_degrees": round(found, 4), "refining": keep}
    seen = f"median correction {found:.3f} deg after {step} steps" + (
        f", {record['unsure_degrees']:.3f} after {record['unsure_step']}" if second_look else
        f", {halfway:.3f} after {record['halfway_step']}" if halfway is not None else "")
    if keep:
        message = f"the camera poses look off ({seen}): refining them (--no-refine-poses turns it off; docs/STABILITY.md)"
    else:
        message = f"the camera poses agree with the photos ({seen}): not refining them"
    _emit(progress, event="pose_check", refining=keep, median_degrees=found, halfway_degrees=halfway, step=step,
          message=message)
    if keep:
        return poses, False
    optimizer.param_groups[:] = [group for group in optimizer.param_groups if group.get("name") != "poses"]
    for parameter in poses.parameters():
        optimizer.state.pop(parameter, None)
    return None, False


def poses_far_off(degrees: float, n_train_views: int, points_held: bool) -> bool:
    """Whether the pose check's statistic (`degrees`, at POSE_CHECK_STEP) says the poses are
    far enough off for the field to start again: MANY_PHOTOS_FAR_OFF_POSE_DEGREES for more than
    COARSE_TO_FINE_MAX_VIEWS photos whose first steps the SfM points' depth held (`points_held`),
    FAR_OFF_POSE_DEGREES otherwise."""
    many_held = many_photos_held(n_train_views, points_held)
    return degrees >= (MANY_PHOTOS_FAR_OFF_POSE_DEGREES if many_held else FAR_OFF_POSE_DEGREES)


def many_photos_held(n_train_views: int, points_held: bool) -> bool:
    """More than COARSE_TO_FINE_MAX_VIEWS photos whose first steps the SfM points held: there
    the far-off restart has the higher bar (poses_far_off) and starts only the geometry again,
    the texture and the colour decoder kept."""
    return points_held and n_train_views > COARSE_TO_FINE_MAX_VIEWS


def _restart_for_far_off_poses(field_module, optimizer, poses: PoseRefinement, meta: dict, progress, step: int,
                               seed: int, *, fraction: float, n_train_views: int) -> None:
    """Where the poses are far off (poses_far_off), start the field again with
    smoother geometry, so it cannot bend its depth around their error (with many photos the
    points held, many_photos_held, the geometry alone); the corrections and their optimizer
    state go on.  Recorded in the model (meta["field_restart"], and the
    field config's geometry weight), so a resumed run trains on as it was; what it measured
    is recorded either way (meta["far_off_check"])."""
    found = poses.own_part_degrees()
    points_held = "point_depth" in meta  # (pulled from the first step, until the pose check)
    meta["far_off_check"] = {"step": step, "median_degrees": round(found, 4), "train_views": n_train_views,
                             "points_held": points_held}
    if not poses_far_off(found, n_train_views, points_held):
        return
    with torch.random.fork_rng(devices=[]):  # a fresh start of its own; the ray order goes on as it was
        torch.manual_seed(seed + 1)
        fresh = build_field(field_module.field_name, make_config(field_module.field_name, field_module.field_config))
    geometry_only = many_photos_held(n_train_views, points_held)
    def starts_again(name: str) -> bool:  # (the geometry includes the depth layers: they decide the depth too)
        return not geometry_only or name.startswith(field_module.GEOMETRY_PARAMETERS)

    field_module.load_state_dict({name: value for name, value in fresh.state_dict().items() if starts_again(name)},
                                 strict=not geometry_only)
    for name, parameter in field_module.named_parameters():
        if starts_again(name):
            optimizer.state.pop(parameter, None)
    field_module.smooth_geometry(FAR_OFF_GEOMETRY_TV)  # (meta holds the field's own field_config record,
    # which this updates, so the saved model carries the weights)
    layers = bool(field_module.config.geometry_layers)
    meta["field_restart"] = {"step": step, "median_degrees": round(found, 4), "geometry_tv": field_module.config.tv_weight,
                             "geometry_only": geometry_only, "depth_layers": layers,
                             **({"depth_layer_tv": field_module.config.geometry_layer_tv} if layers else {})}
    texture = ""
    if n_train_views <= FEW_PHOTOS_TEXTURE_MAX_VIEWS and hasattr(field_module, "start_texture_coarse_to_fine"):
        # (done before the budget ends, even where the check falls late in a short one)
        ramp = min(FEW_PHOTOS_TEXTURE_COARSE_TO_FINE, 0.9 * (1.0 - fraction))
        field_module.start_texture_coarse_to_fine(fraction, ramp)
        meta["field_restart"]["texture_coarse_to_fine"] = round(ramp, 4)
        texture = ", its texture sharpening coarse to fine (few photos)"
    started_again = "the light field's geometry" if geometry_only else "the light field"
    _emit(progress, event="field_restart", step=step, median_degrees=found,
          message=f"the camera poses are far off (median correction {found:.2f} deg after {step} steps): {started_again} "
                  f"starts again, smoother{texture}, while they are corrected (docs/STABILITY.md)")


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
    steps_per_minute = measured_steps_per_minute(seconds)
    rule = default_consistency(slab, train_views, config, steps_per_minute)
    meta["multiview_losses"] = bool(rule)
    if rule == LOSSES_UNTIL_POSES_RIGHT:
        meta["multiview_losses_rule"] = rule
    meta["losses_steps_per_minute"] = round(steps_per_minute)
    if not rule:
        return rule, None
    announce_default_losses(progress, len(train_views))
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
    passes = budget_passes(config, batch, n_rays, rate)
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
    """Camera centres and a representative pinhole (the first view's) for camera paths."""
    camera = views[0].scaled_camera(scale)
    return {"centres": [v.center.tolist() for v in views], "K": camera.calibration_matrix().tolist(),
            "width": int(camera.width), "height": int(camera.height)}


def _config_for_resume(payload: dict, config: TrainConfig, scene: Scene) -> TrainConfig:
    """Resuming keeps what defines the model (preset, split, scale, slab); the budget and the
    checkpoint interval may change."""
    saved = payload["scene"]
    if saved["fingerprint"] != scene.fingerprint():
        raise NeulfError(
            f"the checkpoint was trained on another scene ({saved['root']}, {len(saved['views'])} views); "
            "resume it with that scene, or train a new model into another --out folder."
        )
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

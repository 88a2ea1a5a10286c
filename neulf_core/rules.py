"""The default's rules: what a training run does where the user leaves an option open (depth
layers, a back surface, the multi-view losses, coarse to fine, the training scale, the few-photo
settings, the pass limit), each decided from the capture -- its depth range, its number of
training photos -- and the budget, and each chosen by a measurement, which its comment gives
(the long forms: docs/TRAINING.md).  The trainer (train.py) asks; nothing here trains.
"""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

from .checkpoint import CHECKPOINT_NAME, METADATA_NAME
from .errors import NeulfError
from .fields.disparity import DisparityConfig
from .memo import kept
from .presets import get_preset
from .progress import emit as _emit
from .scene import Scene, scaled_size
from .slab import Slab

if TYPE_CHECKING:
    from .train import TrainConfig


# Depth layers (DisparityConfig.geometry_layers) by default where they were measured to help:
# scenes of a shallow depth range -- HCI (far/near 2.6 in slab units) +1.2 dB and a third less
# disparity error, Statue (2.0) +0.45 dB, CanClip (1.7) +0.08 dB -- but not deep ones
# (Slab.is_deep), where layers spread over the whole range sit far apart: fern (4.6)
# -0.25 dB, the synthetic scene (3.3) -0.5 dB (docs/DEPTH.md).
# With few photos the layers overfit: CanClip at 240x135, 1000 steps, 3 seeds, with / without
# layers: 26 views +0.15 dB, 20 views -0.03, 13 views -0.47, 6 views -1.03 (docs/STABILITY.md).
# From 18 views on they help again where the rig is dense: 18 views, with / without, HCI at
# 256x256 +1.42 dB (3 seeds), CanClip +0.08 dB (2 seeds); nothing was measured from 14 to 17.
# Where this rule misses (2026-12-07, 1.5 minutes, two seeds, docs/BENCHMARKS.md, first
# section): the synthetic scene (14 views, deep) gains from 8 layers at today's code, +0.56 dB
# on its tuned layout and +0.60 +- 0.36 on two rearranged ones, while fern still loses 0.16.
# Left as it is until real captures no rule was chosen on part the two.
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
        if not resume or model_dir is None or not (Path(model_dir) / CHECKPOINT_NAME).is_file():  # (a new model)
            _refuse_tiny_scale(scene, config.scale)
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


# The fewest pixels a side a training photo may be scaled to: at --scale 1e-6 the photos had
# become 1x1 pixels, and a model of one texel "finished" with a PSNR as if it had learned
# something (the Blender audit's Image Scale 1e-06).
SMALLEST_TRAINING_SIDE = 8


def _refuse_tiny_scale(scene: Scene, scale: float) -> None:
    smallest = min((view.size for view in scene.views), key=min)
    width, height = scaled_size(smallest, scale)
    if min(width, height) < SMALLEST_TRAINING_SIDE:
        raise NeulfError(f"scale {scale:g} makes the {smallest[0]}x{smallest[1]} photos {width}x{height} pixels, too "
                         f"small to learn from (at least {SMALLEST_TRAINING_SIDE} pixels a side): give a larger --scale, "
                         "or leave it out for the default.")


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


def announce_field_choices(progress, field_name: str, field_options: dict, asked: dict, teacher: bool) -> None:
    """One line for what the rules chose for a new fast field (depth layers, the coarse-to-fine
    ramp, the back surface) and whether the plane sweep guides early depth; `asked`: the
    TrainConfig values the user gave (None: the rule's), so the line names what the rules chose
    and leaves out what was asked for."""
    chosen = []
    if field_name == "disparity":
        if "geometry_layers" not in asked:
            chosen.append(f"{field_options.get('geometry_layers', 0)} depth layers (--depth-layers)")
        if asked.get("coarse_to_fine") is None:
            chosen.append(f"coarse-to-fine {'on' if field_options.get('geometry_coarse_to_fine') else 'off'} "
                          "(--coarse-to-fine)")
        if asked.get("back_surface") is None:
            chosen.append(f"back surface {'on' if field_options.get('back_surface') else 'off'} (--back-surface)")
    if asked.get("teacher") is None:
        chosen.append(f"depth from the photos' plane sweep {'on' if teacher else 'off'} (--sweep-teacher)")
    if chosen:
        _emit(progress, event="stage", message="by rule: " + ", ".join(chosen))

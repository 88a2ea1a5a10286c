"""The trainer's decisions about the camera poses (their refinement itself is poses.py):
the pose check -- after POSE_CHECK_STEP steps, keep refining only where the corrections say
the poses are off -- the far-off restart -- where they are far off, the field starts again,
smoother -- and a member after the first, which trains with the first one's corrections.
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from . import poses as poses_module
from . import rules
from .checkpoint import load_checkpoint
from .errors import NeulfError
from .fields import build_field, make_config
from .poses import PoseRefinement
from .progress import emit as _emit
from .slab import Slab

if TYPE_CHECKING:
    from .train import TrainConfig

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


def first_members_poses(config: TrainConfig, resumed: dict | None, slab: Slab, train_views: list,
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


def check_possible(config: TrainConfig, preset, step_limit: int | None, resumed: dict | None) -> bool:
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
    return steps >= 2 * poses_module.POSE_CHECK_STEP


def next_look_step(meta: dict) -> int:
    """The step of the pose check's next look: POSE_CHECK_STEP, or after an unsure first look
    POSE_SECOND_LOOK_STEP (poses.poses_look_off)."""
    return poses_module.POSE_SECOND_LOOK_STEP if first_look_unsure(meta.get("pose_check", {})) else poses_module.POSE_CHECK_STEP


def first_look_unsure(record: dict) -> bool:
    """Whether the pose check's record (model.json "pose_check") holds an unsure first look."""
    return "unsure_step" in record


def verdict(poses: PoseRefinement, optimizer, meta: dict, progress, step: int,
                last: bool = False) -> tuple[PoseRefinement | None, bool]:
    """The default's verdict on the poses (poses.py, poses_look_off): keep refining where
    the corrections found so far say the poses are off; elsewhere drop the corrections, which
    would only drift, and their optimizer state.  Returns the corrections (None once dropped)
    and whether the check is still pending: an unsure first look refines on and looks again
    (unless it is the `last` look, at the end of training: then unsure is right).  The record
    and verdict are saved with the model, so a resumed run keeps them."""
    found = poses.own_part_degrees()
    record = meta.get("pose_check", {})
    second_look = first_look_unsure(record)
    keep = poses_module.poses_look_off(found, second_look)
    if keep is None and not last:
        meta["pose_check"] = {**record, "unsure_step": step, "unsure_degrees": round(found, 4)}
        _emit(progress, event="stage", message=f"the pose corrections are small but not negligible (median "
              f"{found:.3f} deg after {step} steps): refining on, looking again after {poses_module.POSE_SECOND_LOOK_STEP} steps")
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
    return points_held and n_train_views > rules.COARSE_TO_FINE_MAX_VIEWS


def restart_for_far_off_poses(field_module, optimizer, poses: PoseRefinement, meta: dict, progress, step: int,
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

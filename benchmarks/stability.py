"""Stability study: where the light field breaks, and by how much (issue 4, "Stability").

    python benchmarks/stability.py [--workers 2] [--fast-steps 1000] [--paper-steps 100] \
        [--seeds 0,1,2] [--cache /tmp/neulf_stability] [--only views,variants,exposure,pose,losses,coarse]

Trains the default model (`fast`) and, on a reduced set of configurations, the paper's
network (`paper`, about 50x slower per step on a CPU) on:

- fewer views: 100/75/50/25% of the training views, the held-out views unchanged (every 8th
  view, never trained on), on CanClip, HCI antinous and the synthetic Lambertian scene;
- view-dependent effects: the synthetic scene in its Lambertian and shiny versions;
- fine texture: the synthetic scene with high-frequency textures;
- exposure: the synthetic scene rendered with each view's exposure jittered by up to one
  stop, and CanClip's photos each brightened or darkened by up to one stop on linear light
  (jitter_capture_exposures), trained with and without per-view appearance compensation,
  scored against the held-out views at the nominal exposure;
- pose noise: training poses rotated and shifted by increasing amounts (held-out poses exact);
- the paper's multi-view losses off and on at equal wall-clock time (`--losses-minutes`) with
  fewer views, on the synthetic scene, fern and CanClip: where the default turns them on;
- coarse to fine off, on the fewer-views runs with at most 13 training views (where the default
  turns it on);

three seeds each (four for the losses study). Fixed step budgets and one torch thread per run, so
the numbers do not depend on how busy the (shared) machine is -- except the losses study, whose
point is equal wall-clock time: run it on an otherwise idle machine (its off / on runs go side
by side, one core each), and its runs stay out of the seed-spread target. Synthetic scenes are rendered once with
`python -m neulf_synth` into the cache folder; finished runs are appended to
`<cache>/runs.jsonl` and reused on the next call (`--fresh` ignores them). A run's key is its
configuration, not the code: after a change of the default's rules (depth layers, the
multi-view losses, coarse to fine, which each row records as `multiview_losses` and
`coarse_to_fine_used`), delete the rows it affects.  Two exceptions are run again by
themselves: a row whose sweep pull faded otherwise than teacher.teacher_fade now gives its
photo count (`sweep_fade`), and one trained with another member count than the members rule
now gives its budget (`members`; neulf_core/members.py).

Writes docs/stability.csv (one row per run), docs/stability.png and the generated tables in
docs/STABILITY.md (between the `stability tables` markers; the prose around them is kept).
"""

from __future__ import annotations

import argparse
import csv
import functools
import json
import math
import os
import platform
import re
import shutil
import subprocess
import sys
import tempfile
import time
import traceback
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass, fields, replace
from datetime import date
from multiprocessing import get_context
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from neulf_core.appearance import linear_to_srgb, srgb_to_linear  # noqa: E402
from neulf_core.errors import NeulfError  # noqa: E402
from neulf_core.images import save_rgb  # noqa: E402
from neulf_core.members import RATE_DECISION_STEP, RULE_MEMBERS, default_split, finished_members, \
    members_by_rule, read_state, work_done  # noqa: E402
from neulf_core.metrics import psnr, ssim  # noqa: E402
from neulf_core.poses import (DEPTH_LIKE_GAUGE, POSE_CHECK_DEGREES, POSE_CHECK_STEP, POSE_CHECK_UNSURE_DEGREES,  # noqa: E402
                              POSE_SECOND_LOOK_DEGREES, POSE_SECOND_LOOK_STEP, fit_view_pose)
from neulf_core.presets import get_preset  # noqa: E402
from neulf_core.render import LightField  # noqa: E402
from neulf_core.slab import slab_frame  # noqa: E402
from neulf_core.scene import Scene, View, camera_spacing, find_model_dir, load_scene, scaled_size, split_views  # noqa: E402
from neulf_core.teacher import TEACHER_FADE, teacher_fade  # noqa: E402
from neulf_core.train import TrainConfig, train  # noqa: E402
from neulf_core.pose_check import (FAR_OFF_POSE_DEGREES, MANY_PHOTOS_FAR_OFF_POSE_DEGREES,  # noqa: E402
                                   many_photos_held, poses_far_off)
from neulf_core.rules import (COARSE_TO_FINE_MAX_VIEWS, CONSISTENCY_MAX_VIEWS, CONSISTENCY_ALWAYS_MAX_VIEWS,  # noqa: E402
                              DEPTH_LAYERS_MIN_VIEWS, LOSSES_MIN_PASSES, LOSSES_UNTIL_POSES_RIGHT, losses_by_default,
                              losses_stop_at_pose_check)

DOCS = REPO / "docs"
CANCLIP = REPO.parent / "shared" / "data" / "canclip"
# The densest capture at hand (a 9x9 grid, 70 training views): the paper's own fewer-views
# scenes had 303-307 photos, so its 25 % still kept 76-77 of them.
HCI = REPO.parent / "shared" / "data" / "hci_antinous"
FERN = REPO.parent / "shared" / "data" / "fern"
FEWER_VIEWS_SCENES = ("canclip", "hci", "lambertian")
# The losses study: scenes and shares of the training views (deep: lambertian, fern; shallow: canclip).
LOSSES_PLAN = {"lambertian": (1.0, 0.5, 0.25), "shiny": (1.0,), "fern": (1.0, 0.5, 0.25), "canclip": (1.0, 0.25)}
# ... and the default in the same minute where it is neither column: 11 to 20 photos of a deep
# scene, whose losses stop where the pose check finds the poses right (rules.losses_by_default).
LOSSES_DEFAULT_PLAN = {"lambertian": (1.0,), "shiny": (1.0,), "fern": (1.0,)}
# The coarse-to-fine study: the fewer-views shares with at most 13 training views (coarse to
# fine's default), trained without it as well.
COARSE_PLAN = {"canclip": (0.5, 0.25), "lambertian": (0.75, 0.5, 0.25)}
DEFAULT_CACHE = Path(tempfile.gettempdir()) / "neulf_stability"
# How a run of several members treats poses (logged as member_poses): the later members follow
# the first one's verdict -- its corrections, fixed, or none and no check of their own
# (neulf_core/members.py).  "first": logged when only the corrections were shared (a row that
# refined stands; one whose first member dropped them had the second check its own); rows
# without it refined each apart.
MEMBER_POSES = "first-verdict"
MEMBER_POSES_CORRECTIONS_ONLY = "first"
FRACTIONS = (1.0, 0.75, 0.5, 0.25)
POSE_SCENES = ("lambertian", "canclip")
# Few photos with pose noise (twenty-first session): the default alone on a quarter of the
# training views, where the refinement has the fewest photos to tell pose from depth.
POSE_FEW_VIEWS = 0.25
POSE_DEGREES = (0.0, 0.1, 0.25, 0.5, 1.0, 2.0)
# Translation noise per degree of rotation noise, as a fraction of the rig's camera spacing:
# 1 degree turns a 320-pixel-wide, 40-degree view by ~8 px; 10% of the spacing shifts the
# nearest synthetic object by ~3 px, so both halves of the noise matter at every level.
SHIFT_PER_DEGREE = 0.1
POSE_NOISE_SEED = 1234
# The pose study trains each level three ways: the default (its pose check), and refinement
# forced on and off (TrainConfig.refine_poses).
POSE_SETTINGS = (None, True, False)
POSE_SETTING_LABELS = {None: "fast (the default: pose check)", True: "fast + `--refine-poses`",
                       False: "fast + `--no-refine-poses`"}
SYNTH = {"grid": "4x4", "size": "320x240", "samples": "32", "seed": "0"}
MARKER_BEGIN = "<!-- stability tables begin (generated by benchmarks/stability.py) -->"
MARKER_END = "<!-- stability tables end -->"


# ----------------------------------------------------------------------------- what one run is


@dataclass(frozen=True)
class Job:
    """One training run. `truth` is the scene whose held-out images are the ground truth; it
    differs from `path` only for the exposure study (jittered training, nominal truth)."""

    scene: str                 # short label: canclip, lambertian, shiny, fine, jitter1, ...
    path: str                  # scene folder trained on
    truth: str                 # scene folder holding the reference held-out images and poses
    scale: float
    preset: str
    steps: int
    seed: int
    fraction: float = 1.0      # share of the training views kept
    pose_degrees: float = 0.0  # rotation noise on the training poses (translation scales with it)
    appearance: bool | None = False  # per-view appearance compensation forced on / off (TrainConfig.appearance;
                                     # None: the trainer's rule, on when neighbouring photos' exposures differ)
    refine_poses: bool | None = None  # per-view pose corrections forced on / off (TrainConfig.refine_poses;
                                      # None: the default's pose check, poses.POSE_CHECK_DEGREES)
    consistency: bool | None = None  # the paper's multi-view losses forced on / off (None: the default's rule)
    minutes: float = 0.0       # a wall-clock budget instead of `steps` (the losses study's equal time)
    coarse_to_fine: bool | None = None  # coarse to fine forced on / off (None: the default's rule)
    # The colour decoder's start (DisparityConfig.colour_start; "random": PyTorch's).  Part of the
    # key, so a new default start re-runs the study; rows logged before it read "random".
    colour_start: str = "random"
    two_starts: bool | None = None  # the better of two starts forced on / off (TrainConfig.two_starts; None: its rule)
    pixel_jitter: float = 0.0  # each training ray at a random point of a square this many pixels wide (TrainConfig)
    members_split: str | None = None  # how members share the budget (TrainConfig.members_split; None: the default's)

    @property
    def key(self) -> str:
        return json.dumps(asdict(self), sort_keys=True)

    @property
    def configuration(self) -> str:
        """The key of everything but the seed: the runs whose spread is one cell."""
        return replace(self, seed=0).key


def appearance_available() -> bool:
    return "appearance" in TrainConfig.__dataclass_fields__


# ----------------------------------------------------------------------------- scenes


def load_any(path: str | Path) -> Scene:
    """A scene folder with sparse/0, or a neulf_synth output (its exact model is sparse_gt/0)."""
    path = Path(path)
    if find_model_dir(path) is None and (path / "sparse_gt" / "0").is_dir():
        return load_scene(path / "sparse_gt" / "0", path / "images")
    return load_scene(path)


def render_synthetic(cache: Path, variant: str, jitter: float = 0.0) -> Path:
    """Render a synthetic scene once into the cache (reused when its summary matches)."""
    name = variant if not jitter else f"{variant}_jitter{jitter:g}"
    out = cache / "scenes" / name
    summary = out / "summary.json"
    if summary.is_file():
        done = json.loads(summary.read_text())
        if done.get("variant") == variant and float(done.get("exposure_jitter_stops", 0)) == jitter \
                and "x".join(map(str, done["size"])) == SYNTH["size"] and done.get("samples") == int(SYNTH["samples"]):
            return out
    command = [sys.executable, "-m", "neulf_synth", str(out), "--variant", variant, "--grid", SYNTH["grid"],
               "--size", SYNTH["size"], "--samples", SYNTH["samples"], "--seed", SYNTH["seed"],
               "--exposure-jitter", str(jitter)]
    print("rendering:", " ".join(command[1:]), flush=True)
    subprocess.run(command, check=True, cwd=REPO, stdout=subprocess.DEVNULL)
    return out


def jitter_capture_exposures(cache: Path, source: Path, stops: float = 1.0, seed: int = 7) -> Path:
    """A copy of a real capture whose photos each change exposure by a stop count drawn
    uniformly in [-stops, stops] (seeded): a gain on linear light, clipped at white and saved
    as 8-bit sRGB, as a camera's exposure changes a photo.  The model folder is copied as is
    (same poses).  Made once into the cache."""
    from PIL import Image

    out = cache / "scenes" / f"{source.name}_jitter{stops:g}"
    done = out / "exposures.json"
    if done.is_file() and json.loads(done.read_text()).get("source") == str(source.resolve()):
        return out
    names = sorted(p.name for p in (source / "images").iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg"))
    drawn = np.random.default_rng(seed).uniform(-stops, stops, len(names))
    if out.exists():
        shutil.rmtree(out)
    (out / "images").mkdir(parents=True)
    shutil.copytree(source / "sparse", out / "sparse")
    for name, k in zip(names, drawn):
        srgb = torch.from_numpy(np.asarray(Image.open(source / "images" / name).convert("RGB"), dtype=np.float64) / 255)
        jittered = linear_to_srgb(srgb_to_linear(srgb) * 2.0 ** k).numpy()  # (clipped at white)
        Image.fromarray(np.round(jittered * 255).astype(np.uint8)).save(out / "images" / (Path(name).stem + ".png"))
    done.write_text(json.dumps({"source": str(source.resolve()), "stops": stops, "seed": seed,
                                "exposures": dict(zip(names, np.round(drawn, 4).tolist()))}, indent=1))
    return out


def check_same_cameras(nominal: Path, jittered: Path) -> dict:
    """The exposure study needs the jittered render to differ from the nominal one only in
    exposure: same view names and poses (neulf_synth draws positions and exposures from
    separate seeded streams). Returns the training views' exposure statistics."""
    a = json.loads((nominal / "ground_truth" / "cameras.json").read_text())["views"]
    b = json.loads((jittered / "ground_truth" / "cameras.json").read_text())["views"]
    if [v["name"] for v in a] != [v["name"] for v in b]:
        raise RuntimeError(f"{nominal} and {jittered} have different views")
    for x, y in zip(a, b):
        for key in ("K", "R", "t"):
            if not np.allclose(x[key], y[key], atol=1e-9):
                raise RuntimeError(f"view {x['name']}: {key} differs between the nominal and jittered renders")
    stops = np.array([v["exposure_stops"] for v in b])
    return {"max_abs_stops": float(np.abs(stops).max()), "mean_stops": float(stops.mean()),
            "exposures": {v["name"]: v["exposure_stops"] for v in b}}


# ----------------------------------------------------------------------------- scene edits


def spread_subset(views: list[View], count: int) -> list[View]:
    """`count` views spread over the rig: greedy farthest-point sampling of the camera centres,
    starting from the view nearest the rig's centre. Deterministic, so the seeds measure
    training noise only, not which views happened to be kept."""
    if count >= len(views):
        return list(views)
    centres = np.array([v.center for v in views])
    chosen = [int(np.argmin(np.linalg.norm(centres - centres.mean(0), axis=1)))]
    distance = np.linalg.norm(centres - centres[chosen[0]], axis=1)
    while len(chosen) < count:
        chosen.append(int(np.argmax(distance)))
        distance = np.minimum(distance, np.linalg.norm(centres - centres[chosen[-1]], axis=1))
    return [views[i] for i in sorted(chosen)]


def rig_spacing(views: list[View]) -> float:
    """Median distance from a camera to its nearest neighbour."""
    return camera_spacing(np.array([v.center for v in views]))


def rotation_about(axis: np.ndarray, degrees: float) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    angle = math.radians(degrees)
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * (k @ k)


def pose_noise(views: list[View], degrees: float, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """(turns, moves), (V, 3) each, world frame: the noise perturb_poses gives `views`.  Each
    camera's turn is `degrees` about a random axis (the vector's length, in degrees) and its
    move SHIFT_PER_DEGREE * degrees * spacing in a random direction, less the mean of those
    over the views.  The axes and directions are drawn from a fixed seed, so a level differs
    from the next only in size.

    Centred because a reconstruction's error is each camera's disagreement with the others:
    the held-out and render cameras come from the same model, so a turn or move shared by
    every training camera is no error at all, while here (held-out poses exact) it would
    put the whole light field off by it, which no per-camera refinement can see (before the
    eighteenth session it was not centred: docs/STABILITY.md, "Pose noise")."""
    rng = np.random.default_rng(POSE_NOISE_SEED)
    draws = [(rng.normal(size=3), rng.normal(size=3)) for _ in views]
    turns = np.array([axis / np.linalg.norm(axis) * degrees for axis, _ in draws])
    moves = np.array([direction / np.linalg.norm(direction) * SHIFT_PER_DEGREE * degrees * spacing
                      for _, direction in draws])
    return turns - turns.mean(0), moves - moves.mean(0)


def moved_view(view: View, turn_vector: np.ndarray, move: np.ndarray) -> View:
    """`view` turned about its centre by `turn_vector` (world frame, its length in degrees)
    and moved by `move`."""
    angle = float(np.linalg.norm(turn_vector))
    turn = rotation_about(turn_vector, angle) if angle > 0 else np.eye(3)
    R = view.R @ turn.T  # camera-to-world R^T becomes turn @ R^T
    return replace(view, R=R, t=-R @ (view.center + move))


def perturb_poses(views: list[View], degrees: float, spacing: float) -> list[View]:
    """Copies of `views`, each turned and moved by its share of pose_noise."""
    turns, moves = pose_noise(views, degrees, spacing)
    return [moved_view(view, turn, move) for view, turn, move in zip(views, turns, moves)]


def depth_like_part(train_views: list[View], degrees: float, spacing: float):
    """The part of the training views' pose noise (pose_noise) along the two rig-wide
    directions the pose refinement holds (poses.DEPTH_LIKE_GAUGE): the turns' fanning (a
    turn toward +u growing with the camera's u, toward +v with its v) and the moves'
    baseline (a move away from the rig's middle, growing with the distance).  The photos
    hardly tell either from a change of the scene's depth, so no refinement removes them,
    and the light field takes them in as depth; held-out cameras at their exact poses then
    see that depth from the wrong place.  Returns a function of a view giving (turn vector,
    move) of that part at its position on the uv plane, the two directions extended
    linearly: moving held-out views by it scores them as if their reconstruction had the
    same rig-wide error, which a real capture's held-out cameras share (STABILITY.md, the
    fifty-ninth session)."""
    turns, moves = pose_noise(train_views, degrees, spacing)
    rotation, origin = slab_frame(train_views)

    def uv_of(centres: np.ndarray) -> np.ndarray:
        return ((np.atleast_2d(centres) - origin) @ rotation.T)[:, :2]

    rig = uv_of(np.array([view.center for view in train_views]))
    middle = rig.mean(0)
    u, v = (rig - middle).T
    fanning, baseline = np.stack([-v, u, 0 * u], 1), np.stack([u, v, 0 * u], 1)
    # Least-squares coefficients of the slab-frame noise along each direction.
    turn_per_unit = float(((turns @ rotation.T) * fanning).sum() / max((fanning ** 2).sum(), 1e-24))
    move_per_unit = float(((moves @ rotation.T) * baseline).sum() / max((baseline ** 2).sum(), 1e-24))

    def at(view: View) -> tuple[np.ndarray, np.ndarray]:
        pu, pv = uv_of(view.center)[0] - middle
        return (turn_per_unit * np.array([-pv, pu, 0.0]) @ rotation,
                move_per_unit * np.array([pu, pv, 0.0]) @ rotation)
    return at


def held_with_noise_part(job: Job, held: list[View]) -> list[View]:
    """The held-out views moved by the depth-like part of the job's pose noise
    (depth_like_part), from the same training views prepare() perturbs."""
    train_views, spacing = kept_share(split_views(load_any(job.truth))[0], job.fraction)
    part = depth_like_part(train_views, job.pose_degrees, spacing)
    return [moved_view(view, *part(view)) for view in held]


def kept_share(train_views: list[View], fraction: float) -> tuple[list[View], float]:
    """(the `fraction` of the training views a job keeps (spread_subset), the spacing of the
    whole rig, which sizes its pose noise)."""
    spacing = rig_spacing(train_views)
    return spread_subset(train_views, max(2, round(fraction * len(train_views)))), spacing


def with_images_from(views: list[View], other: Scene) -> list[View]:
    """The same cameras, each reading its photo from `other` (the jittered render)."""
    return [replace(view, image_path=other.view(view.name).image_path) for view in views]


def prepare(job: Job) -> tuple[Scene, list[View], list[View]]:
    """(scene to train on, its training views, held-out views with the reference photos).
    Held-out views come from `job.truth` with exact poses; only training views are edited."""
    truth = load_any(job.truth)
    train_views, held = split_views(truth)
    if job.path != job.truth:
        train_views = with_images_from(train_views, load_any(job.path))
    train_views, spacing = kept_share(train_views, job.fraction)
    if job.pose_degrees:
        train_views = perturb_poses(train_views, job.pose_degrees, spacing)
    views = sorted(held + train_views, key=lambda v: v.name)
    return replace(truth, views=views), train_views, held


# ----------------------------------------------------------------------------- one run


def score_views(model_dir: Path, held: list[View], scale: float, fit_poses: bool = False,
                moved_held: list[View] | None = None) -> dict:
    """Held-out scores; with `fit_poses` also after fitting each held-out camera's pose to its
    photo with the field frozen (poses.fit_view_pose, BARF's protocol for pose-refined models);
    with `moved_held` (held_with_noise_part) also of those views: the frame error no refinement
    can see left out."""
    light_field = LightField.load(model_dir, "cpu", precision="full")
    field_config = light_field.meta.get("field_config", {})
    psnrs, ssims, matched, half_fit, nonfinite = [], [], [], [], 0
    fitted_psnrs, fitted_degrees = [], []
    spacing = camera_spacing(np.asarray(light_field.meta["rig"]["centres"]))  # the training rig's (pose fits)
    moved = []
    for i, view in enumerate(held):
        target = view.load_image(scale).astype(np.float32) / 255.0
        image = light_field.render_view(view, scale, depth=False).rgb
        nonfinite += int((~np.isfinite(image)).sum())
        image = np.nan_to_num(image, nan=0.0, posinf=1.0, neginf=0.0)
        psnrs.append(psnr(image, target))
        ssims.append(ssim(image, target))
        matched.append(psnr(colour_matched(image, target), target))
        half_fit.append(psnr_right_half_after_left_fit(image, target))
        if fit_poses:
            fitted, degrees, _ = fit_view_pose(light_field, view, scale, spacing)
            fitted_image = np.nan_to_num(light_field.render_view(fitted, scale, depth=False).rgb, nan=0.0)
            fitted_psnrs.append(psnr(fitted_image, target))
            fitted_degrees.append(degrees)
        if moved_held:  # (the same photo, seen from the moved camera)
            moved.append(psnr(np.nan_to_num(light_field.render_view(moved_held[i], scale, depth=False).rgb, nan=0.0), target))
    fitted = {"psnr_pose_fitted": float(np.mean(fitted_psnrs)),
              "pose_fit_degrees": ";".join(f"{d:.3f}" for d in fitted_degrees)} if fit_poses else {}
    if moved_held:
        fitted.update(psnr_noise_part_aligned=float(np.mean(moved)),
                      psnr_per_view_noise_part_aligned=";".join(f"{v.stem}={p:.2f}" for v, p in zip(moved_held, moved)))
    return {"psnr": float(np.mean(psnrs)), "ssim": float(np.mean(ssims)), "psnr_matched": float(np.mean(matched)),
            "psnr_half_fit": float(np.mean(half_fit)), **fitted,
            "psnr_per_view": ";".join(f"{view.stem}={p:.2f}" for view, p in zip(held, psnrs)),
            "nonfinite_pixels": nonfinite, "deep_scene": bool(light_field.slab.is_deep),
            "multiview_losses": light_field.meta.get("multiview_losses"),
            "losses_until_step": light_field.meta.get("multiview_losses_until_step"),
            # A minutes budget's passes as the members rule counted them (None: a steps budget).
            "members_passes": (light_field.meta.get("members_rule") or {}).get("passes"),
            "coarse_to_fine_used": bool(field_config.get("geometry_coarse_to_fine", 0.0)),
            "back_surface": bool(field_config.get("back_surface", False)),
            "back_surface_blend": field_config.get("back_surface_blend", "colour") if field_config.get("back_surface") else None,
            "appearance_used": bool(light_field.meta.get("train_config", {}).get("appearance")),
            "pose_check_refining": light_field.meta.get("pose_check", {}).get("refining"),
            # How the pose corrections held their depth-like part (None: not refined, or before it was logged).
            "pose_gauge": (light_field.meta.get("pose_corrections") or {}).get("depth_like"),
            "pose_check_degrees": light_field.meta.get("pose_check", {}).get("median_degrees"),
            "pose_check_halfway": light_field.meta.get("pose_check", {}).get("halfway_degrees"),
            "field_restarted": "field_restart" in light_field.meta,  # far-off poses (pose_check.poses_far_off)
            # Only the geometry started again (pose_check.many_photos_held; None: not restarted, or logged before).
            "restart_geometry_only": (light_field.meta.get("field_restart") or {}).get("geometry_only"),
            # Whether it started the depth layers again too, smoother (None: not restarted, or logged before).
            "restart_depth_layers": (light_field.meta.get("field_restart") or {}).get("depth_layers"),
            # What that check measured (None: not checked, or logged before it was recorded).
            "far_off_degrees": (light_field.meta.get("far_off_check") or {}).get("median_degrees"),
            "far_off_points_held": (light_field.meta.get("far_off_check") or {}).get("points_held"),
            "appearance_default": light_field.meta.get("appearance_default"),
            "exposure_difference_stops": light_field.meta.get("exposure_difference_stops")}


def starts_cost(model_dir: Path) -> tuple[str | None, int, float]:
    """Which start a model kept where it trained two (neulf_core/starts.py), and the steps and
    seconds of the one it discarded (counted in the run's time: they are the user's wait)."""
    starts = json.loads((model_dir / "model.json").read_text()).get("starts", {})
    if "second_loss" not in starts:  # one start
        return None, 0, 0.0
    discarded = "second_seconds" if starts["kept"] == "first" else "first_seconds"
    return starts["kept"], int(starts["decision_step"]), float(starts.get(discarded, 0.0))


def colour_matched(image: np.ndarray, target: np.ndarray, fit_columns: slice = slice(None)) -> np.ndarray:
    """`image` after the per-channel gain and offset that best fit `target` (least squares) on
    `fit_columns`: a diagnostic that separates a global colour/exposure offset from errors in
    structure."""
    out = np.empty_like(image)
    for c in range(3):
        fit = image[:, fit_columns, c].ravel()
        coef, *_ = np.linalg.lstsq(np.stack([fit, np.ones(fit.size)], axis=1), target[:, fit_columns, c].ravel(), rcond=None)
        out[..., c] = image[..., c] * coef[0] + coef[1]
    return np.clip(out, 0.0, 1.0)


def psnr_right_half_after_left_fit(image: np.ndarray, target: np.ndarray) -> float:
    """NeRF-in-the-wild's protocol for appearance-compensated models: the held-out photo's
    appearance (here a per-channel gain and offset) is fitted on its left half only and the
    PSNR is taken on the right half, which the fit never saw."""
    half = image.shape[1] // 2
    matched = colour_matched(image, target, slice(0, half))
    return psnr(matched[:, half:], target[:, half:])


def in_pose_study(job: Job) -> bool:
    """Whether `job` is one of the pose study's runs (its 0° runs are shared with the other
    studies' baselines), which are scored with the held-out poses fitted as well."""
    return (job.scene in POSE_SCENES and job.preset == "fast" and job.fraction in (1.0, POSE_FEW_VIEWS)
            and job.appearance is False
            and job.consistency is None and not job.minutes and job.coarse_to_fine is None)


def preset_colour_start(preset: str) -> str:
    """The colour decoder's start the preset trains with ("random" where it names none)."""
    return get_preset(preset).field_config.get("colour_start") or "random"


def train_config(job: Job, held: list[View]) -> TrainConfig:
    # Validation and checkpoints only at the end: the budget is steps, and nothing is resumed.
    options = dict(preset=job.preset, steps=job.steps, scale=job.scale, seed=job.seed,
                   exclude=[v.name for v in held], validate_seconds=1e9, checkpoint_seconds=1e9)
    options["appearance"] = job.appearance  # False stays off: the rule would say so on every nominal capture here
    options["refine_poses"] = job.refine_poses
    if job.consistency is not None:
        options["consistency"] = job.consistency
    if job.minutes:
        options.update(steps=None, minutes=job.minutes)
    if job.coarse_to_fine is not None:
        options["coarse_to_fine"] = job.coarse_to_fine
    if job.two_starts is not None:
        options["two_starts"] = job.two_starts
    if job.pixel_jitter:
        options["pixel_jitter"] = float(job.pixel_jitter)
    if job.members_split:
        options["members_split"] = job.members_split
    if job.colour_start != preset_colour_start(job.preset):
        options["field_overrides"] = {"colour_start": "" if job.colour_start == "random" else job.colour_start}
    return TrainConfig(**options)


def sweep_fade(preset: str, n_train_views: int) -> float | None:
    """The share of the budget over which the sweep's depth pull fades for this many training
    photos (teacher.teacher_fade); None for a preset without the sweep."""
    return teacher_fade(n_train_views) if get_preset(preset).teacher else None


def trained_with_another_surface_mix(row: dict) -> bool:
    """Whether a logged fast run of a deep scene (its `deep_scene`, the slab it trained in) was
    trained otherwise than the default now trains deep scenes: with one surface (rows logged
    before the back surface existed have none, or an empty cell in the CSV;
    rules.default_back_surface), or with its surfaces blended otherwise than the fast preset
    blends them (`back_surface_blend`; rows logged before it was recorded blended colours).
    The study runs it again."""
    preset = get_preset(row["preset"])
    if preset.field != "disparity":
        return False
    if row.get("back_surface") is None:
        return bool(row.get("deep_scene"))
    blend = preset.field_config.get("back_surface_blend", "colour")
    return bool(row["back_surface"]) and (row.get("back_surface_blend") or "colour") != blend


def trained_with_another_fade(row: dict) -> bool:
    """Whether a logged run's sweep pull faded otherwise than the code now fades it for its
    photo count (rows logged before the fade depended on it faded over TEACHER_FADE): the
    study runs it again instead of reporting a default that no longer exists."""
    if not row.get("train_views"):
        return False
    logged = row.get("sweep_fade")  # None too where the committed CSV started the log
    if logged is None and get_preset(row["preset"]).teacher:
        logged = TEACHER_FADE
    return logged != sweep_fade(row["preset"], row["train_views"])


def trained_with_another_losses_rule(row: dict) -> bool:
    """Whether a logged run whose multi-view losses the default decided (`consistency` empty,
    a preset that leaves them to rules.losses_by_default) trained with them otherwise than the
    rule now decides for its photo count, depth and step budget, or kept them on where the
    pose check, finding its poses right, now ends them (rules.losses_stop_at_pose_check;
    `losses_until_step`, logged since): the study runs it again.  Minutes runs stand (their
    passes were counted at the rate they measured), and so do runs whose scene is not at hand
    to count its pixels."""
    if row.get("consistency") is not None or get_preset(row["preset"]).consistency is not None:
        return False
    views, deep, logged = row.get("train_views"), row.get("deep_scene"), row.get("multiview_losses")
    if not views or deep is None or logged is None or row.get("minutes") or not row.get("steps"):
        return False
    rule = losses_by_default(bool(deep), int(views))
    if rule is not False:  # the budget counts too
        passes = logged_passes(row, row["steps"])
        if passes is None:
            return False
        rule = losses_by_default(bool(deep), int(views), passes)
    found_right = row.get("refine_poses") is None and row.get("pose_check_refining") is False
    stops = losses_stop_at_pose_check(rule, bool(row.get("appearance_used")), found_right)
    return bool(rule) != bool(logged) or (stops and row.get("losses_until_step") is None)


def scored_without_noise_part(row: dict) -> bool:
    """A default pose-noise run logged before the study scored the held-out views moved by the
    noise's depth-like part (score_views' moved_held): the study runs it again for that score and
    reports it as logged until then."""
    return (row.get("preset") == "fast" and bool(row.get("pose_degrees")) and row.get("refine_poses") is None
            and row.get("scene") in POSE_SCENES and not row.get("minutes") and "psnr_noise_part_aligned" not in row)


def trained_with_another_pose_gauge(row: dict) -> bool:
    """Whether a logged run that refined its poses held the corrections' depth-like part
    otherwise than the code now does (poses.DEPTH_LIKE_GAUGE; rows logged before it was
    recorded held it by a weak prior): the study runs it again."""
    refined = row.get("pose_check_refining") is True or row.get("refine_poses") is True
    return refined and row.get("pose_gauge") != DEPTH_LIKE_GAUGE


def trained_with_another_restart_rule(row: dict) -> bool:
    """Whether a logged run that refined its poses on a scene that is not deep started its
    field again (`field_restarted`) otherwise than pose_check.poses_far_off now decides from what
    the far-off check measured (`far_off_degrees`, `far_off_points_held`): the study runs it
    again.  Rows logged before the fifty-fifth session restarted from 0.4 degrees whatever
    their photo count and logged neither; the default's (its pose check; the preset's SfM
    points pulling until then) are judged by the pose check's statistic at the same step, and
    runs with the refinement forced on (no points) decided as the rule still does."""
    refined = row.get("pose_check_refining") is True or row.get("refine_poses") is True
    views = row.get("train_views")
    if not refined or row.get("deep_scene") is not False or not views or get_preset(row["preset"]).field != "disparity":
        return False
    # Since the fifty-seventh session the depth layers (DEPTH_LAYERS_MIN_VIEWS photos or more) start
    # again with the geometry, smoother; rows restarted before (no `restart_depth_layers`) did not.
    if row.get("field_restarted") and int(views) >= DEPTH_LAYERS_MIN_VIEWS and row.get("restart_depth_layers") is None:
        return True
    degrees, held = row.get("far_off_degrees"), row.get("far_off_points_held")
    if degrees is None:
        if row.get("refine_poses") is True or (row.get("pose_check_degrees") or 0) < POSE_CHECK_DEGREES:
            return False  # (forced: the old rule's decision; an unsure first look: another step's statistic)
        degrees = row["pose_check_degrees"]
    if held is None:  # (logged before it was: the preset's points pull until the pose check, never when forced)
        held = row.get("refine_poses") is None and get_preset(row["preset"]).point_depth
    restarted = bool(row.get("field_restarted"))
    if restarted != poses_far_off(float(degrees), int(views), bool(held)):
        return True
    # Since the fifty-sixth session a restart with many photos the points held starts only the
    # geometry again; rows restarted before (no `restart_geometry_only`) started everything.
    return restarted and bool(row.get("restart_geometry_only")) != many_photos_held(int(views), bool(held))


def split_used(row: dict) -> str:
    """How the logged run's members shared its budget (members.SPLITS): as logged, else the split
    its job asked for, else the steps (the default's until the sixty-fourth session)."""
    return row.get("members_split_used") or row.get("members_split") or "steps"


def trained_with_other_members(row: dict) -> bool:
    """Whether a logged run had another member count, or members sharing the budget otherwise,
    than the default (or its job's split) now gives its budget (neulf_core/members.py; rows
    logged before members trained one; the sixty-second session's runs of the default with its
    members splitting the batch, docs/MEMBERS.md): the study runs it again.  A minutes run is
    judged by the passes its rule counted at the pace it timed over its first steps
    (`members_passes`; counted at the steps it made, a run that went faster than it timed would
    read as another count: fern's 8 photos, one member, 80 passes); one logged before those were
    is counted at the steps it made, unless it trained two members (then it stands)."""
    logged = int(row.get("members") or 1)
    if not row.get("train_views"):
        return False
    split = row.get("members_split") or default_split("cpu")  # (the study trains on a CPU)
    if logged > 1 and split_used(row) != split:
        return True
    if row.get("members_split") == "batch":  # asked for: two members at any budget
        return logged != RULE_MEMBERS
    if row.get("minutes") and row.get("members") is not None:
        if row.get("members_passes") is not None:
            return members_by_rule(float(row["members_passes"]), split) != logged  # the passes its rule counted
        if logged > 1 or int(row.get("steps_done") or 0) <= RATE_DECISION_STEP:
            return False  # two by their pace (at least 60), or a budget that ended before the rule decided
    steps = row.get("steps_done") if row.get("minutes") else row.get("steps")
    if not steps:
        return False
    passes = logged_passes(row, steps)
    return passes is not None and members_by_rule(passes, split) != logged
    # (no scene at hand: it stands)


def logged_passes(row: dict, steps: int) -> float | None:
    """How many times `steps` of the logged run's preset's batch pass over its training pixels;
    None where its scene is no longer at hand to count them."""
    try:
        pixels = int(row["train_views"]) * image_pixels(row["truth"], float(row["scale"]))
    except NeulfError:
        return None
    return int(steps) * get_preset(row["preset"]).batch_size / pixels


def trained_with_members_own_poses(row: dict) -> bool:
    """Whether a logged run of several members let a later member decide its poses apart from
    the first (MEMBER_POSES): refined each member's own, or, where the first member's check
    dropped the refinement, ran the second member's own check.  The study runs it again."""
    if int(row.get("members") or 1) <= 1 or row.get("member_poses") == MEMBER_POSES:
        return False
    refined = bool(row.get("pose_check_refining")) or row.get("refine_poses") is True
    if refined:
        return row.get("member_poses") != MEMBER_POSES_CORRECTIONS_ONLY
    return row.get("pose_check_refining") is False  # the first dropped them; the second checked its own


def run_job(job: Job, threads: int = 1) -> dict:
    """Train and score one configuration; never raises (a crash is a result too)."""
    torch.set_num_threads(threads)
    row = {**asdict(job), "status": "crashed", "steps_done": 0, "train_seconds": math.nan, "warnings": 0,
           "warning_text": "", "error": "", "pose_check_refining": None}
    if job.appearance and not appearance_available():
        return {**row, "status": "unavailable", "error": "TrainConfig has no 'appearance' option"}
    started = time.perf_counter()
    warnings: list[str] = []

    def progress(event: dict) -> None:
        if event.get("event") == "warning":
            warnings.append(str(event.get("message")))

    try:
        scene, train_views, held = prepare(job)
        row.update(train_views=len(train_views), held_out=len(held), sweep_fade=sweep_fade(job.preset, len(train_views)))
        with tempfile.TemporaryDirectory(prefix="neulf_stability_") as model_dir:
            result = train(scene, model_dir, train_config(job, held), progress=progress)
            kept, discarded_steps, discarded_seconds = starts_cost(Path(model_dir))
            members = 1 + len(finished_members(Path(model_dir)))
            steps_done, seconds = work_done(model_dir) if members > 1 else (result.step, result.elapsed)
            row.update(steps_done=steps_done, train_seconds=round(seconds + discarded_seconds, 2),
                       start_kept=kept, discarded_steps=discarded_steps, members=members,
                       member_poses=MEMBER_POSES if members > 1 else None,
                       members_split_used=(read_state(Path(model_dir)) or {}).get("split") if members > 1 else None)
            moved = held_with_noise_part(job, held) if job.pose_degrees else None
            row.update(score_views(Path(model_dir), held, job.scale, fit_poses=in_pose_study(job), moved_held=moved))
        row["status"] = result.status
    except Exception as exc:  # recorded and reported; the study goes on
        row["error"] = f"{type(exc).__name__}: {exc}"
        row["traceback"] = traceback.format_exc(limit=6)
    row.update(warnings=len(warnings), warning_text=" | ".join(warnings),
               wall_seconds=round(time.perf_counter() - started, 2))
    return row


def run_jobs(jobs: list[Job], workers: int = 2, done: dict | None = None, log: Path | None = None,
             by_configuration: bool = False) -> list[dict]:
    """Run the jobs not in `done` (key -> row), at most `workers` at a time, appending each
    finished row to `log` at once so an interrupted study keeps what it finished.  In
    run_order, or with `by_configuration` one configuration's seeds after another (a study cut
    short by a time limit then has whole configurations)."""
    done = dict(done or {})
    todo = sorted((job for job in jobs if job.key not in done), key=job_order(jobs, by_configuration))

    def record(row: dict) -> None:
        done[Job(**{f.name: row[f.name] for f in fields(Job)}).key] = row
        print(progress_line(row, sum(job.key in done for job in jobs), len(jobs)), flush=True)
        if log is not None:
            with open(log, "a") as handle:
                handle.write(json.dumps(row, default=float) + "\n")

    if workers <= 1:
        for job in todo:
            record(run_job(job))
    else:
        with ProcessPoolExecutor(workers, mp_context=get_context("spawn")) as pool:
            futures = {pool.submit(run_job, job): job for job in todo}
            for future in as_completed(futures):
                try:
                    record(future.result())
                except Exception as exc:  # the worker process itself died
                    record({**asdict(futures[future]), "status": "crashed", "error": f"worker died: {exc!r}"})
    return [done[job.key] for job in jobs]


def job_order(jobs: list[Job], by_configuration: bool = False):
    """The sort key run_jobs runs `jobs` by: run_order, or with `by_configuration` the plan's
    order of configurations, each one's seeds together."""
    if not by_configuration:
        return lambda job: (run_order(job, jobs), job.seed)
    first = {}
    for index, job in enumerate(jobs):
        first.setdefault(job.configuration, index)
    return lambda job: (first[job.configuration], job.seed)


def run_order(job: Job, jobs: list[Job]) -> tuple:
    """The fast model's first seed of every configuration, then the paper's network, then the
    other seeds of the configurations the issue's targets are about (all / 25% of the views,
    exposure), then the rest: a study cut short still covers every configuration once and
    has the seed spread where it matters most."""
    first_seed = min(j.seed for j in jobs)
    if job.preset == "paper":
        return (1, job.seed)
    if job.minutes:  # the losses study last, its off / on pairs side by side
        return (4, job.seed, job.scene, job.fraction)
    if job.seed == first_seed:
        return (0, job.seed)
    targeted = job.pose_degrees == 0 and (job.fraction in (1.0, 0.25) or "jitter" in job.scene)
    return (2 if targeted else 3, job.seed)


def progress_line(row: dict, count: int, total: int) -> str:
    score = f"{row['psnr']:.2f} dB" if isinstance(row.get("psnr"), float) else row.get("error", "")
    return (f"[{count}/{total}] {row['scene']} {row['preset']} views={row['fraction']:g} pose={row['pose_degrees']:g}deg "
            f"appearance={row['appearance']} refine={row.get('refine_poses')} seed={row['seed']}"
            f"{'' if row.get('consistency') is None else ' losses=' + ('on' if row['consistency'] else 'off')}"
            f"{' minutes=%g' % row['minutes'] if row.get('minutes') else ''}"
            f"{'' if row.get('coarse_to_fine') is None else ' coarse=' + ('on' if row['coarse_to_fine'] else 'off')}"
            f": {row['status']} {score} "
            f"({row.get('steps_done', 0)} steps, {row.get('train_seconds', math.nan)} s, {row.get('warnings', 0)} warnings)")


# ----------------------------------------------------------------------------- the plan


def plan(args, scenes: dict[str, Path]) -> list[Job]:
    """Every run of the study. The paper's network gets a reduced subset (it is ~50x slower
    per step): one seed fewer configurations, and fewer steps."""
    studies = set(args.only.split(","))
    seeds = [int(s) for s in args.seeds.split(",")]
    jobs: list[Job] = []

    def add(scene: str, preset: str, scale: float, truth: str | None = None, seed_list=None, steps=None, **edits):
        # (a wall-clock job has steps 0: --fast-steps does not change it)
        steps = steps if steps is not None else args.fast_steps if preset == "fast" else args.paper_steps
        for seed in seed_list or seeds:
            path = str(scenes[scene])
            jobs.append(Job(scene, path, str(scenes[truth]) if truth else path, scale, preset, steps, seed,
                            colour_start=preset_colour_start(preset), **edits))

    synth = args.synth_scale
    paper_seeds = seeds[: args.paper_seeds]
    if "views" in studies:
        for fraction in FRACTIONS:
            if "canclip" in scenes:
                add("canclip", "fast", args.canclip_scale, fraction=fraction)
            if "hci" in scenes:
                add("hci", "fast", args.hci_scale, fraction=fraction)
            add("lambertian", "fast", synth, fraction=fraction)
        for fraction in (1.0, 0.25):
            add("lambertian", "paper", synth, seed_list=paper_seeds, fraction=fraction)
    if "variants" in studies:
        for variant in ("lambertian", "shiny", "fine"):
            add(variant, "fast", synth)
            add(variant, "paper", synth, seed_list=paper_seeds)
    if "exposure" in studies:
        add("lambertian", "fast", synth)
        add("jitter1", "fast", synth, truth="lambertian")
        add("jitter1", "fast", synth, truth="lambertian", appearance=None)  # the default: its rule turns it on
        if "canclip_jitter1" in scenes:  # a real capture's photos, each a stop-jittered exposure of the original
            add("canclip_jitter1", "fast", args.canclip_scale, truth="canclip")
            add("canclip_jitter1", "fast", args.canclip_scale, truth="canclip", appearance=None)
    if "pose" in studies:
        # The default (its pose check), and refinement forced on and off; on CanClip, a real
        # capture, 0° is COLMAP's own poses.
        for scene in POSE_SCENES:
            if scene in scenes:
                scale = synth if scene == "lambertian" else args.canclip_scale
                for degrees in POSE_DEGREES:
                    for refine in POSE_SETTINGS:
                        add(scene, "fast", scale, pose_degrees=degrees, refine_poses=refine)
                    add(scene, "fast", scale, fraction=POSE_FEW_VIEWS, pose_degrees=degrees)
    if "losses" in studies:
        scales = {"lambertian": synth, "shiny": synth, "fern": args.fern_scale, "canclip": args.canclip_scale}
        losses_seeds = [int(s) for s in args.losses_seeds.split(",")]
        for scene, shares in LOSSES_PLAN.items():
            if scene not in scenes:
                continue
            for fraction in shares:
                settings = (False, True, None) if fraction in LOSSES_DEFAULT_PLAN.get(scene, ()) else (False, True)
                for consistency in settings:
                    add(scene, "fast", scales[scene], seed_list=losses_seeds, fraction=fraction,
                        consistency=consistency, minutes=args.losses_minutes, steps=0)
    if "coarse" in studies:  # the fewer-views runs the default trains coarse to fine, without it
        for scene, shares in COARSE_PLAN.items():
            if scene in scenes:
                for fraction in shares:
                    add(scene, "fast", args.canclip_scale if scene == "canclip" else synth, fraction=fraction,
                        coarse_to_fine=False)
    jobs = list({job.key: job for job in jobs}.values())  # shared baselines run once
    if args.defaults_only:
        jobs = [job for job in jobs if is_default_run(job)]
    if args.scenes:
        jobs = [job for job in jobs if job.scene in args.scenes.split(",")]
    if args.fractions:
        jobs = [job for job in jobs if job.fraction in {float(f) for f in args.fractions.split(",")}]
    if args.pose_degrees:
        jobs = [job for job in jobs if job.pose_degrees in {float(d) for d in args.pose_degrees.split(",")}]
    return jobs


def is_default_run(job: Job) -> bool:
    """Whether `job` trains the default as a user runs it: the fast preset with every rule
    left to decide (the nominal captures' colour transform is forced off, which is what its
    rule decides there; the jittered photos' is the rule's), no rule forced on or off."""
    forced = (job.refine_poses is not None or job.consistency is not None or job.coarse_to_fine is not None
              or job.minutes or ("jitter" in job.scene and job.appearance is not None) or job.appearance)
    return job.preset == "fast" and not forced


# ----------------------------------------------------------------------------- summaries


def group(rows: list[dict], **match) -> list[dict]:
    return [r for r in rows if all(r.get(k) == v for k, v in match.items())]


def score_of(row: dict, column: str) -> float:
    """A run's score, NaN where it has none: absent from its logged row, or None from the
    CSV's empty cell (a run seeded from docs/stability.csv)."""
    value = row.get(column)
    return math.nan if value is None else value


def stats(rows: list[dict], column: str = "psnr") -> dict | None:
    values = [r[column] for r in rows if r.get("status") == "finished" and np.isfinite(score_of(r, column))]
    if not values:
        return None
    sd = float(np.std(values, ddof=1)) if len(values) > 1 else math.nan
    return {"mean": float(np.mean(values)), "spread": float(np.max(values) - np.min(values)), "n": len(values), "sd": sd}


def difference_standard_error(first: dict, last: dict) -> float:
    """Standard error of `first`'s mean minus `last`'s (two stats() of independent seeds): how far
    the fewer-views loss could move if the same seeds' scatter were drawn again."""
    return math.sqrt(first["sd"] ** 2 / first["n"] + last["sd"] ** 2 / last["n"])


def cell(rows: list[dict], column: str = "psnr") -> str:
    s = stats(rows, column)
    if s is None:
        status = {r.get("status") for r in rows}
        return "not run" if not rows else "/".join(sorted(status))
    if s["n"] == 1:
        return f"{s['mean']:.2f} (n=1)"
    return f"{s['mean']:.2f} ± {s['spread']:.2f}" + ("" if s["n"] >= 3 else f" (n={s['n']})")


def base(scene: str, preset: str | None = None, fraction: float = 1.0, pose_degrees: float = 0.0,
         appearance: bool | None = False, refine_poses: bool | None = None, consistency: bool | None = None,
         minutes: float = 0.0, coarse_to_fine: bool | None = None) -> dict:
    """Row filter for one configuration (unedited unless told); preset None matches both."""
    match = {"scene": scene, "fraction": fraction, "pose_degrees": pose_degrees, "appearance": appearance,
             "refine_poses": refine_poses, "consistency": consistency, "minutes": minutes,
             "coarse_to_fine": coarse_to_fine}
    return match if preset is None else {**match, "preset": preset}


def views_table(rows: list[dict]) -> list[str]:
    lines = ["| scene | model | " + " | ".join(f"{f:.0%} views" for f in FRACTIONS) + " | 100% -> 25% |",
             "|---|---|" + "---|" * (len(FRACTIONS) + 1)]
    for scene in FEWER_VIEWS_SCENES:
        for preset in ("fast", "paper"):
            cells = [group(rows, **base(scene, preset, fraction=f)) for f in FRACTIONS]
            if not any(cells):
                continue
            first, last = stats(cells[0]), stats(cells[-1])
            loss = f"{first['mean'] - last['mean']:.2f} dB lost" if first and last else "-"
            lines.append(f"| {scene} | {preset} | " + " | ".join(cell(c) for c in cells) + f" | {loss} |")
    return lines


def train_view_counts(rows: list[dict]) -> str:
    parts = []
    for scene in FEWER_VIEWS_SCENES:
        counts = [next((r.get("train_views") for r in group(rows, **base(scene, "fast", fraction=f))), None) for f in FRACTIONS]
        if any(counts):
            parts.append(f"{scene}: " + "/".join(str(c) for c in counts))
    return "; ".join(parts)


def variants_table(rows: list[dict]) -> list[str]:
    lines = ["| model | lambertian | shiny (mirror, glass) | fine texture | shiny - lambertian | fine - lambertian |",
             "|---|---|---|---|---|---|"]
    for preset in ("fast", "paper"):
        cells = [group(rows, **base(v, preset)) for v in ("lambertian", "shiny", "fine")]
        s = [stats(c) for c in cells]
        diff = [f"{x['mean'] - s[0]['mean']:+.2f} dB" if x and s[0] else "-" for x in s[1:]]
        lines.append(f"| {preset} | " + " | ".join(cell(c) for c in cells) + f" | {diff[0]} | {diff[1]} |")
    return lines


# The exposure study's captures: (label, the nominal scene, its exposure-jittered copy).
EXPOSURE_SCENES = (("synthetic scene", "lambertian", "jitter1"), ("CanClip (real photos)", "canclip", "canclip_jitter1"))


def exposure_table(rows: list[dict]) -> list[str]:
    lines = ["| scene | trained on | compensation | held-out PSNR (vs nominal exposure) | cost | gain/offset fitted on the "
             "left half, PSNR of the right half (NeRF-W) | cost | colour-matched on the whole photo | cost |",
             "|---|---|---|---|---|---|---|---|---|"]
    for name, nominal_scene, jittered in EXPOSURE_SCENES:
        nominal = group(rows, **base(nominal_scene, "fast"))
        if not group(rows, **base(jittered, "fast", appearance=None)):
            continue
        for scene, appearance, label in ((nominal_scene, False, "nominal exposure"), (jittered, False, "exposure ±1 stop"),
                                         (jittered, None, "exposure ±1 stop")):
            c = group(rows, **base(scene, "fast", appearance=appearance))
            costs = [cost_text(nominal, c, column) if scene != nominal_scene else "-"
                     for column in ("psnr", "psnr_half_fit", "psnr_matched")]
            lines.append(f"| {name} | {label} | {compensation_text(appearance, c)} | {cell(c)} | {costs[0]} | "
                         f"{cell(c, 'psnr_half_fit')} | {costs[1]} | {cell(c, 'psnr_matched')} | {costs[2]} |")
    return lines


def compensation_text(appearance: bool | None, rows: list[dict]) -> str:
    """What the exposure table's row trained with; for the default, what its rule measured."""
    stops = [r["exposure_difference_stops"] for r in rows if r.get("exposure_difference_stops") is not None]
    measured = f", neighbours {np.mean(stops):.2f} stops apart" if stops else ""
    if appearance is None:
        used = [r.get("appearance_used") for r in rows]
        return f"the default's rule: {'per-view appearance' if used and all(used) else 'none'}{measured}"
    return ("per-view appearance" if appearance else "none, forced off") + measured


def cost_text(reference: list[dict], rows: list[dict], column: str) -> str:
    a, b = stats(reference, column), stats(rows, column)
    return f"{a['mean'] - b['mean']:.2f} dB" if a and b else "-"


def exposure_targets(rows: list[dict], name: str, nominal_scene: str, jittered: str) -> list[str]:
    """The exposure target's lines for one capture (none where its jittered runs are missing)."""
    nominal_rows = group(rows, **base(nominal_scene, "fast"))
    comp_rows = group(rows, **base(jittered, "fast", appearance=None))
    nominal, comp, plain = stats(nominal_rows), stats(comp_rows), stats(group(rows, **base(jittered, "fast")))
    out = []
    if nominal and plain:
        out.append(f"- exposure ±1 stop without compensation, {name}: {nominal['mean'] - plain['mean']:.2f} dB lost")
    if nominal and comp:
        cost = nominal["mean"] - comp["mean"]
        out.append(f"- exposure ±1 stop with compensation, {name}, rendered as is against the nominal exposure: "
                   f"{cost:.2f} dB lost (target ≤ 0.5): {'met' if cost <= 0.5 else 'MISSED'}; after a per-channel colour "
                   f"fit to each held-out photo: {cost_text(nominal_rows, comp_rows, 'psnr_matched')} lost")
        nominal_half, comp_half = stats(nominal_rows, "psnr_half_fit"), stats(comp_rows, "psnr_half_fit")
        if nominal_half and comp_half:
            half_cost = nominal_half["mean"] - comp_half["mean"]
            out.append(f"- exposure ±1 stop with compensation, {name}, NeRF-W protocol (gain and offset fitted on the "
                       f"left half of each held-out photo, PSNR of the right half, the nominal model scored alike): "
                       f"{half_cost:.2f} dB lost (target ≤ 0.5): {'met' if half_cost <= 0.5 else 'MISSED'}")
    elif nominal:
        out.append(f"- exposure with compensation, {name}: not measured")
    return out


def pose_table(rows: list[dict]) -> list[str]:
    lines = ["| pose noise | " + " | ".join(f"{d:g}° / {SHIFT_PER_DEGREE * d:.0%}" for d in POSE_DEGREES) + " |",
             "|---|" + "---|" * len(POSE_DEGREES)]
    kept, restarted = [], []
    for label, scene, fraction, refine in pose_settings():
        cells = pose_cells(rows, scene, fraction, refine)
        if any(cells[1:]):
            lines.append(f"| {label} | " + " | ".join(cell(c) for c in cells) + " |")
        if refine is None and any(cells):
            name = scene if fraction == 1.0 else f"{scene} ({fraction:.0%} of the views)"
            kept.append(f"{name} " + ", ".join(f"{d:g}° {pose_check_kept(c)}" for d, c in zip(POSE_DEGREES, cells) if c))
            restarted.append(f"{name} " + ", ".join(f"{d:g}° {sum(bool(r.get('field_restarted')) for r in c)} of {len(c)}"
                                                    for d, c in zip(POSE_DEGREES, cells) if c))
    if kept:
        lines += ["", "Runs in which the default's pose check kept refining (after "
                      f"{POSE_CHECK_STEP} steps, median correction at least {POSE_CHECK_DEGREES:g}°, or "
                      f"{POSE_CHECK_UNSURE_DEGREES:g}-{POSE_CHECK_DEGREES:g}° and at least {POSE_SECOND_LOOK_DEGREES:g}° "
                      f"after {POSE_SECOND_LOOK_STEP}): " + "; ".join(kept) + "."]
        lines += ["", "Runs in which the default then started the field again with smoother geometry (median correction "
                      f"at least {MANY_PHOTOS_FAR_OFF_POSE_DEGREES:g}° with more than {COARSE_TO_FINE_MAX_VIEWS} photos "
                      f"whose first steps the SfM points held, {FAR_OFF_POSE_DEGREES:g}° otherwise, on a scene that is not "
                      "deep; rows logged before the rule: 0): "
                      + "; ".join(restarted) + "."]
    fitted = pose_fitted_table(rows)
    if fitted:
        lines += ["", "Scored with each held-out camera's pose first fitted to its photo, the field frozen (BARF's "
                      "protocol; `evaluate --fit-poses`): what is left is the field's error, not the frame it "
                      "puts the scene in. The noise's isotropic fanning of the rig, which to a light field is a "
                      "change of depth, cannot be seen in the photos; with exact held-out poses it decides part of "
                      "the score above.", "", *fitted]
    aligned = pose_score_table(rows, "psnr_noise_part_aligned", "held-out views moved by the noise's depth-like part",
                               zero_column="psnr")
    if aligned:
        lines += ["", "Scored with each held-out camera moved by the part of the training cameras' noise that the "
                      "refinement holds by design (the turns' fanning and the moves' baseline, "
                      "`depth_like_part`, extended linearly to the held-out camera's place): a real capture's "
                      "held-out and render cameras come from the same reconstruction and share such a rig-wide "
                      "error, as they share its mean, which the noise already leaves out. The difference from "
                      "the first table is what that part costs; the 0° column (no noise, nothing to move) is the first table's.", "", *aligned]
    exact, refined = group(rows, **base("canclip", "fast", refine_poses=False)), group(rows, **base("canclip", "fast", refine_poses=True))
    if refined:
        lines += ["", f"CanClip (COLMAP's own poses, all views): {cell(exact)} dB without refinement, {cell(refined)} dB "
                      f"with `--refine-poses` ({cost_text(exact, refined, 'psnr')} lost), "
                      f"{cell(group(rows, **base('canclip', 'fast')))} dB by default."]
    return lines


def pose_settings() -> list[tuple[str, str, float, bool | None]]:
    """The pose tables' rows: (label, scene, share of the training views, refinement setting)."""
    out = []
    for scene in POSE_SCENES:
        out += [(f"{POSE_SETTING_LABELS[refine]}, {scene}", scene, 1.0, refine) for refine in POSE_SETTINGS]
        out.append((f"{POSE_SETTING_LABELS[None]}, {scene}, {POSE_FEW_VIEWS:.0%} of the views", scene, POSE_FEW_VIEWS, None))
    return out


def pose_cells(rows: list[dict], scene: str, fraction: float, refine: bool | None) -> list[list[dict]]:
    """One pose-table row's runs, one list per noise level."""
    return [group(rows, **base(scene, "fast", fraction=fraction, pose_degrees=d, refine_poses=refine)) for d in POSE_DEGREES]


def pose_fitted_table(rows: list[dict]) -> list[str]:
    """The pose table's cells scored with the held-out poses fitted."""
    return pose_score_table(rows, "psnr_pose_fitted", "held-out poses fitted")


def pose_score_table(rows: list[dict], column: str, title: str, zero_column: str | None = None) -> list[str]:
    """The pose table's cells scored by `column` (rows logged before that score existed read
    'not scored'; table rows none of whose noisy runs has it are left out); the 0° cells by
    `zero_column` where given (a score that equals it without noise)."""
    lines = []
    for label, scene, fraction, refine in pose_settings():
        cells = pose_cells(rows, scene, fraction, refine)
        if any(r.get(column) is not None for c in cells[1:] for r in c):
            columns = [zero_column or column] + [column] * (len(cells) - 1)
            texts = [cell(c, name) if any(r.get(name) is not None for r in c) else "not scored"
                     for c, name in zip(cells, columns)]
            lines.append(f"| {label} | " + " | ".join(texts) + " |")
    header = [f"| pose noise, {title} | " + " | ".join(f"{d:g}° / {SHIFT_PER_DEGREE * d:.0%}" for d in POSE_DEGREES)
              + " |", "|---|" + "---|" * len(POSE_DEGREES)]
    return header + lines if lines else []


def pose_score_spreads(rows: list[dict], column: str = "psnr_pose_fitted") -> list[tuple[float, dict]]:
    """(spread over seeds, configuration) of the pose study's default runs, scored by `column`
    (default: with the held-out poses fitted)."""
    out = []
    for _, scene, fraction, refine in pose_settings():
        if refine is not None:
            continue
        for degrees in POSE_DEGREES:
            match = base(scene, "fast", fraction=fraction, pose_degrees=degrees)
            s = stats(group(rows, **match), column)
            if s and s["n"] >= 2:
                out.append((s["spread"], match))
    return out


def pose_check_kept(rows: list[dict]) -> str:
    """'2 of 3': in how many of a configuration's runs the default's pose check kept refining."""
    decided = [r.get("pose_check_refining") for r in rows if r.get("pose_check_refining") is not None]
    return f"{sum(decided)} of {len(decided)}" if decided else "not recorded"


def losses_table(rows: list[dict]) -> list[str]:
    lines = ["| scene | training views | off | on (the paper's losses) | gain | steps off / on (mean) "
             "| passes with them on | the default at that rate | the default, run (what it did) |",
             "|---|---|---|---|---|---|---|---|---|"]
    timed = [r for r in rows if r.get("minutes") and r.get("consistency") is not None]
    batch = get_preset("fast").batch_size
    for scene in dict.fromkeys([*LOSSES_PLAN, *(r["scene"] for r in timed)]):
        for fraction in sorted({r["fraction"] for r in timed if r["scene"] == scene}, reverse=True):
            minutes = next(r["minutes"] for r in timed if r["scene"] == scene)
            off, on = (group(rows, preset="fast", **base(scene, fraction=fraction, consistency=c, minutes=minutes))
                       for c in (False, True))
            a, b = stats(off), stats(on)
            if not (a or b):
                continue
            gain = f"{b['mean'] - a['mean']:+.2f} dB" if a and b else "-"
            steps = "/".join(f"{np.mean([r['steps_done'] for r in c if r.get('status') == 'finished']):.0f}" if c else "-"
                             for c in (off, on))
            views = next((r.get("train_views") for r in off + on if r.get("train_views")), "?")
            deep = next((r["deep_scene"] for r in off + on if "deep_scene" in r), None)
            done_on = [r["steps_done"] for r in on if r.get("status") == "finished"]
            passes = (np.mean(done_on) * batch / (views * image_pixels(on[0]["path"], on[0]["scale"]))
                      if done_on and isinstance(views, int) else None)
            # What the default decides when its minutes buy the steps these runs made (rules.default_consistency).
            rule = None if deep is None or passes is None else losses_by_default(deep, views, passes)
            default = {None: "?", True: "on", False: "off", LOSSES_UNTIL_POSES_RIGHT: "on until the pose check"}[rule]
            passes_text = "-" if passes is None else f"{passes:.0f}"
            ran = group(rows, preset="fast", **base(scene, fraction=fraction, consistency=None, minutes=minutes))
            lines.append(f"| {scene} | {views} | {cell(off)} | {cell(on)} | {gain} | {steps} | {passes_text} | {default} "
                         f"| {losses_default_cell(ran)} |")
    return lines


def losses_default_cell(runs: list[dict]) -> str:
    """The default's runs of a losses-study row: their PSNR and, per seed, how long the losses
    ran ("off", "on", or "to step N" where the pose check stopped them)."""
    if not runs:
        return "-"
    what = ["off" if not r.get("multiview_losses") else f"to step {r['losses_until_step']}"
            if r.get("losses_until_step") is not None else "on" for r in sorted(runs, key=lambda r: r["seed"])]
    return f"{cell(runs)} ({', '.join(what)})"


@functools.lru_cache(maxsize=None)
def image_pixels(path: str, scale: float) -> int:
    """Pixels of one training photo of the scene at `path` at `scale` (its photos share a size).
    Cached: the losses table asks once per row, and each ask would read the COLMAP model again."""
    width, height = scaled_size(load_any(path).views[0].size, scale)
    return width * height


def coarse_table(rows: list[dict]) -> list[str]:
    lines = ["| scene | training views | without | with (the default) | gain |", "|---|---|---|---|---|"]
    without = [r for r in rows if r.get("coarse_to_fine") is False]
    for scene in dict.fromkeys(r["scene"] for r in without):
        for fraction in sorted({r["fraction"] for r in without if r["scene"] == scene}, reverse=True):
            off = group(rows, preset="fast", **base(scene, fraction=fraction, coarse_to_fine=False))
            on = group(rows, preset="fast", **base(scene, fraction=fraction))
            a, b = stats(off), stats(on)
            if not (a and b):
                continue
            views = next((r.get("train_views") for r in off + on if r.get("train_views")), "?")
            lines.append(f"| {scene} | {views} | {cell(off)} | {cell(on)} | {b['mean'] - a['mean']:+.2f} dB |")
    return lines


def runs_table(rows: list[dict]) -> list[str]:
    lines = ["| model | runs | finished | crashed | NaN/skip warnings | steps per run | mean s per run "
             "| ms per step (wall clock, shared machine) |",
             "|---|---|---|---|---|---|---|---|"]
    for label, preset, timed in (("fast", "fast", False), ("fast, equal time (losses study)", "fast", True),
                                 ("paper", "paper", False)):
        c = [r for r in group(rows, preset=preset) if bool(r.get("minutes")) == timed]
        if not c:
            continue
        ok = [r for r in c if r.get("status") == "finished"]
        seconds = [r["train_seconds"] for r in ok]
        steps = sorted({r["steps_done"] for r in ok})
        steps = steps if not timed or not steps else [f"{min(steps)}-{max(steps)}"]
        per_step = [1000 * r["train_seconds"] / max(r["steps_done"], 1) for r in ok]
        lines.append(f"| {label} | {len(c)} | {len(ok)} | {sum(r.get('status') == 'crashed' for r in c)} | "
                     f"{sum(int(r.get('warnings', 0)) for r in c)} | {'/'.join(map(str, steps))} | "
                     f"{np.mean(seconds) if seconds else math.nan:.0f} | {np.mean(per_step) if per_step else math.nan:.0f} |")
    return lines


def targets(rows: list[dict]) -> list[str]:
    """The issue's targets, checked on the default model."""
    out = []
    for scene in FEWER_VIEWS_SCENES:
        first, last = stats(group(rows, **base(scene, "fast"))), stats(group(rows, **base(scene, "fast", fraction=0.25)))
        if first and last:
            loss = first["mean"] - last["mean"]
            error = difference_standard_error(first, last)
            uncertainty = f" ± {error:.2f} (standard error, {first['n']} / {last['n']} seeds)" if math.isfinite(error) else ""
            out.append(f"- 100% -> 25% views on {scene}: {loss:.2f}{uncertainty} dB lost (target ≤ 1.5): "
                       f"{'met' if loss <= 1.5 else 'MISSED'}")
    spreads = []
    for match in configurations(rows, "fast"):
        if match["minutes"]:  # wall-clock budgets also vary with the machine's load, not only the seed
            continue
        s = stats(group(rows, **match))
        if s and s["n"] >= 2:
            spreads.append((s["spread"], match, group(rows, **match)))
    if spreads:
        worst = max(spreads, key=lambda x: x[0])
        within = sum(s <= 0.2 for s, _, _ in spreads)
        out.append(f"- seed spread (max-min over seeds), fast: worst {worst[0]:.2f} dB ({describe(worst[1])}); "
                   f"{within} of {len(spreads)} configurations within 0.2 dB (target ≤ 0.2): "
                   f"{'met' if worst[0] <= 0.2 else 'MISSED'}")
        out += [f"  - {line}" for line in spread_by_setting(spreads)]
        out += spread_line(pose_score_spreads(rows), "the default's pose-noise configurations scored with the "
                           "held-out poses fitted (BARF's protocol)")
        out += spread_line([(s, m) for s, m in pose_score_spreads(rows, "psnr_noise_part_aligned") if m["pose_degrees"]],
                           "the default's noisy-pose configurations scored with the held-out views moved by the "
                           "noise's depth-like part")
    for name, nominal_scene, jittered in EXPOSURE_SCENES:
        out += exposure_targets(rows, name, nominal_scene, jittered)
    crashed = sum(r.get("status") == "crashed" for r in rows)
    warned = sum(int(r.get("warnings", 0)) for r in rows)
    nonfinite = sum(int(r.get("nonfinite_pixels", 0) or 0) for r in rows)
    out.append(f"- NaN/crash: {crashed} crashed runs, {warned} non-finite-loss warnings, {nonfinite} non-finite pixels "
               f"in {len(rows)} runs: {'met' if not (crashed or warned or nonfinite) else 'MISSED'}")
    return out


def spread_line(spreads: list[tuple[float, dict]], what: str) -> list[str]:
    """The targets' line for (spread, configuration) pairs scored otherwise: how many are within
    0.2 dB, and the widest three beyond it ([] without pairs)."""
    if not spreads:
        return []
    within = sum(s <= 0.2 for s, _ in spreads)
    widest = "; ".join(f"{describe(m)}: {s:.2f}" for s, m in sorted(spreads, key=lambda x: -x[0])[:3] if s > 0.2)
    return [f"  - {what}: {within} of {len(spreads)} within 0.2 dB" + (f" (widest: {widest})" if widest else "")]


def setting_of(match: dict, rows: list[dict] = ()) -> str:
    """Which kind of run a configuration is: the default as a user runs it, or with one of
    the default's rules (pose check, exposure, losses, coarse to fine) switched off or forced
    on for comparison.  `rows`: the
    configuration's runs, which record whether the exposure rule would have turned the
    compensation on (rows logged before the rule: off, as it is on every nominal capture)."""
    rule_wanted_appearance = any(r.get("appearance_default") for r in rows)
    if (match.get("coarse_to_fine") is not None or match.get("consistency") is not None
            or match.get("refine_poses") is not None or match.get("appearance")
            or (match.get("appearance") is False and rule_wanted_appearance)):
        return "with a default rule switched off or forced on (the rule studies)"
    return "the default as a user runs it"


def spread_by_setting(spreads: list[tuple[float, dict, list[dict]]]) -> list[str]:
    """'k of n within 0.2 dB (widest ...)' per kind of run."""
    out = []
    for kind in dict.fromkeys(setting_of(match, runs) for _, match, runs in spreads):
        mine = sorted(((s, m) for s, m, runs in spreads if setting_of(m, runs) == kind), key=lambda x: -x[0])
        within = sum(s <= 0.2 for s, _ in mine)
        widest = "; ".join(f"{describe(m)}: {s:.2f}" for s, m in mine[:3] if s > 0.2)
        out.append(f"{kind}: {within} of {len(mine)} within 0.2 dB" + (f" (widest: {widest})" if widest else ""))
    return out


def configurations(rows: list[dict], preset: str) -> list[dict]:
    """The distinct configurations (everything but the seed) that `preset` was run in."""
    keys = {(r["scene"], r["fraction"], r["pose_degrees"], r["appearance"], r["refine_poses"], r["consistency"],
             r["minutes"], r["coarse_to_fine"]) for r in rows if r["preset"] == preset}
    ordered = sorted(keys, key=lambda k: tuple(-1 if v is None else v for v in k))  # consistency may be None
    return [base(scene, preset, *rest) for scene, *rest in ordered]


def describe(match: dict) -> str:
    parts = [match["scene"], match["preset"]]
    if match.get("fraction", 1.0) != 1.0:
        parts.append(f"{match['fraction']:.0%} views")
    if match.get("pose_degrees"):
        parts.append(f"pose noise {match['pose_degrees']:g}°")
    if match.get("appearance"):
        parts.append("appearance")
    elif match.get("appearance", False) is None:
        parts.append("appearance by the default's rule")
    if match.get("refine_poses") is not None:
        parts.append(f"pose refinement {'on' if match['refine_poses'] else 'off'}")
    if match.get("consistency") is not None:
        parts.append(f"losses {'on' if match['consistency'] else 'off'}")
    if match.get("minutes"):
        parts.append(f"{match['minutes']:g} min")
    if match.get("coarse_to_fine") is not None:
        parts.append(f"coarse to fine {'on' if match['coarse_to_fine'] else 'off'}")
    return ", ".join(parts)


def tables_markdown(rows: list[dict], meta: dict) -> str:
    sections = [
        f"Generated {meta['date']} on {meta['machine']}; fast: {meta['fast_steps']} steps, paper: "
        f"{meta['paper_steps']} steps; seeds {meta['seeds']}; cells: mean ± spread (max - min) of the held-out PSNR "
        "in dB over the seeds, n = number of seeds where fewer than 3.", *random_start_note(rows), *older_surface_note(rows),
        *older_pose_gauge_note(rows),
        *older_restart_rule_note(rows),
        "", "### Fewer views", "", f"Training views kept ({', '.join(map(lambda f: f'{f:.0%}', FRACTIONS))}): "
        f"{train_view_counts(rows)}.", "", *views_table(rows),
        "", "### View-dependent effects and fine texture (synthetic scene, all training views)", "", *variants_table(rows),
        "", "### Exposure (fast; synthetic scene, held-out views scored against the nominal-exposure render)", "",
        *exposure_table(rows),
        "", "### Pose noise (fast; the synthetic Lambertian scene and CanClip, all training views, and the default on a quarter of them; rotation / translation as a share of the camera spacing)", "",
        *pose_table(rows),
        "", f"### The paper's multi-view losses with fewer views (fast; equal time, {meta.get('losses_minutes', 1.0):g} min "
        f"per run; seeds {meta.get('losses_seeds', '0,1')}; the default turns them on for deep scenes with at most "
        f"{CONSISTENCY_ALWAYS_MAX_VIEWS} training views when the budget passes over their pixels at least "
        f"{LOSSES_MIN_PASSES:g} times, with up to {CONSISTENCY_MAX_VIEWS} until the pose check finds the poses right "
        "(unless the photos' colours are learned), never for shallow scenes; the passes "
        "counted at the step rate the run measures; these runs have right poses)", "", *losses_table(rows),
        "", f"### Coarse to fine with fewer views (fast; the default turns it on with at most {COARSE_TO_FINE_MAX_VIEWS} "
        "training views)", "", *coarse_table(rows),
        "", "### Runs", "", *runs_table(rows),
        "", "### Targets (issue 4)", "", *targets(rows),
    ]
    return "\n".join(sections)


def runs_by_study(runs: list[dict]) -> str:
    """How many of `runs` each study holds: "14 losses, 30 pose, 18 others"."""
    studies = {"losses": sum(bool(r["minutes"]) for r in runs), "pose": sum(bool(r["pose_degrees"]) for r in runs)}
    studies["others"] = len(runs) - studies["losses"] - studies["pose"]
    return ", ".join(f"{n} {name}" for name, n in studies.items() if n)


def random_start_note(rows: list[dict]) -> list[str]:
    """Which of the default's runs still have the colour decoder's random start (trained before the
    learned start became the default and not re-run since), by study."""
    fast = [r for r in rows if r["preset"] == "fast"]
    old = [r for r in fast if r.get("colour_start", "random") == "random"]
    if not old:
        return []
    return ["", f"**{len(old)} of the default's {len(fast)} runs were trained before its learned colour start "
                f"(`colour_start` random in docs/stability.csv: {runs_by_study(old)}); their rows stand until the "
                "study re-runs them.**"]


def stale_rows_note(old: list[dict], trained: str) -> list[str]:
    """The report's note on `old`, logged rows that stand until the study re-runs them:
    `trained` says how they were trained, ending in an open bracket that the runs by study
    close."""
    if not old:
        return []
    return ["", f"**{len(old)} {trained}: {runs_by_study(old)}); their rows stand until the study re-runs them.**"]


def older_surface_note(rows: list[dict]) -> list[str]:
    """Which runs of deep scenes were trained with one surface, or with the surfaces blended
    otherwise than the default now blends them, and not re-run since, by study."""
    old = [r for r in rows if trained_with_another_surface_mix(r)]
    one = sum(r.get("back_surface") is None for r in old)
    return stale_rows_note(old, f"runs of deep scenes were trained before their default's surfaces ({one} with one "
                                f"surface, `back_surface` empty in docs/stability.csv; {len(old) - one} blending "
                                "colours, `back_surface_blend` empty or `colour`")


def older_pose_gauge_note(rows: list[dict]) -> list[str]:
    """Which runs refined their poses with the corrections' depth-like part held otherwise than
    the code now holds it (poses.DEPTH_LIKE_GAUGE) and were not re-run since, by study."""
    return stale_rows_note([r for r in rows if trained_with_another_pose_gauge(r)],
                           "runs that refined their poses held the corrections' depth-like part by the weak prior "
                           "it had before (`pose_gauge` empty in docs/stability.csv")


def older_restart_rule_note(rows: list[dict]) -> list[str]:
    """Which runs started their field again for far-off poses otherwise than pose_check.poses_far_off
    and pose_check.many_photos_held now decide, and were not re-run since, by study."""
    return stale_rows_note([r for r in rows if trained_with_another_restart_rule(r)],
                           "runs started their field again for far-off poses otherwise than the rule now decides "
                           f"(before the fifty-fifth session from {FAR_OFF_POSE_DEGREES:g}° whatever the photo count; "
                           "before the fifty-sixth all of it, not the geometry alone, with many photos; before the "
                           "fifty-seventh without starting the depth layers again, smoother")


def update_markdown(path: Path, tables: str, begin: str = MARKER_BEGIN, end: str = MARKER_END) -> None:
    """Replace the generated block (between `begin` and `end`) in `path`, keeping the
    hand-written text around it."""
    text = path.read_text() if path.is_file() else f"# Stability study\n\n{begin}\n{end}\n"
    if begin not in text:
        text += f"\n{begin}\n{end}\n"
    head, rest = text.split(begin, 1)
    tail = rest.split(end, 1)[1] if end in rest else ""
    path.write_text(f"{head}{begin}\n{tables}\n{end}{tail}")


CSV_COLUMNS = ["scene", "preset", "fraction", "pose_degrees", "appearance", "refine_poses", "consistency", "minutes",
               "coarse_to_fine", "colour_start", "coarse_to_fine_used", "appearance_used", "appearance_default", "exposure_difference_stops",
               "pose_check_refining", "pose_check_degrees", "pose_check_halfway", "pose_gauge", "field_restarted", "far_off_degrees", "far_off_points_held", "restart_geometry_only", "restart_depth_layers", "start_kept", "discarded_steps", "members", "members_passes", "member_poses", "members_split_used",
               "sweep_fade", "deep_scene", "multiview_losses", "losses_until_step", "back_surface", "back_surface_blend", "pixel_jitter", "two_starts", "members_split", "seed", "status", "psnr", "ssim",
               "psnr_matched", "psnr_half_fit", "psnr_pose_fitted", "pose_fit_degrees", "psnr_per_view", "psnr_noise_part_aligned",
               "psnr_per_view_noise_part_aligned", "train_views", "held_out", "steps", "steps_done", "train_seconds",
               "wall_seconds", "warnings", "warning_text", "nonfinite_pixels", "error", "scale", "path", "truth"]


def write_csv(rows: list[dict], path: Path, columns: list[str] = CSV_COLUMNS) -> None:
    """One row per run.  Floats are written in full: a fresh machine regenerates the tables from
    this file (seed_log_from_csv), and values rounded here moved spreads that sat on a rounding
    boundary (21.66 ± 0.13 from the run log read 0.12 from 4 decimals)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=columns, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)


def chart(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(18, 4.4), gridspec_kw={"width_ratios": [1, 1, 1.1]})
    style = {"fast": "-o", "paper": "--s"}
    for scene, colour in zip(FEWER_VIEWS_SCENES, ("C0", "C2", "C1")):
        for preset in ("fast", "paper"):
            points = [(f, stats(group(rows, **base(scene, preset, fraction=f)))) for f in FRACTIONS]
            points = [(f, s) for f, s in points if s]
            if points:
                errorbar(axes[0], points, style[preset], colour, f"{scene}, {preset}")
    axes[0].set(xlabel="share of the training views", ylabel="held-out PSNR (dB)", title="Fewer views")
    axes[0].invert_xaxis()

    labels = ["lambertian", "shiny", "fine", "jitter ±1 stop", "jitter + appearance"]
    keys = [base("lambertian"), base("shiny"), base("fine"), base("jitter1"), base("jitter1", appearance=None)]
    for offset, preset in ((-0.2, "fast"), (0.2, "paper")):
        xs, means, errs = [], [], []
        for i, key in enumerate(keys):
            s = stats(group(rows, **{**key, "preset": preset}))
            if s:
                xs.append(i + offset)
                means.append(s["mean"])
                errs.append(s["spread"] / 2)
        if xs:
            axes[1].bar(xs, means, 0.4, yerr=errs, capsize=3, label=preset)
    axes[1].set_xticks(range(len(labels)), labels, rotation=20)
    axes[1].set(ylabel="held-out PSNR (dB)", title="Scene variants and exposure")
    low = [r["psnr"] for r in rows if r.get("status") == "finished"]
    if low:
        axes[1].set_ylim(max(0, min(low) - 3), max(low) + 1)

    for scene, refine, fmt, colour, label in (("lambertian", None, "-s", "C4", "lambertian, fast (the default's pose check)"),
                                              ("lambertian", False, "-o", "C1", "lambertian, fast --no-refine-poses"),
                                              ("lambertian", True, "-^", "C3", "lambertian, fast + --refine-poses"),
                                              ("canclip", None, "--s", "C5", "canclip, fast (the default's pose check)"),
                                              ("canclip", False, "--o", "C0", "canclip, fast --no-refine-poses"),
                                              ("canclip", True, "--^", "C2", "canclip, fast + --refine-poses")):
        points = [(d, stats(group(rows, **base(scene, "fast", pose_degrees=d, refine_poses=refine))))
                  for d in POSE_DEGREES]
        points = [(d, s) for d, s in points if s]
        if points:
            errorbar(axes[2], points, fmt, colour, label)
    for scene, fraction, column, fmt, colour, label in (
            ("lambertian", 1.0, "psnr_pose_fitted", ":s", "C4", "lambertian, default, held-out poses fitted"),
            ("canclip", 1.0, "psnr_pose_fitted", ":s", "C5", "canclip, default, held-out poses fitted"),
            ("lambertian", POSE_FEW_VIEWS, "psnr", "-x", "C7", f"lambertian, default, {POSE_FEW_VIEWS:.0%} of the views"),
            ("canclip", POSE_FEW_VIEWS, "psnr", "--x", "C8", f"canclip, default, {POSE_FEW_VIEWS:.0%} of the views")):
        points = [(d, stats(group(rows, **base(scene, "fast", fraction=fraction, pose_degrees=d)), column))
                  for d in POSE_DEGREES]
        points = [(d, s) for d, s in points if s]
        if len(points) > 1:
            errorbar(axes[2], points, fmt, colour, label)
    axes[2].set(xlabel=f"pose noise (degrees; shift {SHIFT_PER_DEGREE:.0%} of the spacing per degree)",
                ylabel="held-out PSNR (dB)", title="Pose noise")
    for axis in axes:
        axis.grid(alpha=0.3)
        if axis.get_legend_handles_labels()[0]:
            # (the pose panel's ten lines: the legend beside it, not over them)
            axis.legend(fontsize=7, **({"loc": "upper left", "bbox_to_anchor": (1.02, 1.0)} if axis is axes[2] else {}))
    fig.suptitle("Stability: held-out PSNR, mean of seeds, bars = max-min spread")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def errorbar(axis, points, fmt, colour, label) -> None:
    xs = [p[0] for p in points]
    means = [p[1]["mean"] for p in points]
    half = [p[1]["spread"] / 2 for p in points]
    axis.errorbar(xs, means, yerr=half, fmt=fmt, color=colour, capsize=3, label=label)


def write_outputs(rows: list[dict], docs: Path, meta: dict) -> str:
    docs.mkdir(parents=True, exist_ok=True)
    write_csv(rows, docs / "stability.csv")
    chart(rows, docs / "stability.png")
    tables = tables_markdown(rows, meta)
    update_markdown(docs / "STABILITY.md", tables)
    return tables


# ----------------------------------------------------------------------------- main


def machine() -> str:
    cpu = platform.machine()
    try:
        cpu = next(line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
                   if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    trained_on = f"{torch.cuda.get_device_name(0)} (training; scoring on the CPU), " if torch.cuda.is_available() else ""
    return f"{trained_on}{cpu}, {os.cpu_count()} cores, torch {torch.__version__}, 1 torch thread per run"


def previous_generation(markdown: Path) -> dict | None:
    """The date and machine of the tables' last training run, from their header in `markdown`."""
    try:
        found = re.search(r"^Generated (\S+) on (.+?); fast: ", markdown.read_text(), re.MULTILINE)
    except OSError:
        return None
    return {"date": found.group(1), "machine": found.group(2)} if found else None


def generation(args) -> dict:
    """The date and machine for the tables' header: today and this machine; with
    --report-only (nothing trained here) the header's as it was; --machine names them
    where the runs came from more than one (a GPU's and a CPU's, say)."""
    generated = {"date": date.today().isoformat(), "machine": machine()}
    if args.report_only:
        generated = previous_generation(args.docs / "STABILITY.md") or generated
    if args.machine:
        generated = {**generated, "machine": args.machine}
    return generated


def csv_value(text: str):
    """A value of docs/stability.csv as it was logged: '' is None, then bool, int, float, text."""
    if text == "":
        return None
    if text in ("True", "False"):
        return text == "True"
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text


def read_csv_rows(table: Path) -> list[dict]:
    """The runs of a CSV write_csv wrote, each value as it was logged (csv_value)."""
    with open(table, newline="") as handle:
        return [{k: csv_value(v) for k, v in row.items()} for row in csv.DictReader(handle)]


def seed_log_from_csv(log: Path, table: Path) -> int:
    """Start a missing run log from the committed CSV (one row per run, every field a Job is
    keyed by): the log lives in the temp folder, which a fresh machine does not have, and
    without it the study would train all its runs again.  Returns the rows written."""
    if log.is_file() or not table.is_file():
        return 0
    rows = read_csv_rows(table)
    for row in rows:
        # The CSV kept no `member_poses` before 2026-11-28; a run of several members it holds was
        # reported, so it stood: it was trained with the later members following the first.
        if int(row.get("members") or 1) > 1 and row.get("member_poses") is None:
            row["member_poses"] = MEMBER_POSES
    log.parent.mkdir(parents=True, exist_ok=True)
    log.write_text("".join(json.dumps(row) + "\n" for row in rows))
    return len(rows)


def load_log(log: Path, older: dict | None = None, rescore: bool = False) -> dict:
    """key -> row of the logged runs the study counts as done.  `older`, a dict: gets the runs
    that stand but for their surfaces (trained_with_another_surface_mix) or their pose
    corrections' depth-like part (trained_with_another_pose_gauge), for the report until the
    study re-runs them; with `rescore` (the study's own log) also those that lack a score the
    study's tables now read (scored_without_noise_part)."""
    done = {}
    if log.is_file():
        for line in log.read_text().splitlines():
            row = json.loads(line)
            if row.get("status") in ("finished", "crashed") and not trained_with_another_fade(row) \
                    and not trained_with_other_members(row) and not trained_with_members_own_poses(row) \
                    and not trained_with_another_losses_rule(row):
                into = done
                if trained_with_another_surface_mix(row) or trained_with_another_pose_gauge(row) \
                        or trained_with_another_restart_rule(row) or (rescore and scored_without_noise_part(row)):
                    if older is None:
                        continue
                    into = older
                if "pose_check_refining" not in row:  # logged before the pose check: trained without refinement
                    row.setdefault("refine_poses", False)  # unless it says so
                    if row["refine_poses"] is False and not row.get("minutes") and row["steps"] < 2 * POSE_CHECK_STEP:
                        row["refine_poses"] = None  # too short for the check: the default trains it so too
                for f in fields(Job):  # rows logged before a Job field existed ran with its default
                    row.setdefault(f.name, f.default)
                into[Job(**{f.name: row[f.name] for f in fields(Job)}).key] = row
    return done


def report_rows(done: dict, jobs: list[Job], older: dict | None = None) -> list[dict]:
    """The logged rows of `jobs`.  A configuration not yet re-run with every seed since deep
    scenes' surfaces or the pose corrections' depth-like part last changed reports its runs as
    they were (`older`, from load_log), and one not re-run since the learned colour start its runs
    with the random start (logged before; the tables say how many), so no spread mixes the
    two."""
    configs: dict[str, list[Job]] = {}
    for job in jobs:
        configs.setdefault(job.configuration, []).append(job)
    rows = []
    for runs in configs.values():
        if not all(job.key in done for job in runs) and any(job.key in (older or {}) for job in runs):
            rows += [older[job.key] for job in runs if job.key in older]
            continue
        if not all(job.key in done for job in runs):
            runs = [replace(job, colour_start="random") for job in runs]
        rows += [done[job.key] for job in runs if job.key in done]
    return rows


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cache", type=Path, default=DEFAULT_CACHE, help="rendered scenes and the run log")
    parser.add_argument("--docs", type=Path, default=DOCS)
    parser.add_argument("--workers", type=int, default=2, help="runs side by side (each uses 1 torch thread)")
    parser.add_argument("--fast-steps", type=int, default=1000)
    parser.add_argument("--paper-steps", type=int, default=100)
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--paper-seeds", type=int, default=1, help="how many of the seeds the paper's network gets")
    parser.add_argument("--synth-scale", type=float, default=0.5, help="training scale of the 320x240 renders")
    parser.add_argument("--canclip", type=Path, default=CANCLIP)
    parser.add_argument("--canclip-scale", type=float, default=0.25)
    parser.add_argument("--hci", type=Path, default=HCI)
    parser.add_argument("--hci-scale", type=float, default=0.5)
    parser.add_argument("--fern", type=Path, default=FERN)
    parser.add_argument("--fern-scale", type=float, default=0.5, help="of fern's 504x378 images_8")
    parser.add_argument("--losses-minutes", type=float, default=1.0, help="the losses study's equal wall-clock budget")
    parser.add_argument("--losses-seeds", default="0,1,2,3")
    parser.add_argument("--only", default="views,variants,exposure,pose,losses,coarse")
    parser.add_argument("--defaults-only", action="store_true",
                        help="only the default as a user runs it (no paper network, no rule forced on or off)")
    parser.add_argument("--scenes", help="only these scenes (comma-separated labels: canclip, hci, lambertian, ...)")
    parser.add_argument("--fractions", help="only these shares of the training views (comma-separated: 0.25,1)")
    parser.add_argument("--pose-degrees", help="only these pose noises (comma-separated degrees: 0,0.5)")
    parser.add_argument("--by-configuration", action="store_true",
                        help="run one configuration's seeds after another (a run cut short keeps whole configurations)")
    parser.add_argument("--pack", type=Path, metavar="DIR",
                        help="write the study's scenes at their training scale into DIR (to run it on another machine, "
                             "e.g. a GPU one without Blender), print the arguments that use them, and stop")
    parser.add_argument("--fresh", action="store_true", help="ignore the runs already in the cache's log")
    parser.add_argument("--report-only", action="store_true", help="rewrite the docs from the log, train nothing")
    parser.add_argument("--machine", help="the machines the runs came from, for the tables' header (default: this "
                                          "one; with --report-only, the header's as it was)")
    return parser.parse_args(argv)


def pack(args, scenes: dict[str, Path], out: Path) -> str:
    """Copy what the study reads of its scenes into `out`, the real captures' photos already
    at their training scale (the same box filter load_rgb applies; the model's intrinsics
    are rescaled to the files' size at load) and the synthetic renders as they are (their
    depth maps left out).  Returns the arguments that run the study on the copy."""
    out = out.resolve()
    for name in ("lambertian", "shiny", "fine", "jitter1"):
        source = scenes[name]
        target = out / "scenes" / source.name
        for part in ("images", "sparse_gt"):
            shutil.copytree(source / part, target / part, dirs_exist_ok=True)
        (target / "ground_truth").mkdir(parents=True, exist_ok=True)
        shutil.copy2(source / "ground_truth" / "cameras.json", target / "ground_truth" / "cameras.json")
        shutil.copy2(source / "summary.json", target / "summary.json")
    arguments = [f"--cache {out}"]
    for name, scale in (("canclip", args.canclip_scale), ("hci", args.hci_scale)):
        if name not in scenes:
            continue
        scene = load_scene(scenes[name])
        target = out / name
        model = find_model_dir(scenes[name])
        shutil.copytree(model, target / "sparse" / "0", dirs_exist_ok=True)
        (target / "images").mkdir(parents=True, exist_ok=True)
        for view in scene.views:
            if view.image_path.suffix.lower() != ".png":  # a lossy copy would not be the photo the study trains on
                raise SystemExit(f"--pack copies PNG photos only; {view.image_path} is not one")
            save_rgb(target / "images" / view.image_path.name, view.load_image(scale))
        arguments.append(f"--{name} {target} --{name}-scale 1")
    return " ".join(arguments)


def missing_captures_would_be_dropped(args) -> bool:
    """Whether a capture the study's CSV holds runs of is not where --canclip / --hci / --fern say:
    its rows would vanish from docs/ (the tables are written from the planned jobs), so the study
    says which and writes nothing; into another --docs folder a part of the study is written."""
    table = args.docs / "stability.csv"
    logged = {row["scene"] for row in read_csv_rows(table)} if table.is_file() else set()
    missing = [(name, path) for name, path in (("canclip", args.canclip), ("hci", args.hci), ("fern", args.fern))
               if not path.is_dir() and name in logged]
    if not missing or args.docs.resolve() != DOCS.resolve():
        for name, path in missing:
            print(f"skip {name}: {path} not found; its runs are left out of {args.docs}", flush=True)
        return False
    shown = ", ".join(f"{name} ({path})" for name, path in missing)
    print(f"skip: the captures {shown} are not there, and writing docs/ without them would drop their rows of "
          f"{table}; give --canclip / --hci / --fern DIR, or --docs ANOTHER_FOLDER for a part of the study. Nothing "
          "was written.", flush=True)
    return True


def main(argv=None) -> None:
    args = parse_args(argv)
    if not args.pack and missing_captures_would_be_dropped(args):
        return
    args.cache.mkdir(parents=True, exist_ok=True)
    scenes = {v: render_synthetic(args.cache, v) for v in ("lambertian", "shiny", "fine")}
    scenes["jitter1"] = render_synthetic(args.cache, "lambertian", 1.0)
    exposure = check_same_cameras(scenes["lambertian"], scenes["jitter1"])
    print(f"exposure study: same cameras with and without jitter; exposures within ±{exposure['max_abs_stops']:.2f} "
          f"stops, mean {exposure['mean_stops']:+.2f}", flush=True)
    if args.canclip.is_dir():
        scenes["canclip"] = args.canclip
        scenes["canclip_jitter1"] = jitter_capture_exposures(args.cache, args.canclip)
    if args.hci.is_dir():
        scenes["hci"] = args.hci
    if args.fern.is_dir():
        scenes["fern"] = args.fern
    if not appearance_available():
        print("note: TrainConfig has no 'appearance' option yet; those runs are marked unavailable", flush=True)
    if args.pack:
        print(pack(args, scenes, args.pack))
        return
    jobs = plan(args, scenes)
    log = args.cache / "runs.jsonl"
    if not args.fresh and (seeded := seed_log_from_csv(log, args.docs / "stability.csv")):
        print(f"no run log in {args.cache}: started it from {args.docs / 'stability.csv'} ({seeded} runs)", flush=True)
    older = {}
    done = {} if args.fresh else load_log(log, older, rescore=True)
    if args.report_only:
        rows = report_rows(done, jobs, older)
    else:
        rows = run_jobs(jobs, args.workers, done, log, by_configuration=args.by_configuration)
    meta = {**generation(args), "fast_steps": args.fast_steps,
            "paper_steps": args.paper_steps, "seeds": args.seeds, "losses_minutes": args.losses_minutes,
            "losses_seeds": args.losses_seeds}
    print(write_outputs(rows, args.docs, meta))


if __name__ == "__main__":
    main()

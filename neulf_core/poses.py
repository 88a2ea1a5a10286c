"""Per-photo pose refinement: a small learned rotation and shift of each training camera.

A light field is unforgiving of pose error: every training ray is stored at the (u, v, s, t)
its camera's pose gives it, and a camera that is off by a quarter of a pixel writes its
photo's colours onto the wrong rays, where they fight the neighbours' (docs/STABILITY.md:
0.1 degree of noise costs about 1 dB).  Here each training view gets a rotation about its
own centre and a shift, both zero at the start, learned with the field by the same
photometric loss (as BARF and NeRF-- do for radiance fields).

The correction acts on the stored rays themselves: a ray's two slab crossings are two
points on a line through its camera's centre; moving those points with the camera and
intersecting the moved line with the two planes again gives the corrected (u, v, s, t).
So no per-ray bearing is kept and a batch costs a few arithmetic operations per ray.

The corrections are centred (their mean over the views is zero): moving all cameras
together is the same as moving the scene, which would shift the light field away from
the held-out cameras' (and any render camera's) frame.

They move from the first step, but for the first fifth of the budget only in the part of
each correction that is the camera's own: what varies linearly with the cameras' positions
on the uv plane (the rig fanning in or out, turning about its middle) is held at zero until
then.  For a forward-facing rig such a rig-wide correction looks, to the photos, almost like
a change of the scene's depth, so while the field is still noise nothing holds it and it
drifts (exact poses, corrections from the first step: 0.09 degrees after 1000 steps, -1.7 dB
on the synthetic scene).  The camera's own part is what a reconstruction's error mostly is,
and learning it from the start lets the corrections travel far (CanClip, 0.5 degrees of
noise: +4 dB over starting them at a fifth of the budget, measured with the study's first,
uncentred noise; with the noise centred the refinement leaves 1.8 dB of the 11.6 it costs;
docs/STABILITY.md, "Pose refinement").
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import torch
from torch import nn

from .scene import camera_spacing
from .dataset import view_uvst
from .rows import rows_of
from .slab import Slab

# Share of the budget during which the corrections have no rig-wide part (see above).
RIG_WIDE_START = 0.2

# Of the rig-wide part, two directions are a change of the scene's depth to a light field:
# the cameras fanning out in proportion to their position on the uv plane (each image shifts
# by a constant times the camera's position, as a uniform change of inverse depth shifts it;
# only the slight keystone of a turned view tells them apart) and the rig's baseline growing
# (each shift in proportion to the position, which scales every disparity).  The photos do
# not pin them, so the corrections hold neither: both are projected out, as the centring
# projects out the mean (DEPTH_LIKE_GAUGE: the field stays in the frame of the cameras the
# user imported, and every seed in the same one).
# Until the fifty-fourth session a weak prior (1e-3 times their mean square, in degrees and
# tenths of the spacing) held them instead, and the fanning drifted anyway, always the same
# way: +0.03 to +0.21 degrees of fanning on the synthetic scene where the noise needed 0.008
# to 0.05 (docs/STABILITY.md, fifty-fourth session).  Held exactly, the synthetic scene's 14
# photos at 0.1 / 0.25 / 0.5 degrees of noise went from 30.10 +- 0.81 / 30.11 +- 0.20 / 29.83
# +- 0.30 dB to 30.47 +- 0.11 / 30.57 +- 0.30 / 30.16 +- 0.08 (the stability study: 1000
# steps, seeds 0 / 1 / 2; over its 20 noisy-pose configurations a median 0.00 dB).  Its 4
# photos lost 0.15-0.54 dB, where that drift happened to lean the way the study's fixed noise
# draw needs: with the draw's sign flipped the same 4 photos at 0.25 degrees scored 28.67 with
# the prior and 28.99 held.  Over four noise draws (seeds 0 / 1 each, fifty-sixth session) the
# 4 photos are level: held minus prior +0.04 dB at 0.25 degrees, +0.05 at 0.5 (-0.56 to +0.97 by
# draw; the study's draw is the worst at 0.25).
DEPTH_LIKE_GAUGE = "held"

# The pose check (the trainer's default, TrainConfig.refine_poses None): the corrections move
# from the first step, and after POSE_CHECK_STEP steps the median rotation of the cameras' own
# part says whether the poses are off: they are where it is at least POSE_CHECK_DEGREES.
# Where the poses agree with the photos the corrections only drift, and the refinement would
# cost up to a few tenths of a dB; where they are off it recovers most of what the error
# costs.  Measured at step 100 of 1000-step budgets (docs/STABILITY.md, "The pose check"):
# - right poses: 0.011-0.039 degrees on every capture of the study at every share of its
#   photos; up to 0.051 with few photos or exposures that differ (the colour transform not yet
#   learned, the corrections take up some of the difference), 0.059 on fern, 0.067-0.092 where
#   the photos' exposures differ and the colour transform is forced off;
# - 0.1 degrees of centred noise 0.086-0.236, and more noise more (the synthetic scene's 4
#   photos 0.050-0.069); 0.05 degrees 0.040-0.061, which it cannot tell from right poses;
# - Statue's COLMAP poses 0.062-0.076 (0.099-0.137 before the learned colour start).
# Until the thirty-fifth session the corrections also had to be no smaller than 0.8 times
# their size at step 50: Statue's shrink (0.50-0.73 times), and refining there cost 0.2 dB at
# the benchmark's 1.5 minutes.  With the depth-like part held (then by the prior) it no longer costs: Statue
# refined against not, 1000 steps at scale 0.25, seeds 0 / 1 / 2, -0.05 / -0.01 / +0.20 dB; at
# 1.5 minutes at scale 0.5, seed 1 (where the old rule dropped it), +0.42 dB.  And the
# condition dropped real errors too, where their corrections happened to shrink (0.68-0.79
# times): on the synthetic scene with 0.1 degrees of noise one seed of three at 3000 steps,
# 0.77 dB below the other two, and on its 4 photos refining gains 0.19 dB (28.55 +- 0.39 ->
# 28.74 +- 0.09, the refinement forced on).  So the size decides (with a second look where
# it is unsure, below); the trainer still records the statistic halfway to the check
# (model.json, "pose_check") for the study.
# The statistic hardly moves from step 100 to step 700, nor with a 3000-step budget.
POSE_CHECK_STEP = 100
POSE_CHECK_DEGREES = 0.06
# A second look for the statistic that is neither: from POSE_CHECK_UNSURE_DEGREES up to
# POSE_CHECK_DEGREES at step 100 the refinement goes on, and at POSE_SECOND_LOOK_STEP the
# poses are off where it is at least POSE_SECOND_LOOK_DEGREES.  At step 100 few photos with
# 0.1 degrees of noise (the synthetic scene's 4: 0.050-0.069) and right poses (up to 0.059,
# fern with the multi-view losses) overlap; by step 200 the drift of right poses has settled
# and they part: right poses 0.010-0.032 (the synthetic scene's 4 photos, CanClip's 6, fern's
# 4 / 8 / 17, CanClip's 26 with the multi-view losses), 0.1 degrees of noise on the 4 photos
# 0.060-0.070 (docs/STABILITY.md, thirty-fifth session; 1000-step budgets, where the rig-wide
# part joins at step 200, just after the look; with shorter budgets it has joined before,
# which shrinks the statistic, so there the second look leans to right poses).  Only runs in
# the band train differently from a check at step 100 alone, and those refine 100 steps
# longer.
POSE_CHECK_UNSURE_DEGREES = 0.04
POSE_SECOND_LOOK_STEP = 200
POSE_SECOND_LOOK_DEGREES = 0.045


def poses_look_off(degrees: float, second_look: bool = False) -> bool | None:
    """The pose check's verdict from its statistic: at POSE_CHECK_STEP True (off: refine on),
    False (right: drop the corrections) or None (unsure: look again at POSE_SECOND_LOOK_STEP);
    at the second look True or False."""
    if second_look:
        return degrees >= POSE_SECOND_LOOK_DEGREES
    if degrees >= POSE_CHECK_DEGREES:
        return True
    return None if degrees >= POSE_CHECK_UNSURE_DEGREES else False


def rotation_matrices(axis_angle: torch.Tensor) -> torch.Tensor:
    """(V, 3) axis-angle vectors (radians) -> (V, 3, 3) rotations (Rodrigues' formula).

    sin(a)/a and (1 - cos a)/a^2 are taken by their series, which are smooth at a = 0 (where
    every correction starts) and within 2e-7 of the exact values up to 0.3 rad (17 degrees),
    far beyond any pose correction."""
    angle_sq = (axis_angle ** 2).sum(1, keepdim=True)
    a = 1 - angle_sq / 6 + angle_sq ** 2 / 120
    b = 0.5 - angle_sq / 24 + angle_sq ** 2 / 720
    x, y, z = axis_angle.unbind(1)
    zero = torch.zeros_like(x)
    k = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], 1).reshape(-1, 3, 3)
    eye = torch.eye(3, device=axis_angle.device, dtype=axis_angle.dtype).expand_as(k)
    return eye + a[..., None] * k + b[..., None] * (k @ k)


def own_part_projector(positions: np.ndarray) -> np.ndarray:
    """(V, V) matrix that removes from per-view values (one row per view) their least-squares
    fit by a + b . position: what is left is each camera's own part.  `positions`: (V, 2)
    camera positions on the uv plane.  Cameras on a line (or too few to fit a plane) lose only
    what their positions can tell apart."""
    positions = np.asarray(positions, dtype=np.float64)
    basis = np.column_stack([np.ones(len(positions)), positions - positions.mean(0)])
    return np.eye(len(positions)) - basis @ np.linalg.pinv(basis)


class PoseRefinement(nn.Module):
    """Learned corrections of the training cameras, applied to their rays' (u, v, s, t)."""

    def __init__(self, slab: Slab, centres_world: np.ndarray, centred: bool = True, spacing: float | None = None):
        super().__init__()
        self.centred = centred  # False: each camera on its own (fitting one held-out camera, fit_view_pose)
        centres = slab.to_slab(np.asarray(centres_world, dtype=np.float64))
        spacing = camera_spacing(centres) if spacing is None else spacing  # (default: these cameras')
        self.slab = slab
        self.register_buffer("centres", torch.as_tensor(centres, dtype=torch.float32))
        # Shifts are learned in units of the camera spacing, so one learning rate suits every
        # scene's units; rotations in radians.
        self.spacing = spacing
        self.rotation = nn.Parameter(torch.zeros(len(centres), 3))
        self.shift = nn.Parameter(torch.zeros(len(centres), 3))
        # Not saved: it follows from the centres, and models saved before it load as they were.
        self.register_buffer("own_part", torch.as_tensor(own_part_projector(centres[:, :2] / spacing), dtype=torch.float32),
                             persistent=False)
        self.own_part_only = False
        # The two depth-like directions (DEPTH_LIKE_GAUGE) as unit vectors over all views' values;
        # both are orthogonal to the mean (the positions are centred).
        position = torch.as_tensor(centres[:, :2] - centres[:, :2].mean(0), dtype=torch.float32)
        zero = torch.zeros_like(position[:, 0])
        fanning = torch.stack([-position[:, 1], position[:, 0], zero], 1)  # the view turns toward +u at +u, +v at +v
        baseline = torch.stack([position[:, 0], position[:, 1], zero], 1)
        self.register_buffer("fanning", fanning / fanning.norm().clamp_min(1e-12), persistent=False)
        self.register_buffer("baseline", baseline / baseline.norm().clamp_min(1e-12), persistent=False)

    def set_training_progress(self, fraction: float) -> None:
        """The trainer calls this every step: the rig-wide part joins at RIG_WIDE_START."""
        self.own_part_only = fraction < RIG_WIDE_START

    def corrections(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Centred per-view (axis-angle radians, shift in scene units), slab frame, without the
        two depth-like directions (DEPTH_LIKE_GAUGE)."""
        if not self.centred:
            return self.rotation, self.shift * self.spacing
        if self.own_part_only:
            return self.own_part @ self.rotation, (self.own_part @ self.shift) * self.spacing
        rotation, shift = self.rotation - self.rotation.mean(0), self.shift - self.shift.mean(0)
        rotation = rotation - (rotation * self.fanning).sum() * self.fanning
        shift = shift - (shift * self.baseline).sum() * self.baseline
        return rotation, shift * self.spacing

    def corrected_centres(self) -> torch.Tensor:
        """(V, 3) the cameras' centres after their shifts, slab frame (a rotation about a centre
        leaves it in place)."""
        return self.centres + self.corrections()[1]

    def forward(self, uvst: torch.Tensor, view_index: torch.Tensor) -> torch.Tensor:
        rotation, shift = self.corrections()
        turn, moved, centre = rows_of(rotation_matrices(rotation), view_index), rows_of(shift, view_index), \
            self.centres[view_index]
        p_uv, p_st = self.slab.plane_crossings(uvst)
        # Both crossings move with the camera: about its centre, then by its shift.
        a = centre + torch.bmm(turn, (p_uv - centre).unsqueeze(-1)).squeeze(-1) + moved
        b = centre + torch.bmm(turn, (p_st - centre).unsqueeze(-1)).squeeze(-1) + moved
        return self.slab.slab_rays_to_uvst(a, b - a)[0]

    @torch.no_grad()
    def own_part_degrees(self) -> float:
        """The pose check's statistic (POSE_CHECK_DEGREES): the median rotation of the cameras'
        own part of the corrections, in degrees; what it was calibrated on, whether or not the
        rig-wide part has joined by then (budgets under 500 steps, a resumed run)."""
        return float((self.own_part @ self.rotation).norm(dim=1).median()) * 180.0 / math.pi

    @torch.no_grad()
    def summary(self) -> dict:
        """Median and largest correction over the views: degrees, and shares of the spacing."""
        rotation, shift = self.corrections()
        degrees = rotation.norm(dim=1) * 180.0 / math.pi
        spacings = shift.norm(dim=1) / self.spacing
        return {"median_degrees": float(degrees.median()), "max_degrees": float(degrees.max()),
                "median_shift": float(spacings.median()), "max_shift": float(spacings.max())}


def fit_view_pose(light_field, view, scale: float, spacing: float, steps: int = 300, batch: int = 8192, seed: int = 0):
    """`view` with its pose fitted to its photo, the light field frozen: a rotation about its
    centre and a shift, learned by the photometric loss (as BARF and NeRF-- score held-out
    views).  A capture's held-out cameras come from the same reconstruction as its training
    cameras and carry its error too; scored as given, a sharp field loses to a blurred one
    wherever a held-out camera is off (docs/STABILITY.md, the nineteenth session: Statue's
    held-out cameras moved 0.06-0.26 degrees to fit).  `spacing`: the training cameras'
    spacing (the unit of the shift).  Returns (fitted view, degrees turned, shift as a share
    of the spacing)."""
    uvst, valid = view_uvst(view, light_field.slab, scale)
    device = light_field.device
    photo = torch.from_numpy(view.load_image(scale).reshape(-1, 3).astype(np.float32) / 255.0)
    rays = torch.nonzero(valid)[:, 0]
    if len(rays) == 0:
        return view, 0.0, 0.0
    uvst, photo = uvst[rays].to(device), photo[rays].to(device)
    correction = PoseRefinement(light_field.slab, view.center[None], centred=False, spacing=spacing).to(device)
    first_view = torch.zeros(min(batch, len(uvst)), dtype=torch.long, device=device)
    optimizer = torch.optim.Adam(correction.parameters(), lr=1e-3)
    generator = torch.Generator().manual_seed(seed)
    field = light_field.field
    frozen = [p.requires_grad for p in field.parameters()]
    for p in field.parameters():
        p.requires_grad_(False)
    try:
        for step in range(steps):
            for group in optimizer.param_groups:  # 1e-3 down to 1e-4
                group["lr"] = 1e-3 * 0.1 ** (step / steps)
            pick = torch.randint(len(uvst), (len(first_view),), generator=generator).to(device)
            rgb, _ = field(correction(uvst[pick], first_view))
            loss = ((rgb.float() - photo[pick]) ** 2).mean()
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
    finally:
        for p, wanted in zip(field.parameters(), frozen):
            p.requires_grad_(wanted)
    # The slab-frame correction as a world-frame pose: x -> C + W (x - C) + m, with W and m
    # the turn and shift brought out of the slab frame; the camera's rays turn with it.  In
    # float64 on the host: MPS has no float64, so the corrections leave the device first.
    with torch.no_grad():
        rotation, shift = (c.cpu().double() for c in correction.corrections())
        turn = rotation_matrices(rotation)[0].numpy()
        slab_rotation = light_field.slab.rotation
        turn_world = slab_rotation.T @ turn @ slab_rotation
        shift_world = slab_rotation.T @ shift.numpy()[0]
        degrees = float(rotation.norm()) * 180.0 / math.pi
        moved = float(shift.norm()) / spacing
    R = view.R @ turn_world.T
    centre = view.center + shift_world
    return replace(view, R=R, t=-R @ centre), degrees, moved

"""Named training presets: a field representation, its size, and the recipe that trains it.

`paper` and `authors` are the published NeuLF networks with the published recipe (Adam,
learning rate 5e-4 decayed x0.995 per epoch, 8192-ray batches).  `fast` is this project's
default for CPUs and small GPUs; see docs/BENCHMARKS.md for how it was chosen.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from .errors import NeulfError


@dataclass(frozen=True)
class Preset:
    field: str
    field_config: dict = field(default_factory=dict)
    lr: float = 5e-4
    lr_decay_per_epoch: float | None = None   # the paper's schedule; None: decay over the budget
    lr_final_ratio: float = 0.1               # learning rate at the end of the budget / at start
    lr_schedule: str = "exponential"          # how it gets there: "exponential" or "cosine" (train.learning_rate_factor)
    batch_size: int = 8192
    adam_beta2: float = 0.999                 # Adam's second-moment decay (the paper: PyTorch's default)
    consistency: bool | None = False          # the paper's multi-view losses by default; None: rules.default_consistency (docs/DEPTH.md)
    teacher: bool = False                     # early depth pulled toward the classic plane sweep (teacher.py, docs/DEPTH.md)
    point_depth: bool = False                 # keypoint rays pulled toward their SfM point's depth (point_depth.py)
    # The default's pose check (train.py, poses.poses_look_off): refine the poses from the start
    # and keep refining only where the corrections say they are off.  Its thresholds were set
    # on the disparity field, whose early steps already fit the photos' edges; the published
    # MLPs are still a blur at the check's step, so their corrections fit the blur and the check
    # keeps them: the authors' network on CanClip lost 2.2 dB at 1000 steps (240x135, CPU,
    # 21.39 against 23.55 dB) and 4.5 dB in a minute at 960x540 on an H200 (22.99 against 27.51,
    # 7,490 steps against 17,744; docs/BENCHMARKS.md).  Off: the published recipe, fixed poses
    # unless asked.
    pose_check: bool = False
    description: str = ""


# The fast field's texture: 4 channels at ~1 texel per pixel keep the default model.pt under
# 3 MB at 480x270 (2.66 MB; 8 channels: 4.82 MB, 0.33 dB better on CanClip; docs/BENCHMARKS.md).
# Its geometry planes: 4 channels per scale instead of 8 render a frame about 25 % faster and
# train about 20 % more steps in the same minutes, for the same held-out PSNR within 0.1 dB on
# CanClip, Statue and fern (docs/BENCHMARKS.md, "Geometry channels").
# Its colour decoder: 128 wide instead of 64 costs about 9 % more time per step and was measured
# better at equal training time on every scene tried (1.5 minutes, seeds 0 / 1: CanClip
# +0.33 / +0.35 dB, Statue +0.17 / +0.16, fern +0.10 / +0.06, HCI +0.33 / +0.20;
# docs/BENCHMARKS.md, "Colour decoder width").  Models saved before keep their 64.
# Its depth detail (DisparityConfig.depth_detail_shift): a depth correction stored over the
# texture's coordinates at a quarter of its size, shared by every viewpoint.
# Its colour decoder returns a colour and its linear change across the uv plane per surface
# point (`view_dependence_linear`, starting view-independent) instead of reading (u, v) as an
# input: at the stability study's 1000 steps (three seeds, every share of the views) CanClip
# +0.39-0.47 dB, HCI +1.10-1.18 dB, the synthetic scene -0.17..+0.22; at the product's 1.5
# minutes (side by side, seeds 0 / 1) CanClip +0.17 / +0.16 dB, HCI +1.07 / +0.75, Statue
# +0.24 / -0.28, fern -0.18 / -0.06 (docs/BENCHMARKS.md and docs/STABILITY.md, "Linear view
# dependence").
# Its decoders learn at 3 times the preset's rate (`decoder_lr_factor`; its feature grids at
# 10 times it).  At the product's 1.5 minutes, side by side against 1 time, seeds 0 / 1:
# CanClip +0.18 / +0.49 dB, Statue +0.00 / +0.26, fern +0.06 / +0.11, HCI +0.79 / +0.56
# (mean +0.31; docs/BENCHMARKS.md, "Decoders at 3 times the rate").  At the stability study's
# 1000 steps, three seeds: CanClip +0.51 dB with all 26 photos, +0.23 with 6, HCI's 18 views
# +0.54, the synthetic scene's 14 / 10 / 7 / 4 photos +0.18 / +0.21 / +0.02 / -0.06; 10 times
# gained more on the real captures but lost 0.23 dB on the synthetic scene's 4 photos and
# broke two of issue 4's targets (docs/STABILITY.md, "Decoders at the grids' rate").
# Its geometry planes have 16 / 32 / 64 cells across the st plane, one octave coarser than the
# field's own 32 / 64 / 128: the finest cells fit one photo's noise, while the depth detail, read
# over the texture's coordinates, still gives a depth edge its place.  First for at most 13
# photos (forty-sixth session; at 1000 steps, seeds 0-3, CanClip's 6 photos 34.92 -> 35.24 dB,
# the synthetic scene's 4 / 7 / 10 +0.23 / +0.19 / +0.34), then for every capture (forty-seventh)
# from the product's budget: 1.5 minutes at 480x270 (fern 504x378), side by side on pinned
# cores against 32 / 64 / 128, seeds 0-4, scored with 4 points a pixel: fern +0.20 ± 0.04 dB
# (standard error; 5 of 5 pairs up), CanClip +0.02 ± 0.03, Statue -0.02 ± 0.11; at 1000 steps the
# synthetic scene's 14 photos +0.34, HCI's 18 +0.13, CanClip's 26 -0.06.  A third of the
# geometry's parameters (74 k instead of 232 k).  Models saved before keep theirs (model.json).
# Where a deep scene gives it a back surface, the two surfaces' texture features are blended and
# decoded once, not decoded to two colours and blended (DisparityConfig.back_surface_blend): half
# the decoder's work.  Fifty-second session, AMD EPYC: the stability study's 147 deep-scene runs
# trained again, 45 configurations against the colour blend at the same seeds: +0.03 dB (mean
# and median), 32 better, 13 worse; 1000 steps in 40 instead of 47 s (runs a day apart); the
# default's seed spread 26 of 36 configurations inside 0.2 dB, as before (docs/STABILITY.md,
# fifty-second session).  Models saved before blend colours (model.json).
FAST_FIELD = {"texture_channels": 4, "geometry_channels": 4, "hidden": 128, "depth_detail_shift": 2,
              "view_dependence_linear": True, "decoder_lr_factor": 3.0, "colour_start": "statue_v1",
              "geometry_spatial_res": [16, 32, 64], "back_surface_blend": "features"}
# Its learning rate: a cosine from 2e-3 down to 1 % over the budget instead of an exponential
# decay to 10 %.  Same cost per step; the field learns longer at a high rate, then settles.
# Stability study's setting (1000 steps, three seeds, mean / spread of held-out PSNR):
# HCI 70 views 45.03 / 0.29 -> 45.35 / 0.08 dB, HCI 18 views 44.47 / 0.45 -> 45.04 / 0.13,
# CanClip 26 views 34.37 -> 34.66, 6 views 33.21 -> 33.45, the synthetic scene 14 views
# 28.99 -> 29.11, 4 views 27.47 -> 27.59 (docs/STABILITY.md, "Learning-rate schedule").
# Decaying exponentially to 1 % instead lost 1.8 dB on HCI's 18 views against the old
# schedule; a cosine to 10 % or to 0 came within 0.16 dB of this one, with a wider spread.
# Its optimiser: Adam with a second-moment decay of 0.99 instead of PyTorch's 0.999, as grid
# fields are commonly trained (Instant-NGP): the per-texel step sizes follow the shrinking
# gradients sooner, so the field converges in fewer steps.  At the product's setting
# (1.5 minutes at 480x270, side by side, seeds 0 / 1): HCI +1.35 / +1.45 dB, CanClip
# +0.23 / +0.19, fern +0.04 / +0.01, Statue +0.04 / -0.18; at the stability study's 1000
# steps HCI 52 views 45.17 -> 46.20 dB, CanClip 6 views 33.50 -> 33.70 (docs/STABILITY.md,
# "Adam's second moment").  0.95 gained more at 1000 steps but lost on Statue at 1.5 minutes
# (-0.07 / -0.23 dB).
FAST_SCHEDULE = {"lr": 2e-3, "lr_final_ratio": 0.01, "lr_schedule": "cosine", "adam_beta2": 0.99}
# Except for captures whose photos differ in exposure (`train --appearance`): there the fast
# field keeps 8 geometry channels, which the stability study's +-1-stop exposure jitter needs
# (NeRF-W protocol, 1000 steps, seeds 0 / 1: 26.86 / 27.26 dB with 8, 26.03 / 26.23 with 4;
# docs/STABILITY.md).
APPEARANCE_GEOMETRY = {"geometry_channels": 8}
# ... and Adam's PyTorch default second-moment decay, 0.999: with the per-photo colour
# transforms learning alongside, 0.99 lost 0.37 dB on the jittered photos as rendered and
# 0.18 dB under NeRF-W's protocol (1000 steps, seeds 0-2: 24.47 -> 24.10, 27.23 -> 27.05 dB;
# docs/STABILITY.md, "Adam's second moment").
APPEARANCE_ADAM_BETA2 = 0.999

# The most depth layers the fast field takes (8 is the default's; each layer is a plane of the
# geometry: thousands exhaust memory).  The CLI and Blender both refuse more.
MAX_DEPTH_LAYERS = 64

PRESETS: dict[str, Preset] = {
    "paper": Preset("mlp", {"depth": 20, "width": 256, "skip": "input"}, lr=5e-4, lr_decay_per_epoch=0.995,
                    description="the paper's network: 20 x 256 ReLU layers, raw-input skips every 4 layers"),
    "authors": Preset("mlp", {"depth": 8, "width": 256, "skip": "embedding"}, lr=5e-4, lr_decay_per_epoch=0.995,
                      description="the authors' code default: 8 x 256, embedding skips"),
    "fast": Preset("disparity", FAST_FIELD, **FAST_SCHEDULE, batch_size=8192, teacher=True, consistency=None, point_depth=True,
                   pose_check=True,
                   description="per-ray disparity shearing one shared st texture; trains in minutes on a CPU"),
    # (the sweep teacher as `fast`, in the model it trains; its size search goes without, autosize._search.
    # The teacher came to `fast` the day `auto` was made, and `auto` was left without it until the
    # sixty-sixth session)
    "auto": Preset("disparity", FAST_FIELD, **FAST_SCHEDULE, batch_size=8192, teacher=True, consistency=None, point_depth=True,
                   pose_check=True, description="the fast field with its texture sized per scene on validation views (autosize.py)"),
    "planes": Preset("planes", {}, lr=2e-3, lr_final_ratio=0.1, batch_size=8192,
                     description="six factorised (u,v,s,t) feature planes + tiny MLP (K-Planes style)"),
}
DEFAULT_PRESET = "fast"


def get_preset(name: str) -> Preset:
    if name not in PRESETS:
        raise NeulfError(f"unknown preset '{name}'; choose one of: {', '.join(PRESETS)}.")
    return PRESETS[name]

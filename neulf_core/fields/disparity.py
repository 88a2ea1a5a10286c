"""A disparity-sheared light field: per-ray depth plus one shared texture.

For a Lambertian point at depth z, a ray leaving the uv plane at (u, v) and crossing the
st plane at (s, t) sees the same point as the ray from the slab origin that crosses the
st plane at

    s' = s + u * delta,   t' = t + v * delta,   delta = z_st / z - 1

(delta is the point's disparity relative to the st plane).  So the field predicts a smooth
per-ray disparity with a small factorised-planes network, shears (s, t) by it, and reads
the colour from one high-resolution texture over (s', t') that *every* camera observes --
the angular axes, which only as many cameras sample, carry only the smooth disparity.  The
depth output comes for free: z = z_st / (1 + delta).  The colour decoder leaves room for
view-dependent effects: with (u, v) as an input, or (the fast preset's) as a colour that
changes linearly across the uv plane per surface point.  With delta = 0 at the start the field is
exactly classic single-focal-plane light field rendering.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ..device import HALF_DEVICES
from ..errors import NeulfError
from . import register
from .planes import ANGULAR, PAIRS, PlanesConfig, PlanesField, total_variation

# The geometry planes that mix one angular and one spatial axis (us, ut, vs, vt) share a shape
# within a scale, so each scale samples them in one batched grid_sample (see _geometry_features).
MIXED = [i for i, (a, b) in enumerate(PAIRS) if (a in ANGULAR) != (b in ANGULAR)]
# The geometry decoder's four outputs: the front surface's depth logit, and with a back surface
# the back's depth as a share of the front's (a logit; so it stays behind) and the front's weight
# (a logit).  Both of the latter start at one half (zero bias and near-zero weights).
FRONT_DEPTH, BACK_SHARE, FRONT_WEIGHT = 3, 0, 1
ANGULAR_PAIR = PAIRS.index(ANGULAR)
SPATIAL_PAIR = PAIRS.index((2, 3))


BACK_SURFACE_BLENDS = ("colour", "features")  # DisparityConfig.back_surface_blend


@dataclass
class DisparityConfig:
    texture_size: list[int] = field(default_factory=lambda: [512, 512])  # finest level (rows, columns)
    texture_levels: int = 4            # each coarser level halves the size (coarse levels widen the basin)
    texture_channels: int = 8
    texture_margin: float = 0.25       # the sheared (s', t') leave [-1, 1] a little
    geometry_angular_res: int = 8
    geometry_spatial_res: list[int] = field(default_factory=lambda: [32, 64, 128])
    geometry_channels: int = 8
    hidden: int = 64
    view_dependence: bool = True
    # Linear view dependence: the colour decoder reads the texture only and returns, besides
    # the colour's logit, its slope in (u, v) at that surface point, starting at zero, so the
    # field starts view-independent and its change of colour between viewpoints is a plane
    # fitted per point, not a ReLU network's random function of (u, v).  On in the fast preset
    # (presets.FAST_FIELD, with the numbers); off here, so models saved before read as they were.
    view_dependence_linear: bool = False
    # The decoders' learning rate as a multiple of the preset's (the feature grids learn at 10
    # times it).  The fast preset's is 3 (presets.FAST_FIELD, with the numbers); 1 here, so
    # models saved before the factor resume as they were trained.
    decoder_lr_factor: float = 1.0
    # Depth layers for the geometry (`train --depth-layers N`): feature planes at N disparities
    # spread evenly between near and far, each read where the ray crosses its depth as seen
    # from the slab origin, so a depth edge near one of them stays put as the camera moves.
    # Sharper depth and +1.2 dB on the dense HCI light field, +0.45 dB on Statue, but -0.25 dB
    # on fern and -0.5 dB on the synthetic scene (wide depth ranges), ~10 % slower per step:
    # the trainer turns them on for shallow scenes only (rules.default_depth_layers).
    geometry_layers: int = 0
    geometry_layer_res: int = 128
    geometry_layer_channels: int = 2
    geometry_layer_tv: float = 1e-3
    tv_weight: float = 1e-3
    # Depth detail (`depth_detail_shift` = k > 0; the fast preset's k is 2): a coarse feature
    # grid over the *sheared* coordinates (s', t'), the texture's size >> k, whose linear
    # read-out corrects the planes' disparity logit.  Every camera that sees a surface point
    # reads the same cell there, so a correction learned from some photos holds for every
    # viewpoint, as the colour texture's does -- where the planes' correction is a function of
    # the ray, and a viewpoint between the photos gets an interpolation of theirs.  At 1000
    # steps, seeds 0 / 1 / 2: the synthetic scene's 14 views 29.53 -> 30.03 dB, its 4 views
    # 27.76 -> 28.18, CanClip's 6 views 33.70 -> 34.07 (docs/STABILITY.md); fern at 1.5 minutes
    # +0.11 / +0.19 dB (docs/BENCHMARKS.md, "Depth detail").  The trainer leaves it out where
    # the depth layers are on (train._build_field).  0: off (models saved before read as they were).
    depth_detail_shift: int = 0
    depth_detail_channels: int = 4
    # How many times a ray reads the detail, each time where the last correction put its surface
    # point (as parallax mapping iterates).  The trainer reads it twice for captures of at most
    # 13 photos (rules.default_depth_detail_reads): there the planes' depth is further off, and
    # a read where it puts the point learns a correction for the wrong point.  The synthetic
    # scene at 2400 steps, seeds 0 / 1, two reads against one: 4 views +0.27 / +0.21 dB, 7
    # views +0.23 / +0.12, but 14 views -0.19 / -0.19 (a higher training PSNR: with many photos
    # the second read fits them, not the viewpoints between them; docs/BENCHMARKS.md, "Depth
    # detail").
    # Models saved before read it once.
    depth_detail_reads: int = 1
    # Coarse to fine: the finer geometry scales fade in over this share of the training budget
    # (0: all from the start); the trainer sets it for captures of few photos
    # (rules.default_coarse_to_fine).
    geometry_coarse_to_fine: float = 0.0
    # Texture coarse to fine: the texture's finer levels fade in, coarse to fine, over this
    # share of the training budget from `texture_ramp_start` on (0: all from the start), as
    # BARF fades in its encoding so that poses can be registered against a blurred scene
    # first.  The trainer sets it where it restarts the field for far-off poses with few
    # photos (pose_check.FEW_PHOTOS_TEXTURE_COARSE_TO_FINE; start_texture_coarse_to_fine).
    texture_coarse_to_fine: float = 0.0
    texture_ramp_start: float = 0.0
    # A back surface (`train --back-surface`): each ray sees a front surface and one behind it,
    # each reading the texture where its own depth shears the ray, their colours (and depth
    # units) mixed by a weight the geometry planes also give.  Meant for outlines: with one
    # surface a ray there gets a depth between the object's and the background's and reads a
    # texel of neither, where two can blend two right colours as the photo's pixel does.  As
    # measured the gain is mostly elsewhere: on the synthetic scene +0.02 / +0.11 dB inside the
    # shiny objects' mask (their outlines included), +0.38 outside it (docs/VIEW_DEPENDENCE.md).
    # The trainer turns it on for deep scenes (rules.default_back_surface, with the numbers).
    # Off here, so models saved before read as they were.
    back_surface: bool = False
    # How the two surfaces mix: "colour" decodes each surface's texture features to a colour and
    # blends the colours; "features" blends the features and decodes once, half the colour
    # decoder's work.  A trained model never lets one surface take a ray's whole colour (the
    # front's weight: median 0.31-0.40, 1-99 % of rays within 0.12-0.78;
    # benchmarks/back_surface_weights.py), so the blend is a second tap along the depth either
    # way, and a tap of features decodes as well as a tap of colours.  The fast preset blends
    # features (presets.FAST_FIELD, with the numbers); "colour" here, so models saved before
    # read as they were.
    back_surface_blend: str = "colour"  # BACK_SURFACE_BLENDS
    # The colour decoder's start: the name of a packaged start (neulf_core/fields/starts/<name>.npz,
    # learned by scripts/learn_colour_start.py) or "" for PyTorch's random initialisation.  With a
    # learned start no seed draws the decoder, and it was the decoder's random start that spread
    # the seeds on the dense captures (docs/STABILITY.md, "Twenty-eighth session"): CanClip 26
    # views 0.23 -> 0.05 dB, HCI 70 views 0.36 -> 0.02 at 1000 steps.  Used only where the
    # decoder's shape is the start's (the fast preset's); otherwise the random start.  The fast
    # preset names one (presets.FAST_FIELD); "" here, so models saved before read as they were.
    colour_start: str = ""
    # Slab geometry in normalised units, set by the trainer from the slab (see slab_geometry()).
    uv_half: list[float] = field(default_factory=lambda: [1.0, 1.0])
    uv_centre: list[float] = field(default_factory=lambda: [0.0, 0.0])
    st_half: list[float] = field(default_factory=lambda: [1.0, 1.0])
    st_centre: list[float] = field(default_factory=lambda: [0.0, 0.0])
    z_st: float = 1.0
    z_near: float = 0.5
    z_far: float = 2.0


# The finest texture's texel budget: it keeps the default model.pt small for photos of any size
# (CanClip at 480x270 needs 202,800 texels: 1.6 MB with the depth layers, 8-bit grids; more
# texels or channels at this budget were measured not to pay, docs/BENCHMARKS.md).
MAX_TEXELS = 220_000
STARTS = Path(__file__).resolve().parent / "starts"  # the packaged colour-decoder starts (load_colour_start)
DECODE_ROWS = 8192  # rays per colour-decoder call when rendering on a CPU (DisparityField._colour)


def texture_size_for(image_size: tuple[int, int], margin: float = 0.25) -> list[int]:
    """Finest texture (rows, columns): about one texel per training pixel over the sheared
    range -- finer only memorises noise, coarser blurs (docs/BENCHMARKS.md) -- shrunk, with
    the image's aspect, to the texel budget that keeps the model file small."""
    width, height = image_size
    rows, cols = height * (1 + margin), width * (1 + margin)
    shrink = min(1.0, (MAX_TEXELS / (rows * cols)) ** 0.5)
    return [int(round(rows * shrink)), int(round(cols * shrink))]


def colour_start_path(name: str) -> Path:
    return STARTS / f"{name}.npz"


@lru_cache(maxsize=None)
def _read_colour_start(path: Path) -> dict[str, torch.Tensor]:
    """The start's weights, read once per process (every field built, a loaded model's too, asks)."""
    if not path.is_file():
        raise NeulfError(f"the colour decoder's start '{path.stem}' is not in {path.parent}: this installation of "
                         "neulf is incomplete; install it again (pip install -e . in the project, or the Blender "
                         "extension's zip).")
    with np.load(path) as start:
        return {key: torch.from_numpy(start[key]) for key in start.files if not key.startswith("meta")}


def load_colour_start(decoder: nn.Sequential, name: str) -> bool:
    """Copy the packaged start `name` into `decoder` where every weight has the start's shape;
    returns whether it did (a decoder of another shape keeps its random start)."""
    weights = _read_colour_start(colour_start_path(name))
    own = dict(decoder.named_parameters())
    if set(weights) != set(own) or any(weights[k].shape != own[k].shape for k in own):
        return False
    with torch.no_grad():
        for key, value in weights.items():
            own[key].copy_(value)
    return True


def slab_geometry(slab) -> dict:
    """The slab quantities the shear needs (what DisparityConfig's geometry fields hold)."""
    centre, half = (slab.lo + slab.hi) / 2, (slab.hi - slab.lo) / 2
    return {"uv_half": half[:2].tolist(), "uv_centre": centre[:2].tolist(), "st_half": half[2:].tolist(),
            "st_centre": centre[2:].tolist(), "z_st": float(slab.z_st), "z_near": float(slab.z_near), "z_far": float(slab.z_far)}


class DisparityField(nn.Module):
    # What of the state dict is geometry: the planes and their decoder, and the depth layers
    # (the trainer's far-off restart starts these again where it keeps the texture).
    GEOMETRY_PARAMETERS = ("geometry.", "layers")

    def __init__(self, config: DisparityConfig):
        super().__init__()
        if config.back_surface_blend not in BACK_SURFACE_BLENDS:
            raise NeulfError(f"this model blends its two surfaces by '{config.back_surface_blend}', which this version "
                             f"of NeuLF does not know ({' or '.join(BACK_SURFACE_BLENDS)}): update NeuLF or train it again.")
        self.config = config
        self.geometry = PlanesField(PlanesConfig(angular_res=config.geometry_angular_res, spatial_res=config.geometry_spatial_res,
                                                 channels=config.geometry_channels, hidden=32, hidden_layers=1,
                                                 tv_weight=config.tv_weight))
        with torch.no_grad():  # start at zero disparity: the texture sits on the st plane
            last = self.geometry.decoder[-1]
            last.weight.mul_(0.01)
            last.bias.zero_()
            last.bias[FRONT_DEPTH] = self._unit_of_st()
        if config.geometry_layers:
            k, c, res = config.geometry_layers, config.geometry_layer_channels, config.geometry_layer_res
            self.register_buffer("layer_disparity", self.disparity(torch.linspace(0, 1, k)), persistent=False)
            self.layers = nn.Parameter(torch.randn(k, c, res, res) * 0.01)
            first = self.geometry.decoder[0]
            self.geometry.decoder[0] = nn.Linear(first.in_features + k * c, first.out_features)
        rows, cols = config.texture_size
        if config.depth_detail_shift:
            shift = config.depth_detail_shift
            self.depth_detail = nn.Parameter(
                torch.randn(1, config.depth_detail_channels, max(2, rows >> shift), max(2, cols >> shift)) * 0.1)
            # A zero read-out: the correction starts at nothing and the field at the planes' depth.
            self.depth_detail_readout = nn.Linear(config.depth_detail_channels, 1)
            nn.init.zeros_(self.depth_detail_readout.weight)
            nn.init.zeros_(self.depth_detail_readout.bias)
        self.textures = nn.ParameterList(
            nn.Parameter(torch.randn(1, config.texture_channels, max(2, rows >> level), max(2, cols >> level)) * 0.01)
            for level in range(config.texture_levels))
        if config.geometry_coarse_to_fine > 0:
            # Persistent: a model saved part-way (a checkpoint, Cancel) renders with the weights
            # it was trained with, and a resumed one continues from them.
            self.register_buffer("geometry_scale_weights", _fade_in_weights(len(config.geometry_spatial_res), 0.0))
        self._ramp_done = False  # every weight at 1: the trainer's calls need no more copies
        if config.texture_coarse_to_fine > 0:  # (persistent, as the geometry's weights)
            self.register_buffer("texture_level_weights", self._texture_weights(config.texture_ramp_start))
        self.linear_view_dependence = config.view_dependence and config.view_dependence_linear
        self.uv_input = config.view_dependence and not self.linear_view_dependence  # (u, v) as two decoder columns
        decoder_in = config.texture_channels * config.texture_levels + (2 if self.uv_input else 0)
        decoder_out = 3 + (6 if self.linear_view_dependence else 0)  # colour logit, its slope along u, along v
        self.decoder = nn.Sequential(nn.Linear(decoder_in, config.hidden), nn.ReLU(), nn.Linear(config.hidden, decoder_out))
        if config.colour_start:
            load_colour_start(self.decoder, config.colour_start)
        if self.linear_view_dependence:
            with torch.no_grad():  # zero slope: the colour starts the same from every viewpoint
                self.decoder[-1].weight[3:] = 0.0
                self.decoder[-1].bias[3:] = 0.0
        for layer in (*self.geometry.decoder, *self.decoder):
            if isinstance(layer, nn.ReLU):  # in place: one (N, hidden) buffer fewer; its gradient needs only the output
                layer.inplace = True
        for name in ("uv_half", "uv_centre", "st_half", "st_centre"):
            self.register_buffer(name, torch.tensor(getattr(config, name), dtype=torch.float32), persistent=False)

    def _unit_of_st(self) -> float:
        c = self.config
        unit = (1.0 / c.z_st - 1.0 / c.z_far) / (1.0 / c.z_near - 1.0 / c.z_far)
        unit = min(max(unit, 1e-3), 1 - 1e-3)
        return float(torch.logit(torch.tensor(unit)))

    @torch.no_grad()
    def set_training_progress(self, fraction: float) -> None:
        """Coarse to fine (geometry_coarse_to_fine = T; the trainer calls this every step): the
        coarsest geometry scale counts from the start, and scale k of K fades in linearly while
        the budget goes from T (k - 1) / (K - 1) to T k / (K - 1).  With few photos the depth
        then settles on the broad shapes they agree on before finer cells can bend it toward
        one photo's noise (docs/STABILITY.md).  A weight never drops: a model resumed with a
        larger budget (a smaller fraction) keeps the scales it has."""
        if self.config.texture_coarse_to_fine > 0:
            torch.maximum(self.texture_level_weights, self._texture_weights(fraction).to(self.texture_level_weights.device),
                          out=self.texture_level_weights)
        ramp = self.config.geometry_coarse_to_fine
        if ramp <= 0 or self._ramp_done:
            return
        weights = _fade_in_weights(self.geometry_scale_weights.numel(), fraction / ramp)
        torch.maximum(self.geometry_scale_weights, weights.to(self.geometry_scale_weights.device),
                      out=self.geometry_scale_weights)
        self._ramp_done = bool((weights == 1).all())

    def _texture_weights(self, fraction: float) -> torch.Tensor:
        """(levels,) weights of the texture's levels, finest first, at `fraction` of the budget."""
        c = self.config
        return _fade_in_weights(c.texture_levels, (fraction - c.texture_ramp_start) / c.texture_coarse_to_fine).flip(0)

    @torch.no_grad()
    def start_texture_coarse_to_fine(self, fraction: float, ramp: float) -> None:
        """From `fraction` of the budget on, only the coarsest texture level counts, the finer
        ones fading in over the next `ramp` of it; kept in the config (and the model's
        field_config), so a resumed or saved model reads the texture as it was trained."""
        self.config.texture_coarse_to_fine, self.config.texture_ramp_start = ramp, fraction
        self.field_config.update(texture_coarse_to_fine=ramp, texture_ramp_start=fraction)
        self.register_buffer("texture_level_weights", self._texture_weights(fraction).to(self.textures[0].device))

    def disparity(self, unit: torch.Tensor) -> torch.Tensor:
        c = self.config
        inverse_depth = 1.0 / c.z_far + unit * (1.0 / c.z_near - 1.0 / c.z_far)
        return c.z_st * inverse_depth - 1.0

    def forward(self, uvst: torch.Tensor):
        surfaces, front_weight = self.surfaces(uvst)
        uv = uvst[:, :2]
        unit = _depth_unit(surfaces, front_weight)
        if front_weight is None:
            (grid, _), = surfaces
            return self._colour(self._texture_features(grid, uv), uv), unit
        (front_grid, _), (back_grid, _) = surfaces
        # Both surfaces' texture reads in one batch of 2N rays: fewer kernel calls.
        both = self._texture_features(torch.cat([front_grid, back_grid]), torch.cat([uv, uv]))
        if self.config.back_surface_blend == "features":
            front_features, back_features = both.chunk(2)
            return self._colour(torch.lerp(back_features, front_features, front_weight.to(both.dtype)), uv), unit
        front_rgb, back_rgb = self._colour(both, torch.cat([uv, uv])).chunk(2)
        return torch.lerp(back_rgb, front_rgb, front_weight.to(front_rgb.dtype)), unit

    def depth_unit(self, uvst: torch.Tensor) -> torch.Tensor:
        """forward's depth unit (N, 1), the same values, without the texture reads and the colour
        decoder (about half of a query's time on a CPU: CanClip's default, 32k rays): a render's
        depth-only queries (the centre rays of a render with depth and several points a pixel,
        a picked pixel's depth)."""
        return _depth_unit(*self.surfaces(uvst))

    def _texture_features(self, grid: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
        """(N, F) colour-decoder input of rays whose surface points read the texture at grid (N, 2)."""
        features = [_features_at(texture, grid) for texture in self.textures]
        if self.config.texture_coarse_to_fine > 0:
            features = [f * w for f, w in zip(features, self.texture_level_weights)]
        if self.uv_input:
            features.append(uv)
        return _rows(features)

    def _colour(self, features: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
        if torch.is_grad_enabled() or features.device.type != "cpu" or features.shape[0] <= DECODE_ROWS:
            return self._decode(features, uv)
        # Rendering on a CPU: a 32k-ray chunk's hidden layer (32k x 128 floats, 16 MB) falls out
        # of the cache between the decoder's steps; 8k rows at a time decode in 4.2 instead of
        # 6.6 ms per 32k rays (docs/BENCHMARKS.md, "Colour decoder width").
        return torch.cat([self._decode(rows, uv_rows) for rows, uv_rows in zip(features.split(DECODE_ROWS), uv.split(DECODE_ROWS))])

    def _decode(self, features: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
        out = self.decoder(features)
        if not self.linear_view_dependence:
            return torch.sigmoid(out)
        # The colour's logit plus its slope along u, then along v: two fused multiply-adds.
        logit = torch.addcmul(out[:, :3], out[:, 3:6], uv[:, :1])
        return torch.sigmoid(torch.addcmul(logit, out[:, 6:], uv[:, 1:]))

    def sheared(self, uvst: torch.Tensor, detail_reads: list | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Where rays (N, 4) read the texture for their (front) surface, (N, 2) in [-1, 1], and
        its depth unit (N, 1).  `detail_reads`, a list: gets the (N, 2) points where the rays
        read the depth detail."""
        surfaces, _ = self.surfaces(uvst, detail_reads, back=False)
        return surfaces[0]

    def surfaces(self, uvst: torch.Tensor, detail_reads: list | None = None,
                 back: bool = True) -> tuple[list, torch.Tensor | None]:
        """([(grid, unit)] for the front surface and, with a back surface, the back one; the
        front's weight (N, 1) in the colour, or None with one surface).  `detail_reads`, a list:
        gets the points where the front surface reads the depth detail.  `back` False: the front
        surface only (its weight None), without the back one's work."""
        # float32 even when rendering under float16 autocast (render.PRECISIONS): a texel is
        # 1/512 of the range, and float16 disparities moved colours to 55 dB from float32.
        if uvst.device.type not in HALF_DEVICES:  # no autocast there to switch off
            return self._surfaces(uvst, detail_reads, back)
        with torch.autocast(uvst.device.type, enabled=False):
            return self._surfaces(uvst, detail_reads, back)

    def _surfaces(self, uvst: torch.Tensor, detail_reads: list | None, back: bool) -> tuple[list, torch.Tensor | None]:
        uv = uvst[:, :2] * self.uv_half + self.uv_centre
        scale = 1.0 / (1.0 + self.config.texture_margin)  # sheared st leaves [-1, 1] a little
        out = self.geometry.decoder(self._ray_geometry_features(uvst, uv, scale))
        front = self._surface(uvst, uv, out[:, FRONT_DEPTH:FRONT_DEPTH + 1], scale, detail_reads)
        if not (self.config.back_surface and back):
            return [front], None
        back_unit = front[1] * torch.sigmoid(out[:, BACK_SHARE:BACK_SHARE + 1])  # behind the front
        back = self._surface(uvst, uv, torch.logit(back_unit.clamp(1e-6, 1 - 1e-6)), scale, None)
        return [front, back], torch.sigmoid(out[:, FRONT_WEIGHT:FRONT_WEIGHT + 1])

    def _ray_geometry_features(self, uvst: torch.Tensor, uv: torch.Tensor, scale: float) -> torch.Tensor:
        """The geometry decoder's input: the planes' features, and the depth layers' where on."""
        features = self._geometry_features(uvst)
        if not self.config.geometry_layers:
            return features
        k, n = self.layers.shape[0], uvst.shape[0]
        grids = (uvst[:, 2:] + uv * (self.layer_disparity[:, None, None] / self.st_half)) * scale
        layered = _sample(self.layers, grids.view(k, n, 1, 2)).view(-1, n).t()
        return torch.cat([features, layered], 1)

    def _surface(self, uvst: torch.Tensor, uv: torch.Tensor, logit: torch.Tensor, scale: float,
                 detail_reads: list | None) -> tuple[torch.Tensor, torch.Tensor]:
        """(grid, unit) of a surface at depth logit (N, 1), with the depth detail's correction."""
        unit = torch.sigmoid(logit)
        grid = self._shear(uvst, uv, unit, scale)
        if self.config.depth_detail_shift:
            for _ in range(max(1, self.config.depth_detail_reads)):
                if detail_reads is not None:
                    detail_reads.append(grid)
                # Read the correction where the current depth puts the ray's surface point, then shear again.
                unit = torch.sigmoid(logit + self.depth_detail_readout(_features_at(self.depth_detail, grid)))
                grid = self._shear(uvst, uv, unit, scale)
        return grid, unit

    def _shear(self, uvst: torch.Tensor, uv: torch.Tensor, unit: torch.Tensor, scale: float) -> torch.Tensor:
        # sheared st = st + uv * delta in slab units, back in normalised st (one fused form).
        shift = uv * (self.disparity(unit) / self.st_half)
        return (uvst[:, 2:] + shift) * scale

    @torch.no_grad()
    def fill_unseen_texels(self, uvst_chunks) -> float:
        """Texels that no training ray reads (past the edge of what the photos saw, or behind
        something from every camera) keep their random start and decode to a wrong colour
        where a new viewpoint reads them.  Give each the features of the nearest seen texels
        (push-pull over a pyramid), so an extrapolated view continues the edge the photos
        saw.  The depth detail's unseen cells likewise, which would otherwise give such a view
        a random depth correction.  `uvst_chunks`: iterable of (N, 4) training rays.  Returns
        the unseen share of the finest texture."""
        grids = list(self.textures) + ([self.depth_detail] if self.config.depth_detail_shift else [])
        seen = [torch.zeros(g.shape[2] * g.shape[3], dtype=torch.bool, device=g.device) for g in grids]
        for uvst in uvst_chunks:
            detail_reads = []
            # The front surface's reads only: a back surface's carry (1 - its weight) of the colour,
            # and where that is small its texels keep their random start.  (Counting them too, or
            # those of weight 0.5 or more, scored the same to 0.01 dB: the synthetic scene, seeds 0 / 1.)
            grid, _ = self.sheared(uvst, detail_reads)
            for texture, mask in zip(self.textures, seen):
                mark_bilinear_footprint(mask, grid, texture.shape[2], texture.shape[3])
            for points in detail_reads:
                mark_bilinear_footprint(seen[-1], points, self.depth_detail.shape[2], self.depth_detail.shape[3])
        for values, mask in zip(grids, seen):
            mask = mask.view(values.shape[2:])
            values.data.copy_(torch.where(mask, values.data, push_pull_fill(values.data, mask)))
        return float(1.0 - seen[0].float().mean())

    def _geometry_features(self, uvst: torch.Tensor) -> torch.Tensor:
        """PlanesField.features with fewer kernel calls: each pair's sample grid is built once
        for all scales, the three (u, v) planes are sampled as one 24-channel texture, and
        the four mixed planes of a scale as one batch (same values, a third of the calls)."""
        n = uvst.shape[0]
        grids = [torch.stack([uvst[:, b], uvst[:, a]], dim=-1).view(1, n, 1, 2) for a, b in PAIRS]
        mixed_grid = torch.cat([grids[i] for i in MIXED], 0)
        scales = self.geometry.scales
        angular = _sample(torch.cat([planes[ANGULAR_PAIR] for planes in scales], 1), grids[ANGULAR_PAIR])
        per_scale = []
        for k, planes in enumerate(scales):
            mixed = _sample(torch.cat([planes[i] for i in MIXED], 0), mixed_grid).view(len(MIXED), -1, n)
            spatial = _sample(planes[SPATIAL_PAIR], grids[SPATIAL_PAIR]).view(-1, n)
            channels = spatial.shape[0]
            product = angular.view(-1, n)[k * channels:(k + 1) * channels] * spatial
            for plane in mixed.unbind(0):  # explicit products: prod()'s gradient divides
                product = product * plane
            if self.config.geometry_coarse_to_fine > 0:
                product = product * self.geometry_scale_weights[k]
            per_scale.append(product.t())
        return _rows(per_scale)

    def smooth_geometry(self, factor: float) -> None:
        """The geometry's total-variation weights times `factor` from now on, the planes' and
        the depth layers' alike (the trainer raises them when it restarts the field for far-off
        poses); kept in the config, so a model resumed later trains on with them."""
        self.config.tv_weight *= factor
        self.geometry.config.tv_weight = self.config.tv_weight
        self.field_config["tv_weight"] = self.config.tv_weight
        if self.config.geometry_layers:
            self.config.geometry_layer_tv *= factor
            self.field_config["geometry_layer_tv"] = self.config.geometry_layer_tv

    def regularisation(self) -> torch.Tensor:
        total = self.geometry.regularisation()
        if self.config.geometry_layers and self.config.geometry_layer_tv:
            total = total + self.config.geometry_layer_tv * total_variation(self.layers)
        return total

    def param_groups(self, lr: float):
        grids = list(self.geometry.scales.parameters()) + ([self.layers] if self.config.geometry_layers else [])
        decoders = list(self.geometry.decoder.parameters()) + list(self.decoder.parameters())
        if self.config.depth_detail_shift:
            grids.append(self.depth_detail)
            decoders += list(self.depth_detail_readout.parameters())
        return [
            {"params": list(self.textures.parameters()), "lr": lr * 10.0, "name": "texture"},
            {"params": grids, "lr": lr * 10.0, "name": "geometry planes"},
            {"params": decoders, "lr": lr * self.config.decoder_lr_factor, "name": "decoders"},
        ]


def _depth_unit(surfaces: list, front_weight: torch.Tensor | None) -> torch.Tensor:
    """The depth unit (N, 1) of DisparityField.surfaces' result: the one surface's, or the two
    surfaces' mixed by the front's weight."""
    if front_weight is None:
        return surfaces[0][1]
    (_, front_unit), (_, back_unit) = surfaces
    return torch.lerp(back_unit, front_unit, front_weight)


def _fade_in_weights(count: int, progress: float) -> torch.Tensor:
    """(count,) weights, coarse to fine, at `progress` through the ramp (0 start, 1 end): the
    first is 1 throughout, the k-th rises from 0 to 1 while progress goes from (k - 1) /
    (count - 1) to k / (count - 1)."""
    position = min(1.0, max(0.0, progress)) * max(1, count - 1)
    return torch.tensor([min(1.0, max(0.0, position - k + 1)) for k in range(count)])


def mark_bilinear_footprint(mask: torch.Tensor, grid: torch.Tensor, rows: int, cols: int) -> None:
    """Set mask (rows * cols,) at the four texels each bilinear sample at grid (N, 2) reads
    (align_corners=True, border padding: coordinates past the edge read the edge)."""
    x = ((grid[:, 0].clamp(-1, 1) + 1) * 0.5 * (cols - 1))
    y = ((grid[:, 1].clamp(-1, 1) + 1) * 0.5 * (rows - 1))
    for xs in (x.floor(), x.ceil()):
        for ys in (y.floor(), y.ceil()):
            mask[ys.long() * cols + xs.long()] = True


def push_pull_fill(texture: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """texture (1, C, H, W) with every texel where mask (H, W) is False replaced by a
    smooth interpolation of the True ones: averages of seen texels are pushed down a
    pyramid until every cell has one, then pulled back up into the holes."""
    values, weights = [texture * mask], [mask[None, None].to(texture.dtype)]
    while bool((weights[-1] == 0).any()) and min(weights[-1].shape[2:]) > 1:
        values.append(F.avg_pool2d(values[-1], 2, ceil_mode=True))
        weights.append(F.avg_pool2d(weights[-1], 2, ceil_mode=True))
    filled = values[-1] / weights[-1].clamp_min(1e-12)
    for value, weight in zip(reversed(values[:-1]), reversed(weights[:-1])):
        coarse = F.interpolate(filled, size=value.shape[2:], mode="bilinear", align_corners=False)
        filled = torch.where(weight > 0, value / weight.clamp_min(1e-12), coarse)
    return filled


def _sample(texture: torch.Tensor, grid: torch.Tensor) -> torch.Tensor:
    """Bilinear samples (B, C, N, 1) of texture (B, C, H, W) at grid (B, N, 1, 2) in [-1, 1]."""
    return F.grid_sample(texture, grid, mode="bilinear", padding_mode="border", align_corners=True)


def _features_at(texture: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """(N, C) features of a texture (1, C, H, W) at points (N, 2) in [-1, 1] (a transposed view)."""
    return _sample(texture, points.view(1, -1, 1, 2)).view(texture.shape[1], -1).t()


def _rows(columns: list[torch.Tensor]) -> torch.Tensor:
    """(N, sum C) row-major from (N, C) views (transposed grid_sample outputs): one copy, and
    the decoder's matrix products then write their outputs without another transpose."""
    return torch.cat(columns, 1)


register("disparity", DisparityConfig, DisparityField, "per-ray disparity (small planes) shearing one shared st texture")

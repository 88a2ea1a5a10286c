"""Training rays held compactly: (u, v, s, t) as float32 (or float16) and colours as uint8.

A 40-view 960x540 capture is 20.7 M rays: 20.7 M x (16 + 3 + 2) bytes = 435 MB, which
fits a laptop; float16 coordinates bring it to 270 MB.  With pixel jitter (below) each ray
also keeps its (u, v, s, t) change for one pixel step right and one down, in float16: 16
bytes more a ray (330 MB for that capture).

Pixel jitter: a photo's pixel records the light over its whole area (and a renderer's pixel
filter, or a sensor's, spreads it wider), not along the ray through its centre.  Trained on
centre rays only, the field is free to put a depth step anywhere between two pixel centres,
and each seed puts it somewhere else (docs/SEED_SCATTER.md: the silhouettes carry most of the
seed-to-seed difference).  With pixel jitter each training ray is moved to a random point of
its pixel every step.  The field then learns each photo blurred by one more pixel, rendered
at the pixel centres: on the project's Cycles renders (a 1.5-pixel filter, smooth textures)
that pins the silhouettes, on real photos the blur costs more than it steadies, so it is off
by default (docs/TRAINING.md has the numbers).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from .memo import inputs_key, kept
from .rays import pixel_centres, view_rays
from .scene import View
from .slab import Slab


@dataclass
class RaySet:
    uvst: torch.Tensor        # (N, 4) normalised coordinates
    rgb: torch.Tensor         # (N, 3) uint8
    view_index: torch.Tensor  # (N,) int16, index into `names`
    names: list[str]
    pixel_step: torch.Tensor | None = None  # (N, 2, 4) float16: uvst's change one pixel right, one down

    def __len__(self) -> int:
        return int(self.rgb.shape[0])

    def to(self, device) -> "RaySet":
        step = self.pixel_step.to(device) if self.pixel_step is not None else None
        return RaySet(self.uvst.to(device), self.rgb.to(device), self.view_index.to(device), self.names, step)

    def batch(self, index: torch.Tensor, generator: torch.Generator | None = None, jitter: float = 1.0):
        """(uvst float32, rgb float32 in [0, 1]) for ray indices `index`; where the set holds
        pixel steps and a generator is given, each ray moved to a random point of a square
        `jitter` pixels wide around its pixel centre (1: anywhere in its pixel)."""
        uvst = rows_at(self.uvst, index).float()
        if self.pixel_step is not None and generator is not None and jitter > 0:
            offsets = (torch.rand((len(index), 2, 1), generator=generator).to(uvst.device) - 0.5) * jitter
            uvst = uvst + (offsets * rows_at(self.pixel_step, index).float()).sum(1)
        return uvst, rows_at(self.rgb, index).float() / 255.0

    def subset(self, count: int, generator: torch.Generator) -> "RaySet":
        if count >= len(self):
            return self
        index = torch.randperm(len(self), generator=generator)[:count].to(self.rgb.device)
        step = self.pixel_step[index] if self.pixel_step is not None else None
        return RaySet(self.uvst[index], self.rgb[index], self.view_index[index], self.names, step)


def rows_at(values: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """`values[index]` for a 1-D index: the same rows, read by index_select, which on a CPU
    gathers a training step's 8192 random rows of the millions 3-5 times faster than advanced
    indexing (CanClip's 3.4 M rays, one thread: 0.6 against 0.2 ms for (u, v, s, t), 0.5
    against 0.13 ms for the colours)."""
    return values.index_select(0, index)


def view_uvst(view: View, slab: Slab, scale: float, shift: tuple[float, float] = (0.0, 0.0)) -> tuple[torch.Tensor, torch.Tensor]:
    """(H*W, 4) normalised (u, v, s, t) of a view's pixels (their centres, or moved by `shift`
    pixels) and the mask of representable rays."""
    camera = view.scaled_camera(scale)
    pixels = pixel_centres(int(camera.width), int(camera.height)) + np.asarray(shift, dtype=np.float64)
    origin, directions = view_rays(camera, view.R, view.t, pixels)
    uvst, valid = slab.rays_to_uvst(torch.from_numpy(origin), torch.from_numpy(directions))
    return uvst.float(), valid


def view_pixel_steps(view: View, slab: Slab, scale: float, uvst: torch.Tensor) -> torch.Tensor:
    """(H*W, 2, 4): how (u, v, s, t) changes from each pixel centre to the next one right and
    the next one down (through the camera's own model, distortion included)."""
    return torch.stack([view_uvst(view, slab, scale, shift)[0] - uvst for shift in ((1.0, 0.0), (0.0, 1.0))], dim=1)


def build_rayset(views: list[View], slab: Slab, scale: float, coord_dtype=torch.float32, on_view=None,
                 pixel_steps: bool = False, masks: list | None = None, photos_at: float | None = None,
                 photos: list | None = None) -> RaySet:
    """The rays of `views` (those the slab represents); with `pixel_steps`, each ray's change
    for one pixel step as well, for pixel jitter (module docstring).  `masks`, a list: gets
    each view's (H*W,) mask of the pixels whose rays the set holds, which the sweep teacher
    and the point depths take instead of tracing every pixel's ray again (CanClip at 480x270:
    1.4 s of a run's start).  `photos`, a list: gets each view's photo at scale `photos_at`
    too, from the same decode (the depth teacher's sweep reads them smaller)."""
    uvst_parts, rgb_parts, index_parts, step_parts = [], [], [], []
    for i, view in enumerate(views):
        uvst, valid = view_uvst(view, slab, scale)
        if masks is not None:
            masks.append(valid)
        if photos is not None:
            photo, other = view.load_images([scale, photos_at])
            photos.append(other)
        else:
            photo = view.load_image(scale)
        rgb = torch.from_numpy(photo.reshape(-1, 3).copy())
        uvst_parts.append(uvst[valid].to(coord_dtype))
        rgb_parts.append(rgb[valid])
        index_parts.append(torch.full((int(valid.sum()),), i, dtype=torch.int16))
        if pixel_steps:
            step_parts.append(view_pixel_steps(view, slab, scale, uvst)[valid].to(torch.float16))
        if on_view is not None:
            on_view(i, len(views), view)
    return RaySet(torch.cat(uvst_parts), torch.cat(rgb_parts), torch.cat(index_parts), [v.name for v in views],
                  torch.cat(step_parts) if pixel_steps else None)


def kept_rayset(slot: str, views: list[View], slab: Slab, scale: float, on_view=None, pixel_steps: bool = False,
                masks: list | None = None, photos_at: float | None = None, photos: list | None = None) -> RaySet:
    """build_rayset, or, within a training call (memo.kept_while_training) and for the same
    inputs as the last set in `slot`, that set (with its masks and photos) again without
    reading a photo: a model's members and the better-of-two-starts rule train the same photos
    again (CanClip's 26 photos at 480x270, one thread: 1.6 s a run, a third of it decoding
    them).  The set is shared, not copied: training only reads it."""
    built_masks = []
    built_photos = [] if photos is not None else None
    key = inputs_key(views, slab.to_dict(), scale, pixel_steps, photos_at if photos is not None else None)
    rays, view_masks, view_photos = kept(slot, key, lambda: (
        build_rayset(views, slab, scale, on_view=on_view, pixel_steps=pixel_steps, masks=built_masks,
                     photos_at=photos_at, photos=built_photos), built_masks, built_photos))
    if masks is not None:
        masks.extend(view_masks)
    if photos is not None:
        photos.extend(view_photos)
    return rays


def mean_colour(rays: RaySet) -> np.ndarray:
    return (rays.rgb.float().mean(0) / 255.0).cpu().numpy()

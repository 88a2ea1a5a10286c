"""Pixel jitter (neulf_core/dataset.py): each training ray moved to a random point of its
pixel, from each ray's own change of (u, v, s, t) for one pixel step."""

from __future__ import annotations

import json

import torch

from neulf_core.dataset import build_rayset, view_uvst
from neulf_core.scene import load_scene, split_views
from neulf_core.slab import fit_slab
from neulf_core.train import TrainConfig, train


def _rays(tiny_scene, pixel_steps=True):
    scene = load_scene(tiny_scene)
    views, _ = split_views(scene, holdout_every=0)
    slab = fit_slab(scene, views)
    return views, slab, build_rayset(views[:2], slab, 1.0, pixel_steps=pixel_steps)


def test_each_ray_knows_its_pixel_step(tiny_scene):
    views, slab, rays = _rays(tiny_scene)
    assert rays.pixel_step.shape == (len(rays), 2, 4) and rays.pixel_step.dtype == torch.float16
    assert _rays(tiny_scene, pixel_steps=False)[2].pixel_step is None
    # The first view's rays (all valid here) in row-major order: a step right is the next
    # pixel's ray, a step down the ray one row below.
    camera = views[0].scaled_camera(1.0)
    width, height = int(camera.width), int(camera.height)
    uvst, valid = view_uvst(views[0], slab, 1.0)
    assert bool(valid.all())
    grid = uvst.reshape(height, width, 4)
    steps = rays.pixel_step[: width * height].float().reshape(height, width, 2, 4)
    assert torch.allclose(steps[:, :-1, 0], grid[:, 1:] - grid[:, :-1], atol=2e-4)
    assert torch.allclose(steps[:-1, :, 1], grid[1:] - grid[:-1], atol=2e-4)
    assert float(steps.abs().max()) > 1e-3  # a real step, not zero


def test_a_batch_moves_each_ray_inside_its_pixel_only_when_asked(tiny_scene):
    _, _, rays = _rays(tiny_scene)
    index = torch.arange(0, len(rays), 7)
    centre, rgb = rays.batch(index)
    assert torch.equal(centre, rays.uvst[index].float())
    moved, rgb_moved = rays.batch(index, torch.Generator().manual_seed(0))
    assert torch.equal(rgb, rgb_moved) and not torch.equal(moved, centre)
    # Inside the pixel: at most half a step along each pixel axis from the centre ray.
    bound = 0.5 * rays.pixel_step[index].float().abs().sum(1) + 1e-6
    assert bool(((moved - centre).abs() <= bound).all())
    half, _ = rays.batch(index, torch.Generator().manual_seed(0), jitter=0.5)  # a square half a pixel wide:
    assert torch.allclose(half - centre, 0.5 * (moved - centre), atol=1e-6)  # the same draws, half the way
    assert torch.equal(rays.batch(index, torch.Generator().manual_seed(0), jitter=0.0)[0], centre)
    again, _ = rays.batch(index, torch.Generator().manual_seed(0))
    assert torch.equal(again, moved)  # drawn from the generator: a seeded run repeats
    part = rays.subset(50, torch.Generator().manual_seed(1))
    assert part.pixel_step.shape == (50, 2, 4) and rays.to("cpu").pixel_step is rays.pixel_step


def test_training_records_the_choice_and_trains_without_it_too(tiny_scene, tmp_path):
    common = dict(preset="fast", steps=30, batch_size=256, field_overrides={"texture_size": [16, 16]},
                  validate_seconds=1e9, checkpoint_seconds=1e9, teacher=False, refine_poses=False)
    for jitter in (1.0, 0.0):
        result = train(tiny_scene, tmp_path / str(jitter), TrainConfig(pixel_jitter=jitter, **common))
        meta = json.loads((tmp_path / str(jitter) / "model.json").read_text())
        assert result.status == "finished" and meta["train_config"]["pixel_jitter"] == jitter
    assert TrainConfig().pixel_jitter == 0.0  # off by default: real photos lose (docs/TRAINING.md)


def test_the_command_line_turns_it_on():
    from neulf_core.cli import build_parser

    parser = build_parser()
    assert parser.parse_args(["train", "scene", "--out", "m", "--steps", "5"]).pixel_jitter == 0.0
    assert parser.parse_args(["train", "scene", "--out", "m", "--steps", "5", "--pixel-jitter", "0.5"]).pixel_jitter == 0.5

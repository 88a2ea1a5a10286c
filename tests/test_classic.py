"""Classic light field rendering from the training photos (the baseline and Blender preview)."""

from __future__ import annotations

import numpy as np

from conftest import look_at_rotation, render_tiny_view, tiny_camera, TINY_LOOK_AT
from neulf_core.classic import ClassicLightField
from neulf_core.metrics import psnr
from neulf_core.scene import load_scene, split_views
from neulf_core.slab import fit_slab


def _classic(tiny_scene):
    scene = load_scene(tiny_scene)
    train_views, held_out = split_views(scene, holdout_every=0)
    return scene, ClassicLightField(train_views, fit_slab(scene, train_views), 1.0)


def test_a_training_view_is_reproduced(tiny_scene):
    scene, classic = _classic(tiny_scene)
    view = scene.views[4]
    photo = view.load_image().astype(np.float32) / 255
    assert psnr(classic.render_view(view, 1.0, mode="plane"), photo) > 45


def test_a_novel_view_between_cameras_matches_the_analytic_image(tiny_scene):
    """A camera between the rig's cameras sees the slanted textured plane; both modes must
    render it (the sweep's advantage on real depth ranges is measured in docs/BENCHMARKS.md)."""
    scene, classic = _classic(tiny_scene)
    camera = tiny_camera()
    centre = np.array([0.06, -0.05, 0.02])
    R = look_at_rotation(centre, TINY_LOOK_AT)
    t = -R @ centre
    truth = render_tiny_view(camera, R, t)
    K = camera.calibration_matrix()
    plane = psnr(classic.render(K, camera.width, camera.height, R, t, mode="plane"), truth)
    sweep = psnr(classic.render(K, camera.width, camera.height, R, t, mode="sweep", depths=24), truth)
    assert plane > 35 and sweep > 35, (plane, sweep)


def test_the_sweep_projects_each_plane_where_the_cameras_see_it(tiny_scene):
    """The sweep's line per ray (`_projection`: base + s * step, computed once per render)
    puts the point at distance s where projecting it through each photo's R, t and K does,
    and says alike which photos see it."""
    import torch
    import torch.nn.functional as F

    from neulf_core.rays import view_rays

    scene, classic = _classic(tiny_scene)
    view = scene.views[4]
    origin, directions = (torch.as_tensor(a, dtype=torch.float32) for a in view_rays(view.camera, view.R, classic.slab.origin_relative_t(view.R, view.t)))  # (rays relative to the slab origin)
    index = torch.tensor([0, 3, 7])
    photos = classic.images[index].float() / 255
    base, step = classic._projection(index, origin, directions)
    height, width = classic.images.shape[2:]
    seen = []
    for distance in (0.3, 2.0, 3.0, 5.0):
        colours, inside = classic._sample(base, step, torch.full((len(directions),), distance), photos)
        camera = (origin + directions * distance) @ classic.R[index].transpose(1, 2) + classic.t[index][:, None]
        pixel = camera @ classic.K[index].transpose(1, 2)
        pixel = pixel[..., :2] / pixel[..., 2:]
        grid = torch.stack([pixel[..., 0] / width * 2 - 1, pixel[..., 1] / height * 2 - 1], -1)
        expected = F.grid_sample(photos, grid[:, :, None], mode="bilinear", padding_mode="border", align_corners=False)
        assert torch.allclose(colours, expected[..., 0], atol=1e-4)
        agree = inside == ((grid.abs() <= 1).all(-1) & (camera[..., 2] > 0))
        assert agree.float().mean() > 0.999  # (a point on a photo's very edge may round either way)
        seen.append(inside)
    seen = torch.cat(seen, 1)
    assert bool(seen.any()) and not bool(seen.all())  # points inside the photos and outside them both checked


def test_photos_of_different_sizes_are_swept_together(tiny_scene, tmp_path):
    """One photo file at half the size of the others (scene.py scales its intrinsics to the
    file): the sweep resamples it to the others' size with its K, so it renders and gives the
    depth teacher its targets as the full-size photo does (before: torch.stack failed)."""
    import shutil

    from PIL import Image

    from neulf_core.teacher import compute_sweep_depth_targets

    folder = tmp_path / "mixed"
    shutil.copytree(tiny_scene, folder)
    small = folder / "images" / "view_02.png"
    Image.open(small).resize((24, 18), Image.BILINEAR).save(small)
    mixed = load_scene(folder)
    assert mixed.views[2].size == (24, 18)
    train_views, _ = split_views(mixed, holdout_every=0)
    classic = ClassicLightField(train_views, fit_slab(mixed, train_views), 1.0)
    _, full = _classic(tiny_scene)
    assert classic.images.shape == full.images.shape
    np.testing.assert_allclose(classic.K.numpy(), full.K.numpy(), rtol=1e-6)  # its K scaled back with it
    camera = tiny_camera()
    centre = np.array([0.1, -0.02, 0.0])  # next to view_02, which it sees most of
    R = look_at_rotation(centre, TINY_LOOK_AT)
    truth = render_tiny_view(camera, R, -R @ centre)
    K = camera.calibration_matrix()
    assert psnr(classic.render(K, camera.width, camera.height, R, -R @ centre, mode="plane"), truth) > 30
    # The photo itself, at its own size, through the others (the depth teacher's render).
    image = classic.render_view(mixed.views[2], 1.0, mode="sweep", depths=8, exclude=2)
    assert image.shape == (18, 24, 3)
    unit, confidence = compute_sweep_depth_targets(train_views, classic.slab, 1.0, sweep_scale=1.0)
    assert unit.shape == confidence.shape == (8 * 48 * 36 + 24 * 18,)
    assert bool(unit.isfinite().all()) and bool(confidence.isfinite().all())

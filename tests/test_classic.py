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
    origin, directions = (torch.as_tensor(a, dtype=torch.float32) for a in view_rays(view.camera, view.R, view.t))
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

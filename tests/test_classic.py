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

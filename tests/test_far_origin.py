"""A COLMAP model's frame is arbitrary: a georeferenced or merged one can sit 1e5-1e7 units from
its world's origin, where float32 world coordinates are coarser than the camera rig.  Rendering
(render.LightField) and the plane sweep (classic.py, the depth teacher's) make their rays
relative to the slab's origin in float64 first, so the same capture moved far away renders the
same picture.  (Before: 1e7 off, the model that scores 28.9 dB rendered 19.7 dB; the sweep's
depth targets were off by 0.15 of the depth range on average.)"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from conftest import look_at_rotation
from neulf_core.classic import ClassicLightField
from neulf_core.cli import main
from neulf_core.render import LightField
from neulf_core.scene import load_scene, split_views
from neulf_core.slab import fit_slab

FAR = np.array([1.0e7, -2.0e7, 3.0e6])


def moved(view, offset=FAR):
    """The view with the world moved by `offset` (the camera centre moves with it)."""
    return replace(view, t=view.t - view.R @ offset)


@pytest.fixture(scope="module")
def light_field(tiny_scene, tmp_path_factory):
    out = tmp_path_factory.mktemp("far") / "model"
    assert main(["train", str(tiny_scene), "--out", str(out), "--steps", "30", "--batch-size", "512",
                 "--validate-seconds", "1e9"]) == 0
    return LightField.load(out, "cpu")


def far_copy(light_field: LightField) -> LightField:
    return LightField(light_field.field, replace(light_field.slab, origin=light_field.slab.origin + FAR),
                      light_field.meta, light_field.device)


@pytest.mark.parametrize("options", [{}, {"pixel_samples": 4}, {"aperture": 0.02, "focus_distance": 3.0}],
                         ids=["pinhole", "pixel samples", "refocus"])
def test_a_camera_far_from_the_origin_renders_as_near_it(light_field, options):
    centre = np.array([0.04, -0.03, 0.0])
    R = look_at_rotation(centre, np.array([0.0, 0.0, 3.0]))
    K = np.array([[40.0, 0, 16], [0, 40.0, 12], [0, 0, 1]])
    near = light_field.render(K, 32, 24, R, -R @ centre, **options)
    far = far_copy(light_field).render(K, 32, 24, R, -R @ (centre + FAR), **options)
    assert np.abs(near.rgb - far.rgb).max() < 2e-3, np.abs(near.rgb - far.rgb).max()
    np.testing.assert_allclose(far.depth, near.depth, rtol=1e-4)
    assert far.warnings == near.warnings


def test_a_registered_view_far_from_the_origin_renders_as_near_it(light_field, tiny_scene):
    view = load_scene(tiny_scene).views[2]
    near = light_field.render_view(view, 0.5)
    far = far_copy(light_field).render_view(moved(view), 0.5)
    assert np.abs(near.rgb - far.rgb).max() < 2e-3
    np.testing.assert_allclose(far.depth, near.depth, rtol=1e-4)


def test_the_plane_sweep_far_from_the_origin_sweeps_as_near_it(tiny_scene):
    scene = load_scene(tiny_scene)
    train_views, _ = split_views(scene, holdout_every=0)
    slab = fit_slab(scene, train_views)
    near = ClassicLightField(train_views, slab, 1.0)
    far = ClassicLightField([moved(v) for v in train_views], replace(slab, origin=slab.origin + FAR), 1.0)
    view = scene.views[4]
    image, depth = near.render_view(view, 1.0, exclude=4, with_depth=True)
    far_image, far_depth = far.render_view(moved(view), 1.0, exclude=4, with_depth=True)
    assert np.abs(image - far_image).max() < 2e-3
    np.testing.assert_allclose(far_depth.unit.numpy(), depth.unit.numpy(), atol=1e-3)


def test_training_rays_and_camera_centres_far_from_the_origin_are_as_near_it(tiny_scene):
    """The training side: the rays' (u, v, s, t), the multi-view losses' camera neighbours and
    the pose corrections' camera centres are all made in the slab's frame in float64 before
    they become float32, so the capture moved 1e7 away trains on the same numbers."""
    from neulf_core.consistency import camera_neighbours
    from neulf_core.dataset import view_uvst
    from neulf_core.poses import PoseRefinement

    scene = load_scene(tiny_scene)
    train_views, _ = split_views(scene, holdout_every=8)
    slab = fit_slab(scene, train_views)
    far_slab = replace(slab, origin=slab.origin + FAR)
    far_views = [moved(v) for v in train_views]
    near_uvst, near_valid = view_uvst(train_views[1], slab, 0.5)
    far_uvst, far_valid = view_uvst(far_views[1], far_slab, 0.5)
    assert bool((near_valid == far_valid).all())
    assert float((near_uvst - far_uvst).abs().max()) < 1e-5
    centres = np.array([v.center for v in train_views])
    far_centres = np.array([v.center for v in far_views])
    np.testing.assert_allclose(far_centres - centres, np.broadcast_to(FAR, centres.shape), rtol=0, atol=1e-6)
    near_neighbours, far_neighbours = camera_neighbours(centres, slab), camera_neighbours(far_centres, far_slab)
    # (the rig is a grid: cameras at equal distances may swap places in the order, so compare the
    # chosen neighbours' distances, which are what the weights follow)
    gap = lambda n: (n.centres[n.index] - n.centres[:, None]).norm(dim=-1)
    assert float((gap(near_neighbours) - gap(far_neighbours)).abs().max()) < 1e-6
    assert float((near_neighbours.weights - far_neighbours.weights).abs().max()) < 1e-6
    assert float((near_neighbours.centres - far_neighbours.centres).abs().max()) < 1e-6
    assert float((PoseRefinement(slab, centres).centres - PoseRefinement(far_slab, far_centres).centres).abs().max()) < 1e-6

"""Synthetic-aperture refocus: lens sampling, ray geometry, and the pinhole limit."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from neulf_core.rays import pinhole_rays
from neulf_core.refocus import lens_rays, lens_samples, max_blur_radius_px, sample_count


def test_lens_samples_cover_the_unit_disk():
    assert np.array_equal(lens_samples(1), np.zeros((1, 2)))
    points = lens_samples(64)
    assert points.shape == (64, 2)
    radius = np.linalg.norm(points, axis=1)
    assert radius.max() <= 1.0 and radius.min() < 0.2 and radius.max() > 0.9
    assert np.abs(points.mean(0)).max() < 0.05


def test_sample_count_follows_the_blur():
    assert sample_count(0.3) == 1                    # a pinhole costs one ray
    assert 4 <= sample_count(1.5) < sample_count(3.0) <= 96
    assert sample_count(100.0) == 96
    # Blur radius: f * A * |1/Z - 1/focus|, worst over the depth range.
    assert abs(max_blur_radius_px(500.0, 0.1, 2.0, 1.0, 4.0) - 500 * 0.1 * 0.5) < 1e-12


def test_every_lens_ray_of_a_pixel_meets_its_focal_point():

    angle = 0.3
    R = np.array([[np.cos(angle), 0, -np.sin(angle)], [0, 1, 0], [np.sin(angle), 0, np.cos(angle)]])
    t = np.array([0.2, -0.1, 0.5])
    K = np.array([[80.0, 0, 31.0], [0, 82.0, 22.0], [0, 0, 1]])
    origin, directions = pinhole_rays(K, R, t, 64, 48)
    focus = 3.7
    focal = []
    for point in lens_samples(12):
        lens_origin, d = lens_rays(origin, directions, R, focus, 0.25, point)
        # The lens point lies in the camera's x-y plane within the aperture.
        offset = (lens_origin[0] - origin).numpy()
        assert abs(offset @ R[2]) < 1e-12 and np.linalg.norm(offset) <= 0.25 + 1e-12
        # Where this ray reaches depth `focus` along the optical axis:
        length = (focus - (lens_origin - origin) @ torch.as_tensor(R[2])) / (d @ torch.as_tensor(R[2]))
        focal.append((lens_origin + d * length[:, None]).numpy())
    focal = np.stack(focal)
    assert np.abs(focal - focal[0]).max() < 1e-9
    # ... which is the pinhole ray's point at that depth.
    pinhole_point = (origin + directions * (focus / (directions @ torch.as_tensor(R[2])))[:, None]).numpy()
    assert np.abs(focal[0] - pinhole_point).max() < 1e-9


def test_f_stop_gives_the_thin_lens_aperture_radius():
    from neulf_core.refocus import aperture_from_f_stop

    assert abs(aperture_from_f_stop(0.05, 2.0) - 0.0125) < 1e-15  # a 50 mm f/2 lens: 25 mm wide


@pytest.fixture(scope="module")
def distorted_view_and_model(tiny_scene, tmp_path_factory):
    """A model of the tiny scene and one of its views seen through a strongly distorted lens
    (SIMPLE_RADIAL, k = -0.25: its corners 3-4 pixels from its pinhole part's)."""
    from dataclasses import replace

    import pycolmap

    from neulf_core.cli import main
    from neulf_core.render import LightField
    from neulf_core.scene import load_scene

    out = tmp_path_factory.mktemp("refocus") / "model"
    assert main(["train", str(tiny_scene), "--out", str(out), "--steps", "200", "--batch-size", "1024",
                 "--validate-seconds", "1e9", "--members", "1"]) == 0
    view = load_scene(tiny_scene).views[4]
    c = view.camera
    camera = pycolmap.Camera(model="SIMPLE_RADIAL", width=c.width, height=c.height,
                             params=[c.params[0], c.params[2], c.params[3], -0.25])
    return replace(view, camera=camera), LightField.load(out, "cpu")


def test_a_refocused_registered_view_keeps_its_own_lens_distortion(distorted_view_and_model):
    """render_view refocuses through the view's own camera model: focused on its surface, the
    picture is its plain render (41.9 dB here); through the view's pinhole part, as before, the
    pixels moved and it scored 17.7 dB against it."""
    from neulf_core.metrics import psnr

    view, light_field = distorted_view_and_model
    plain = light_field.render_view(view, 1.0)
    focus = float(plain.depth[18, 24])
    refocused = light_field.render_view(view, 1.0, aperture=0.3, focus_distance=focus)
    assert light_field._lens_plan(view.camera.calibration_matrix(), focus, 0.3, 256) is not None  # (a real lens)
    assert psnr(refocused.rgb, plain.rgb) > 35
    pinhole_part = light_field.render(view.camera.calibration_matrix(), view.camera.width, view.camera.height,
                                      view.R, view.t, aperture=0.3, focus_distance=focus)
    assert psnr(pinhole_part.rgb, plain.rgb) < 25


def test_a_registered_view_s_depth_pick_reads_its_own_depth_map(distorted_view_and_model):
    view, light_field = distorted_view_and_model
    depth = light_field.render_view(view, 1.0).depth
    for x, y in [(24, 18), (2, 1), (45, 33)]:
        assert light_field.view_depth_at(view, 1.0, x + 0.5, y + 0.5) == pytest.approx(float(depth[y, x]), rel=1e-5)

"""Geometry: camera rays against pycolmap's own projection, the light slab, the
forward-facing check, and the conversion of the field's depth to optical-axis depth."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pycolmap
import pytest
import torch

from conftest import look_at_rotation, scene_or_skip
from neulf_core.errors import NeulfError
from neulf_core.fields import build_field, make_config
from neulf_core.rays import pinhole_K, pinhole_rays, pixel_centres, view_rays
from neulf_core.render import LightField
from neulf_core.scene import Scene, View, load_scene, split_views
from neulf_core.slab import Slab, fit_slab, slab_frame

CAMERAS = {
    "PINHOLE": (320, 240, [300.0, 310.0, 161.0, 118.5]),
    "SIMPLE_RADIAL": (320, 240, [300.0, 160.0, 120.0, -0.18]),
    "RADIAL": (320, 240, [300.0, 158.0, 122.0, -0.12, 0.02]),
    "OPENCV": (320, 240, [300.0, 305.0, 158.0, 121.0, -0.12, 0.03, 0.001, -0.0015]),
    "OPENCV_FISHEYE": (320, 240, [200.0, 202.0, 160.0, 120.0, 0.05, -0.01, 0.002, -0.0005]),
    "FULL_OPENCV": (320, 240, [300.0, 305.0, 158.0, 121.0, -0.1, 0.02, 0.001, -0.001, 0.001, 0.0005, 0.0002, 0.0001]),
}


def random_pose(rng) -> pycolmap.Rigid3d:
    quat = rng.normal(size=4)
    quat /= np.linalg.norm(quat)
    return pycolmap.Rigid3d(pycolmap.Rotation3d(quat), rng.normal(size=3) * 2.0)


def test_pixel_centres_are_row_major_at_half_pixels():
    pixels = pixel_centres(3, 2)
    np.testing.assert_array_equal(pixels, [[0.5, 0.5], [1.5, 0.5], [2.5, 0.5], [0.5, 1.5], [1.5, 1.5], [2.5, 1.5]])


def sample_pixels(camera: pycolmap.Camera, rng) -> np.ndarray:
    """A grid of pixel centres including the four corner pixels, plus random positions."""
    width, height = int(camera.width), int(camera.height)
    centres = pixel_centres(width, height).reshape(height, width, 2)
    grid = centres[::7, ::7].reshape(-1, 2)
    corners = centres[[0, 0, -1, -1], [0, -1, 0, -1]]
    random = rng.uniform([0, 0], [width, height], size=(200, 2))
    return np.concatenate([grid, corners, random])


def assert_round_trip(camera: pycolmap.Camera, pose: pycolmap.Rigid3d, rng, pixels=None):
    matrix = np.asarray(pose.matrix())
    R, t = matrix[:, :3], matrix[:, 3]
    pixels = sample_pixels(camera, rng) if pixels is None else pixels
    origin, directions = view_rays(camera, R, t, pixels)
    assert directions.shape == (len(pixels), 3)
    np.testing.assert_allclose(np.linalg.norm(directions, axis=1), 1.0, atol=1e-12)
    # The origin is the camera centre pycolmap reports.
    np.testing.assert_allclose(origin, pose.inverse().translation, atol=1e-9)
    depths = rng.uniform(0.5, 20.0, size=len(pixels))
    points = origin + depths[:, None] * directions
    in_camera = pose * points  # pycolmap's own world -> camera transform
    assert np.all(in_camera[:, 2] > 0), "points along a camera's rays must lie in front of it"
    projected = np.asarray(camera.img_from_cam(in_camera))
    error = np.abs(projected - pixels).max()
    assert error < 1e-4, f"{camera.model_name}: ray round trip off by {error:.2e} px"


@pytest.mark.parametrize("model", sorted(CAMERAS))
def test_view_rays_round_trip_through_pycolmap_projection(model):
    width, height, params = CAMERAS[model]
    camera = pycolmap.Camera(model=model, width=width, height=height, params=params)
    rng = np.random.default_rng(sorted(CAMERAS).index(model))
    for _ in range(3):
        assert_round_trip(camera, random_pose(rng), rng)


def test_view_rays_default_pixels_are_all_pixel_centres():
    camera = pycolmap.Camera(model="OPENCV", width=20, height=10, params=CAMERAS["OPENCV"][2][:4] + [-0.1, 0.0, 0.0, 0.0])
    R, t = np.eye(3), np.zeros(3)
    _, all_dirs = view_rays(camera, R, t)
    _, explicit = view_rays(camera, R, t, pixel_centres(20, 10))
    assert all_dirs.shape == (200, 3)
    np.testing.assert_array_equal(all_dirs, explicit)


def test_view_rays_round_trip_real_canclip_camera(shared_data):
    scene_dir = scene_or_skip(shared_data, "canclip")
    recon = pycolmap.Reconstruction(str(scene_dir / "sparse" / "0"))
    image = sorted(recon.images.values(), key=lambda im: im.name)[3]
    camera = recon.cameras[image.camera_id]
    assert camera.model_name == "SIMPLE_RADIAL" and camera.params[3] < -0.15
    rng = np.random.default_rng(5)
    assert_round_trip(camera, image.cam_from_world(), rng)
    # ... and through the scene loader's view, which must hold the same camera and pose.
    view = load_scene(scene_dir).view(image.name)
    np.testing.assert_allclose(view.camera.params, camera.params)
    pixels = sample_pixels(camera, rng)
    origin, directions = view_rays(view.camera, view.R, view.t, pixels)
    points = origin + 5.0 * directions
    projected = np.asarray(camera.img_from_cam(image.cam_from_world() * points))
    assert np.abs(projected - pixels).max() < 1e-4


# ----------------------------------------------------------------------------- pinhole rays (torch)


def test_pinhole_rays_equal_view_rays_for_a_pinhole_camera():
    width, height = 37, 23
    camera = pycolmap.Camera(model="PINHOLE", width=width, height=height, params=[41.0, 44.5, 17.25, 12.75])
    rng = np.random.default_rng(11)
    pose = random_pose(rng)
    R, t = np.asarray(pose.matrix())[:, :3], np.asarray(pose.matrix())[:, 3]
    K = pinhole_K(camera)
    np.testing.assert_allclose(K, [[41.0, 0, 17.25], [0, 44.5, 12.75], [0, 0, 1]])
    origin, directions = view_rays(camera, R, t)
    origin_t, directions_t = pinhole_rays(K, R, t, width, height, dtype=torch.float64)
    assert directions_t.dtype == torch.float64 and directions_t.shape == (width * height, 3)
    np.testing.assert_allclose(origin_t.numpy(), origin, atol=1e-12)
    assert np.abs(directions_t.numpy() - directions).max() < 1e-9

    band = slice(5, 12)
    _, band_dirs = pinhole_rays(K, R, t, width, height, dtype=torch.float64, rows=band)
    assert band_dirs.shape == (7 * width, 3)
    np.testing.assert_allclose(band_dirs.numpy(), directions.reshape(height, width, 3)[5:12].reshape(-1, 3), atol=1e-12)
    _, last_dirs = pinhole_rays(K, R, t, width, height, dtype=torch.float64, rows=slice(20, 99))
    np.testing.assert_allclose(last_dirs.numpy(), directions.reshape(height, width, 3)[20:].reshape(-1, 3), atol=1e-12)
    origin32, single = pinhole_rays(K, R, t, width, height, dtype=torch.float32)
    assert single.dtype == torch.float32 and origin32.dtype == torch.float32
    assert np.abs(single.numpy() - directions).max() < 1e-6


def test_pinhole_rays_with_skew_project_back_to_their_pixels():
    width, height = 16, 12
    K = np.array([[30.0, 2.5, 8.3], [0.0, 28.0, 5.9], [0.0, 0.0, 1.0]])
    rng = np.random.default_rng(2)
    pose = random_pose(rng)
    R, t = np.asarray(pose.matrix())[:, :3], np.asarray(pose.matrix())[:, 3]
    origin, directions = pinhole_rays(K, R, t, width, height, dtype=torch.float64)
    points = origin.numpy() + 3.0 * directions.numpy()
    homogeneous = (points @ R.T + t) @ K.T
    np.testing.assert_allclose(homogeneous[:, :2] / homogeneous[:, 2:], pixel_centres(width, height), atol=1e-9)


# ----------------------------------------------------------------------------- the slab

REAL_SCENES = {  # scene: (images folder or None, image scale for the check)
    "canclip": (None, 0.125),
    "statue": (None, 0.125),
    "fern": (None, 0.25),
    "hci_antinous": (None, 0.125),
}


@pytest.fixture(scope="module")
def real_slabs(shared_data):
    """name -> (scene, train views, slab, scale): loaded once per module."""
    cache = {}

    def get(name):
        if name not in cache:
            scene = load_scene(scene_or_skip(shared_data, name))
            train, _ = split_views(scene)
            scale = REAL_SCENES[name][1]
            cache[name] = (scene, train, fit_slab(scene, train, scale=scale), scale)
        return cache[name]

    return get


def synthetic_rig(columns=4, rows=3, spacing=0.2, model="SIMPLE_RADIAL", k=-0.1, converge=True):
    """A forward-facing rig: cameras on a tilted grid, all looking at one point (or parallel),
    sparse points scattered at depths 2.5 .. 6 in front of them."""
    if model == "SIMPLE_RADIAL":
        camera = pycolmap.Camera(model=model, width=40, height=30, params=[38.0, 20.0, 15.0, k])
    else:
        camera = pycolmap.Camera(model="PINHOLE", width=40, height=30, params=[38.0, 38.0, 20.0, 15.0])
    tilt = look_at_rotation(np.zeros(3), np.array([0.3, -0.2, 1.0]))  # the rig's own orientation
    target = np.array([0.0, 0.0, 4.0]) @ tilt
    views = []
    for r in range(rows):
        for c in range(columns):
            local = np.array([(c - (columns - 1) / 2) * spacing, (r - (rows - 1) / 2) * spacing, 0.05 * ((r + c) % 2)])
            centre = local @ tilt + np.array([1.0, 2.0, -0.5])
            R = look_at_rotation(centre, target + np.array([1.0, 2.0, -0.5]), down=tilt[1]) if converge else tilt
            views.append(View(f"rig_{r}{c}.png", camera, R, -R @ centre))
    rng = np.random.default_rng(3)
    local_points = np.column_stack([rng.uniform(-1, 1, 200), rng.uniform(-1, 1, 200), rng.uniform(2.5, 6.0, 200)])
    points = local_points @ tilt + np.array([1.0, 2.0, -0.5])
    return Scene(Path("synthetic"), views, points, "colmap")


def all_uvst(slab: Slab, views, scale: float) -> tuple[torch.Tensor, list]:
    parts, rays = [], []
    for view in views:
        camera = view.scaled_camera(scale)
        origin, directions = view_rays(camera, view.R, view.t)
        uvst, valid = slab.rays_to_uvst(torch.from_numpy(origin), torch.from_numpy(directions))
        assert bool(valid.all()), f"{view.name}: a training ray does not cross the slab forwards"
        assert uvst.dtype == torch.float64
        parts.append(uvst)
        rays.append((origin, directions))
    return torch.cat(parts), rays


def check_slab(scene: Scene, train, slab: Slab, scale: float):
    uvst, rays = all_uvst(slab, train, scale)
    lo, hi = uvst.min(0).values.numpy(), uvst.max(0).values.numpy()
    assert np.all(lo >= -1 - 1e-6) and np.all(hi <= 1 + 1e-6), (lo, hi)
    np.testing.assert_allclose(lo, -1.0, atol=1e-6)
    np.testing.assert_allclose(hi, 1.0, atol=1e-6)

    # The uv plane passes through the mean camera centre; the slab axes are orthonormal.
    centres = np.stack([v.center for v in train])
    np.testing.assert_allclose(slab.origin, centres.mean(0), atol=1e-9)
    assert slab.z_uv == 0.0 and slab.z_st > 0
    np.testing.assert_allclose(slab.rotation @ slab.rotation.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(slab.rotation) > 0
    assert abs(slab.to_slab(centres)[:, 2].mean()) < 1e-9 * max(1.0, np.abs(centres).max())
    # The slab axis is the mean viewing direction.
    mean_forward = np.mean([v.forward for v in train], axis=0)
    np.testing.assert_allclose(slab.rotation[2], mean_forward / np.linalg.norm(mean_forward), atol=1e-12)
    assert 0 < slab.z_near < slab.z_st < slab.z_far

    # (u, v, s, t) -> ray reproduces each original ray's line and direction.
    scale_of_scene = float(np.abs(slab.hi - slab.lo).max())
    for view, (origin, directions) in list(zip(train, rays))[:4]:
        d = torch.from_numpy(directions[::5])
        coords, _ = slab.rays_to_uvst(torch.from_numpy(origin), d)
        points, back = slab.uvst_to_rays(coords)
        points, back, d = points.numpy(), back.numpy(), d.numpy()
        np.testing.assert_allclose(np.linalg.norm(np.cross(back, d), axis=1), 0.0, atol=1e-10)
        assert np.all(np.sum(back * d, axis=1) > 0)
        offset = points - origin
        distance_to_line = np.linalg.norm(offset - np.sum(offset * d, axis=1, keepdims=True) * d, axis=1)
        assert distance_to_line.max() < 1e-9 * max(1.0, scale_of_scene)
        np.testing.assert_allclose(slab.to_slab(points)[:, 2], slab.z_uv, atol=1e-9 * max(1.0, scale_of_scene))
        # unnormalised coordinates: the same
        raw, _ = slab.rays_to_uvst(torch.from_numpy(origin), torch.from_numpy(directions[::5]), normalise=False)
        points_raw, _ = slab.uvst_to_rays(raw, normalised=False)
        np.testing.assert_allclose(points_raw.numpy(), points, atol=1e-9 * max(1.0, scale_of_scene))


@pytest.mark.parametrize("name", sorted(REAL_SCENES))
def test_fit_slab_on_real_scenes(real_slabs, name):
    scene, train, slab, scale = real_slabs(name)
    check_slab(scene, train, slab, scale)


@pytest.mark.parametrize("rig", ["converging_barrel", "parallel_pincushion"])
def test_fit_slab_on_a_synthetic_rig(rig):
    """Barrel distortion puts the extreme rays in the image corners; strong pincushion
    distortion on a parallel rig puts them in the middle of the image edges."""
    scene = synthetic_rig(k=-0.1) if rig == "converging_barrel" else synthetic_rig(k=0.3, converge=False)
    train, _ = split_views(scene, holdout_every=0)
    slab = fit_slab(scene, train)
    check_slab(scene, train, slab, 1.0)
    # The st plane sits at the harmonic mean depth of the points (mean disparity), inside their range.
    depths = (scene.points - slab.origin) @ slab.rotation[2]
    assert depths.min() < slab.z_st < depths.max()
    # ... exactly there: the harmonic mean of the points' depths (the 1 % tails left out), not their
    # arithmetic mean (4.1 here against 3.86).
    kept = depths[(depths >= np.percentile(depths, 1)) & (depths <= np.percentile(depths, 99))]
    assert slab.z_st == pytest.approx(1.0 / np.mean(1.0 / kept), rel=1e-9)
    assert slab.z_near == pytest.approx(0.9 * np.percentile(depths, 1), rel=0.05)
    assert slab.z_far == pytest.approx(1.1 * np.percentile(depths, 99), rel=0.05)


def test_rays_more_than_80_degrees_off_the_slab_axis_do_not_cross_it():
    """A ray at 79 degrees to the slab axis crosses the planes; one at 81 does not (nor one
    looking back), and a camera whose corner rays run that far off is refused by the slab."""
    slab = Slab(rotation=np.eye(3), origin=np.zeros(3), z_uv=0.0, z_st=1.0, z_near=0.5, z_far=2.0,
                lo=-np.ones(4), hi=np.ones(4))
    angles = np.radians([0.0, 79.0, 81.0, 100.0])
    directions = torch.from_numpy(np.column_stack([np.sin(angles), np.zeros(4), np.cos(angles)]))
    _, valid = slab.rays_to_uvst(torch.zeros(3, dtype=torch.float64), directions)
    assert valid.tolist() == [True, True, False, False]
    rig = synthetic_rig(model="PINHOLE")
    wide = pycolmap.Camera(model="PINHOLE", width=40, height=30, params=[3.0, 3.0, 20.0, 15.0])  # corners 83 degrees off
    views = [View(v.name, wide, v.R, v.t) for v in rig.views]
    with pytest.raises(NeulfError, match="almost parallel to the light slab"):
        fit_slab(Scene(Path("wide"), views, rig.points, "colmap"), views)


def test_fit_slab_overrides_and_invalid_depths():
    scene = synthetic_rig(model="PINHOLE")
    train = scene.views
    slab = fit_slab(scene, train, st_depth=5.0, uv_depth=0.5, near=2.0, far=8.0)
    assert (slab.z_uv, slab.z_st, slab.z_near, slab.z_far) == pytest.approx((0.5, 5.0, 1.8, 8.8))
    check_uv = slab.to_slab(slab.plane_corners("uv"))[:, 2]
    np.testing.assert_allclose(check_uv, 0.5, atol=1e-12)
    with pytest.raises(NeulfError, match="near"):
        fit_slab(scene, train, near=3.0, far=2.0)
    with pytest.raises(NeulfError, match="beyond the uv plane"):
        fit_slab(scene, train, st_depth=0.5, uv_depth=1.0)
    no_points = Scene(Path("x"), scene.views, np.zeros((0, 3)), "colmap")
    with pytest.raises(NeulfError, match="depth"):
        fit_slab(no_points, train)
    assert fit_slab(no_points, train, st_depth=4.0, near=2.0, far=7.0).z_st == 4.0


def test_llff_scene_without_bounds_needs_the_depths_given():
    """An LLFF poses_bounds.npy of 15 numbers a row has no near/far (scene.depth_bounds None,
    test_scene_loading): the slab says which depths to give instead of failing on an index."""
    rig = synthetic_rig(model="PINHOLE")
    llff = Scene(Path("llff"), rig.views, np.zeros((0, 3)), "llff")
    with pytest.raises(NeulfError, match=r"no usable near/far depths.*--st-depth, --near, --far"):
        fit_slab(llff, llff.views)
    empty = Scene(Path("llff"), rig.views, np.zeros((0, 3)), "llff", depth_bounds=np.zeros((len(rig.views), 0)))
    with pytest.raises(NeulfError, match="no usable near/far depths"):
        fit_slab(empty, empty.views)
    assert fit_slab(llff, llff.views, st_depth=4.0, near=2.0, far=7.0).z_st == 4.0


def test_slab_dict_round_trip_and_planes():
    scene = synthetic_rig()
    slab = fit_slab(scene, scene.views)
    data = json.loads(json.dumps(slab.to_dict()))
    back = Slab.from_dict(data)
    for key in ("rotation", "origin", "lo", "hi"):
        np.testing.assert_array_equal(getattr(back, key), getattr(slab, key))
        assert getattr(back, key).dtype == np.float64
    for key in ("z_uv", "z_st", "z_near", "z_far"):
        assert getattr(back, key) == getattr(slab, key)

    # Plane corners (world) lie on their planes and span the normalisation range.
    for plane, z, axes in (("uv", slab.z_uv, slice(0, 2)), ("st", slab.z_st, slice(2, 4))):
        corners = np.asarray(data[f"{plane}_corners_world"])
        np.testing.assert_allclose(corners, slab.plane_corners(plane))
        local = slab.to_slab(corners)
        np.testing.assert_allclose(local[:, 2], z, atol=1e-9)
        np.testing.assert_allclose(local[:, :2].min(0), slab.lo[axes], atol=1e-9)
        np.testing.assert_allclose(local[:, :2].max(0), slab.hi[axes], atol=1e-9)
        np.testing.assert_allclose(slab.to_world(local), corners, atol=1e-9)
        # The rays through opposite corners have normalised coordinates of +-1 on that plane.
    ray_points, _ = slab.uvst_to_rays(torch.tensor([[-1.0, -1.0, 1.0, 1.0]], dtype=torch.float64))
    np.testing.assert_allclose(ray_points.numpy()[0], slab.plane_corners("uv")[0], atol=1e-9)


def test_depth_unit_mapping_is_inverse_and_linear_in_disparity():
    scene = synthetic_rig()
    slab = fit_slab(scene, scene.views)
    unit = torch.linspace(0, 1, 101, dtype=torch.float64)
    depth = slab.depth_from_unit(unit)
    assert float(depth[0]) == pytest.approx(slab.z_far) and float(depth[-1]) == pytest.approx(slab.z_near)
    assert torch.all(depth[1:] < depth[:-1])
    np.testing.assert_allclose(slab.unit_from_depth(depth).numpy(), unit.numpy(), atol=1e-12)
    disparity = 1.0 / depth
    np.testing.assert_allclose(np.diff(disparity.numpy()), float(disparity[1] - disparity[0]), rtol=1e-9)
    some_depths = torch.tensor([slab.z_near, 0.5 * (slab.z_near + slab.z_far), slab.z_far], dtype=torch.float64)
    np.testing.assert_allclose(slab.depth_from_unit(slab.unit_from_depth(some_depths)).numpy(), some_depths.numpy(), rtol=1e-12)


# ----------------------------------------------------------------------------- forward-facing check


def ring_views(count: int, span_degrees: float):
    camera = pycolmap.Camera(model="PINHOLE", width=32, height=24, params=[30.0, 30.0, 16.0, 12.0])
    views = []
    angles = np.linspace(-span_degrees / 2, span_degrees / 2, count, endpoint=span_degrees < 360)
    for i, angle in enumerate(np.radians(angles)):
        centre = 3.0 * np.array([np.sin(angle), 0.0, -np.cos(angle)])
        R = look_at_rotation(centre, np.zeros(3))
        views.append(View(f"ring_{i:02d}.png", camera, R, -R @ centre))
    return views


def test_360_ring_is_rejected_as_not_forward_facing():
    views = ring_views(12, 360)
    scene = Scene(Path("ring"), views, np.random.default_rng(0).uniform(-0.5, 0.5, (50, 3)), "colmap")
    with pytest.raises(NeulfError) as info:
        fit_slab(scene, views)
    message = str(info.value)
    assert "not forward-facing" in message and "360" in message
    with pytest.raises(NeulfError, match="not forward-facing"):
        slab_frame(ring_views(12, 180))  # a half ring: the cameras still look too many ways


def test_forward_rig_and_modest_arc_pass_the_check():
    rotation, origin = slab_frame(synthetic_rig().views)
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
    rotation, _ = slab_frame(ring_views(7, 40))  # a 40-degree arc looking at one point
    np.testing.assert_allclose(rotation[2], [0, 0, 1], atol=1e-9)


# ----------------------------------------------------------------------------- depth along the optical axis


def constant_depth_light_field(slab: Slab, unit_depth: float) -> LightField:
    """A real (tiny) planes field whose depth output is the constant `unit_depth`."""
    config = make_config("planes", {"angular_res": 2, "spatial_res": [4], "channels": 2, "hidden": 4, "hidden_layers": 1})
    field_module = build_field("planes", config)
    with torch.no_grad():
        last = field_module.decoder[-1]
        last.weight[3].zero_()
        last.bias[3] = float(np.log(unit_depth / (1 - unit_depth)))
    return LightField(field_module, slab, {"scene": {"mean_colour": [0.2, 0.3, 0.4]}}, torch.device("cpu"))


def plane_axis_depth(slab: Slab, slab_depth: float, R, t, bearings) -> np.ndarray:
    """Optical-axis depth Z of the plane {z_slab . (X - O) = slab_depth} seen along camera
    bearings b (z = 1): X = R^T (Z b - t)  =>  Z = (depth + z.(O + R^T t)) / (z . R^T b)."""
    z = slab.rotation[2]
    return (slab_depth + z @ (slab.origin + R.T @ t)) / ((bearings @ R) @ z)


def test_render_depth_of_a_constant_slab_depth_for_a_tilted_camera():
    scene = synthetic_rig(model="PINHOLE")
    slab = fit_slab(scene, scene.views)
    unit = 0.37
    light_field = constant_depth_light_field(slab, unit)
    slab_depth = float(slab.depth_from_unit(torch.tensor(unit, dtype=torch.float64)))
    assert slab.z_near < slab_depth < slab.z_far

    # A camera near the rig, turned 12 and 8 degrees away from the slab axis.
    centre = slab.to_world(np.array([[0.05, -0.03, 0.1]]))[0]
    target = slab.to_world(np.array([[np.tan(np.radians(12)) * 5, np.tan(np.radians(8)) * 5, 5.0]]))[0]
    R = look_at_rotation(centre, target, down=slab.rotation[1])
    t = -R @ centre
    width, height = 24, 18
    K = np.array([[20.0, 0, 12.5], [0, 21.0, 8.5], [0, 0, 1]])
    rendering = light_field.render(K, width, height, R, t, depth=True, chunk=100)  # several row bands
    assert rendering.valid.all()
    bearings = np.column_stack([pixel_centres(width, height), np.ones(width * height)]) @ np.linalg.inv(K).T
    expected = plane_axis_depth(slab, slab_depth, R, t, bearings).reshape(height, width)
    np.testing.assert_allclose(rendering.depth, expected, rtol=1e-5)
    assert np.ptp(expected) > 0.01 * expected.mean()  # the tilt makes the depth vary across the image

    # _axis_depth directly, in float64 (renders use float32 ray geometry, like training), on rays made
    # relative to the slab origin as render makes them.
    light_field.geometry_dtype = torch.float64
    origin, directions = pinhole_rays(K, R, light_field.slab.origin_relative_t(R, t), width, height, dtype=torch.float64)  # (slab-relative)
    axis = light_field._axis_depth(origin, directions, torch.full((width * height,), slab_depth, dtype=torch.float64),
                                   torch.as_tensor(R[2]))
    np.testing.assert_allclose(axis.numpy(), expected.ravel(), rtol=1e-10)


def test_render_view_depth_through_a_distorted_camera():
    scene = synthetic_rig(model="SIMPLE_RADIAL")
    slab = fit_slab(scene, scene.views)
    unit = 0.8
    light_field = constant_depth_light_field(slab, unit)
    slab_depth = float(slab.depth_from_unit(torch.tensor(unit, dtype=torch.float64)))
    view = scene.views[5]
    rendering = light_field.render_view(view, scale=1.0, chunk=333)
    width, height = view.size
    assert rendering.rgb.shape == (height, width, 3) and rendering.depth.shape == (height, width)
    bearings = np.asarray(view.camera.cam_from_img(pixel_centres(width, height)))
    bearings = np.column_stack([bearings, np.ones(len(bearings))])
    expected = plane_axis_depth(slab, slab_depth, view.R, view.t, bearings).reshape(height, width)
    np.testing.assert_allclose(rendering.depth, expected, rtol=1e-5)


def test_slab_keeps_its_tensors_but_follows_changed_values_and_leaves_them_out_of_pickles():
    """Slab._tensors keeps its tensors per device and dtype (no host copy per training step);
    a changed value gives new ones, inference-mode tensors never reach a backward pass, and a
    pickled or copied slab carries none of them."""
    import copy
    import pickle

    slab = Slab(rotation=np.eye(3), origin=np.zeros(3), z_uv=0.0, z_st=1.0, z_near=0.5, z_far=2.0,
                lo=np.array([-1.0, -1, -2, -2]), hi=np.array([1.0, 1, 2, 2]))
    first = slab._tensors(torch.device("cpu"), torch.float32)
    assert slab._tensors(torch.device("cpu"), torch.float32) is first
    slab.origin = np.array([0.0, 0.0, -0.5])
    moved = slab._tensors(torch.device("cpu"), torch.float32)
    assert moved is not first and torch.equal(moved[1], torch.tensor([0.0, 0.0, -0.5]))
    slab.origin = np.array([0.0, 0.0, -0.25])  # values no tensor was made for yet: made under inference mode
    with torch.inference_mode():
        slab.rays_to_uvst(torch.zeros(3), torch.tensor([[0.0, 0.0, 1.0]]))
    origins = torch.zeros(1, 3, requires_grad=True)
    uvst, _ = slab.rays_to_uvst(origins, torch.tensor([[0.1, 0.0, 1.0]]))
    uvst.sum().backward()  # (an inference-mode tensor here would refuse the backward pass)
    assert origins.grad is not None
    for other in (pickle.loads(pickle.dumps(slab)), copy.deepcopy(slab)):
        assert "_tensor_cache" not in other.__dict__ and np.array_equal(other.origin, slab.origin)


def test_bearings_kept_are_pycolmap_s_and_follow_the_camera():
    """view_rays keeps the bearings it last unprojected (pycolmap's undistortion is a quarter of
    a render_view): asked again they are the same read-only array, equal to pycolmap's; another
    lens, size or set of pixels gives its own."""
    from neulf_core.rays import camera_bearings, pixel_centres

    camera = pycolmap.Camera(model="SIMPLE_RADIAL", width=40, height=30, params=[35.0, 20.0, 15.0, -0.2])
    pixels = pixel_centres(40, 30)
    first = camera_bearings(camera, pixels)
    expected = np.asarray(camera.cam_ray_from_img(pixels), np.float64)
    np.testing.assert_array_equal(first, expected)
    assert camera_bearings(camera, pixels.copy()) is first and not first.flags.writeable
    other = pycolmap.Camera(model="SIMPLE_RADIAL", width=40, height=30, params=[35.0, 20.0, 15.0, -0.1])
    np.testing.assert_array_equal(camera_bearings(other, pixels), np.asarray(other.cam_ray_from_img(pixels)))
    shifted = pixels + 0.25
    np.testing.assert_array_equal(camera_bearings(camera, shifted), np.asarray(camera.cam_ray_from_img(shifted)))
    assert not np.array_equal(camera_bearings(camera, shifted), first)

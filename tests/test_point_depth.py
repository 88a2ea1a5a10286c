"""The SfM points' depth (neulf_core/point_depth.py): keypoints read with the model, points
triangulated again from the training photos alone, one depth target per keypoint ray, and the
trainer pulling toward them only where the model keeps tracks."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pycolmap
import pytest
import torch

from conftest import make_tiny_scene, tiny_camera, tiny_poses
from neulf_core.point_depth import point_depth_targets, triangulate
from neulf_core.scene import load_scene
from neulf_core.slab import fit_slab
from neulf_core.train import TrainConfig, train

POINTS = 40


def plane_points(count: int = POINTS) -> np.ndarray:
    """Points on the tiny scene's plane z = 3 + 0.3 x, inside every view."""
    xy = np.random.default_rng(3).uniform(-0.35, 0.35, size=(count, 2))
    return np.column_stack([xy, 3.0 + 0.3 * xy[:, 0]])


def project(camera: pycolmap.Camera, R: np.ndarray, t: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Pixel coordinates (COLMAP's: pixel (0, 0) spans 0..1) of world points."""
    local = points @ R.T + t
    return (local @ camera.calibration_matrix().T)[:, :2] / local[:, 2:3]


def write_model_with_tracks(folder: Path, points: np.ndarray, seen_by: dict[int, list[int]] | None = None) -> None:
    """The tiny scene's cameras with every point observed (exactly) by the views `seen_by`
    names for it (all nine by default)."""
    camera, poses = tiny_camera(), tiny_poses()
    recon = pycolmap.Reconstruction()
    recon.add_camera_with_trivial_rig(pycolmap.Camera(model=camera.model_name, width=camera.width, height=camera.height,
                                                      params=np.asarray(camera.params), camera_id=1))
    observers = {p: seen_by.get(p, list(range(len(poses)))) if seen_by else list(range(len(poses)))
                 for p in range(len(points))}
    for i, (R, t) in enumerate(poses):
        mine = [p for p in range(len(points)) if i in observers[p]]
        keypoints = project(camera, R, t, points[mine]) if mine else np.zeros((0, 2))
        image = pycolmap.Image(name=f"view_{i:02d}.png", camera_id=1, image_id=i + 1,
                               points2D=pycolmap.Point2DList([pycolmap.Point2D(xy=xy) for xy in keypoints]))
        recon.add_image_with_trivial_frame(image, pycolmap.Rigid3d(np.hstack([R, t.reshape(3, 1)])))
    for p, xyz in enumerate(points):
        track = pycolmap.Track()
        for i in observers[p]:
            track.add_element(i + 1, sorted(q for q in range(len(points)) if i in observers[q]).index(p))
        recon.add_point3D(xyz, track, np.array([128, 128, 128], np.uint8))
    folder.mkdir(parents=True, exist_ok=True)
    recon.write_binary(str(folder))


@pytest.fixture(scope="module")
def tracked_scene(tmp_path_factory) -> Path:
    folder = make_tiny_scene(tmp_path_factory.mktemp("tracked"))
    write_model_with_tracks(folder / "sparse" / "0", plane_points())
    return folder


def test_loading_keeps_each_views_triangulated_keypoints(tracked_scene, tiny_scene):
    scene = load_scene(tracked_scene)
    camera, (R, t) = tiny_camera(), tiny_poses()[4]
    view = scene.views[4]
    assert view.keypoints.shape == (POINTS, 2) and view.point_ids.shape == (POINTS,)
    expected = project(camera, R, t, plane_points())
    assert np.allclose(np.sort(view.keypoints, axis=0), np.sort(expected, axis=0), atol=1e-6)
    assert all(v.keypoints is None for v in load_scene(tiny_scene).views)  # points without tracks


def test_keypoints_follow_photos_smaller_than_the_model_s(tracked_scene, tmp_path):
    """Photos on disk at half the model's size (LLFF's images_2/, a downsized copy): the keypoints
    are read at the photos' size, as the cameras are (at the model's they had pulled the rays of
    pixels twice as far from the corner toward the points' depths)."""
    from PIL import Image

    half = tmp_path / "images_half"
    half.mkdir()
    for photo in sorted((tracked_scene / "images").iterdir()):
        image = Image.open(photo)
        image.resize((image.width // 2, image.height // 2), Image.BOX).save(half / photo.name)
    full, small = load_scene(tracked_scene).views[4], load_scene(tracked_scene, half).views[4]
    assert small.size == (full.size[0] // 2, full.size[1] // 2)
    np.testing.assert_allclose(small.keypoints, full.keypoints * 0.5, atol=1e-9)
    np.testing.assert_array_equal(small.point_ids, full.point_ids)


def test_the_training_photos_alone_triangulate_the_points(tracked_scene):
    views = load_scene(tracked_scene).views
    points = triangulate(views[:3])  # three views of one row of the rig
    assert len(points) == POINTS
    truth = plane_points()
    for pid, xyz in points.items():
        view = views[0]
        index = int(np.flatnonzero(view.point_ids == pid)[0])
        # the point whose keypoint this is: the nearest true point to the triangulated one
        assert np.min(np.linalg.norm(truth - xyz, axis=1)) < 1e-6, (pid, xyz, index)
    assert triangulate(views[:1]) == {}  # one photo places no point


def test_a_point_fewer_than_two_training_photos_see_gives_no_depth(tmp_path):
    folder = make_tiny_scene(tmp_path / "scene")
    points = plane_points(2)
    write_model_with_tracks(folder / "sparse" / "0", points, seen_by={0: [0, 8], 1: [1, 2, 3]})
    views = load_scene(folder).views
    placed = triangulate([views[0], views[1], views[2]])  # point 0: only view 0 of its two is here
    assert len(placed) == 1 and np.allclose(next(iter(placed.values())), points[1], atol=1e-6)


def test_each_keypoints_ray_gets_its_points_depth(tracked_scene):
    scene = load_scene(tracked_scene)
    views = scene.views[:8]
    slab = fit_slab(scene, views)
    unit, mask = point_depth_targets(views, slab, 1.0)
    width, height = int(views[0].camera.width), int(views[0].camera.height)
    assert unit.shape == mask.shape == (len(views) * width * height,)  # every tiny ray crosses the slab
    view = views[2]
    xyz = plane_points()
    truth = torch.as_tensor(slab.to_slab(xyz)[:, 2])
    expected = slab.unit_from_depth(truth).float()
    keypoints = project(tiny_camera(), *tiny_poses()[2], xyz)
    rays = 2 * width * height + np.floor(keypoints[:, 1]).astype(int) * width + np.floor(keypoints[:, 0]).astype(int)
    assert bool(mask[rays].all())
    # two keypoints in one pixel keep one of their depths; the rest are exact
    distinct = np.unique(rays, return_counts=True)[1].max() == 1
    assert torch.allclose(unit[rays], expected, atol=1e-4) or not distinct
    assert int(mask.sum()) <= len(views) * POINTS
    corner = project(tiny_camera(), *tiny_poses()[0], xyz)  # view 0 sees the points it has inside its frame
    inside = (corner >= 0).all(1) & (corner[:, 0] < width) & (corner[:, 1] < height)
    pixels = np.floor(corner[inside]).astype(int)
    assert int(mask[: width * height].sum()) == len(np.unique(pixels[:, 1] * width + pixels[:, 0]))


def test_training_pulls_toward_the_points_only_where_the_model_keeps_tracks(tracked_scene, tiny_scene, tmp_path):
    runs = {"tracks": (tracked_scene, None, None), "off": (tracked_scene, False, None),
            "no tracks": (tiny_scene, None, None),
            "poses refined": (tracked_scene, None, True)}  # placed through poses said to be off: not by default
    recorded = {}
    for name, (scene, point_depth, refine_poses) in runs.items():
        out = tmp_path / name.replace(" ", "_")
        train(scene, out, TrainConfig(steps=3, seed=0, point_depth=point_depth, teacher=False, refine_poses=refine_poses,
                                      validate_seconds=1e9, checkpoint_seconds=1e9))
        recorded[name] = json.loads((out / "model.json").read_text()).get("point_depth")
    scene = load_scene(tracked_scene)
    training = [v for i, v in enumerate(scene.views) if i % 8]  # every 8th view held out, from the first
    expected = int(point_depth_targets(training, fit_slab(scene, training), 1.0)[1].sum())
    assert recorded["tracks"]["rays"] == expected > 0.5 * len(training) * POINTS
    assert recorded["off"] is None and recorded["no tracks"] is None and recorded["poses refined"] is None


def test_training_traces_each_photos_rays_once(tracked_scene, tmp_path, monkeypatch):
    """The sweep teacher and the point depths take the training rays' masks of representable
    pixels (build_rayset's `masks`) instead of tracing every pixel's ray again: a run traces
    each training and held-out view once, with both on."""
    from neulf_core import dataset, point_depth, teacher

    traced = []
    trace = dataset.view_uvst

    def counted(view, *args, **kwargs):
        traced.append(view.name)
        return trace(view, *args, **kwargs)

    for module in (dataset, point_depth, teacher):
        monkeypatch.setattr(module, "view_uvst", counted)
    out = tmp_path / "model"
    train(tracked_scene, out, TrainConfig(steps=3, seed=0, members=1, two_starts=False, validate_seconds=1e9,
                                          checkpoint_seconds=1e9))
    meta = json.loads((out / "model.json").read_text())
    assert meta["point_depth"]["rays"] > 0 and meta["train_config"]["teacher"] is not False
    assert sorted(traced) == sorted(v.name for v in load_scene(tracked_scene).views)


def test_training_decodes_each_photo_once(tracked_scene, tmp_path, monkeypatch):
    """The sweep's smaller photos come from the decode that read the training ones: a run with
    the sweep on decodes each training and held-out photo once."""
    from neulf_core import images

    decoded = []
    decode = images.open_upright

    def counted(path, *args, **kwargs):
        decoded.append(Path(path).name)
        return decode(path, *args, **kwargs)

    monkeypatch.setattr(images, "open_upright", counted)
    out = tmp_path / "model"
    train(tracked_scene, out, TrainConfig(steps=3, seed=0, members=1, two_starts=False, validate_seconds=1e9,
                                          checkpoint_seconds=1e9))
    assert json.loads((out / "model.json").read_text())["train_config"]["teacher"] is not False
    assert sorted(decoded) == sorted(Path(v.image_path).name for v in load_scene(tracked_scene).views)


def test_the_targets_follow_the_masks_they_are_given(tracked_scene):
    """Given masks that leave pixels out, the point depths keep exactly the other pixels' targets,
    in order (the sweep's targets take the same masks the same way)."""
    from neulf_core.dataset import view_uvst
    from neulf_core.teacher import compute_sweep_depth_targets

    scene = load_scene(tracked_scene)
    views = scene.views[:4]
    slab = fit_slab(scene, views)
    full = [view_uvst(v, slab, 1.0)[1] for v in views]
    assert all(bool(m.all()) for m in full)  # every tiny ray crosses the slab: the masks below drop pixels
    masks = [m.clone() for m in full]
    for i, m in enumerate(masks):
        m[i::3] = False
    kept = torch.cat(masks)
    for targets in (lambda r: point_depth_targets(views, slab, 1.0, r),
                    lambda r: compute_sweep_depth_targets(views, slab, 1.0, representable=r)):
        everything, masked = targets(full), targets(masks)
        for whole, part in zip(everything, masked):
            assert torch.equal(part, whole[kept])

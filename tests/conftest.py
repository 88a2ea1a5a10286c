"""Shared fixtures: the reference scenes in ../shared/data (skipped cleanly when absent) and
a tiny synthetic COLMAP scene written here with pycolmap, so the training, checkpoint and
CLI tests run on a fresh checkout.

The synthetic scene: a textured, slightly slanted plane (z = 3 + 0.3 x in world units)
rendered with numpy into a 3x3 grid of PINHOLE cameras at 48x36 that all look at the
plane's centre, plus 3D points sampled on the plane (they give the slab its depth range).
"""

from __future__ import annotations

import importlib
import importlib.util
import os
import struct
import sys
import zlib
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from PIL import Image

SHARED_DATA_ENV = "NEULF_SHARED_DATA"

TINY_WIDTH, TINY_HEIGHT, TINY_FOCAL = 48, 36, 44.0
TINY_LOOK_AT = np.array([0.0, 0.0, 3.0])


def shared_data_dir() -> Path:
    if os.environ.get(SHARED_DATA_ENV):
        return Path(os.environ[SHARED_DATA_ENV]).expanduser()
    return Path(__file__).resolve().parents[2] / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    root = shared_data_dir()
    if not (root / "canclip").is_dir():
        pytest.skip(f"reference scenes not found in {root} (set {SHARED_DATA_ENV})")
    return root


def scene_or_skip(shared_data: Path, name: str) -> Path:
    path = shared_data / name
    if not path.is_dir():
        pytest.skip(f"reference scene {name} not in {shared_data}")
    return path


# ----------------------------------------------------------------------------- writing models


def look_at_rotation(centre: np.ndarray, target: np.ndarray, down=(0.0, 1.0, 0.0)) -> np.ndarray:
    """World-to-camera rotation of a COLMAP camera (x right, y down, z forward) at `centre`."""
    z = np.asarray(target, float) - np.asarray(centre, float)
    z /= np.linalg.norm(z)
    x = np.cross(np.asarray(down, float), z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z])


def write_colmap_model(folder: Path, cameras, poses, names, points=None, fmt: str = "binary") -> Path:
    """Write a COLMAP model with pycolmap.  cameras: one pycolmap.Camera per image (or one
    shared); poses: (R, t) world-to-camera; fmt: binary/text (4.x, with rigs and frames) or
    legacy_binary/legacy_text (cameras, images, points3D only)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    recon = pycolmap.Reconstruction()
    if isinstance(cameras, pycolmap.Camera):
        cameras = [cameras] * len(names)
    camera_ids = {}
    for camera in cameras:
        if id(camera) in camera_ids:
            continue
        cam = pycolmap.Camera(model=camera.model_name, width=camera.width, height=camera.height,
                              params=np.asarray(camera.params), camera_id=len(camera_ids) + 1)
        recon.add_camera_with_trivial_rig(cam)
        camera_ids[id(camera)] = cam.camera_id
    for i, (camera, (R, t), name) in enumerate(zip(cameras, poses, names)):
        image = pycolmap.Image(name=name, camera_id=camera_ids[id(camera)], image_id=i + 1)
        pose = pycolmap.Rigid3d(np.hstack([np.asarray(R, float), np.asarray(t, float).reshape(3, 1)]))
        recon.add_image_with_trivial_frame(image, pose)
    for xyz in (np.zeros((0, 3)) if points is None else points):
        recon.add_point3D(np.asarray(xyz, float), pycolmap.Track(), np.array([128, 128, 128], np.uint8))
    if fmt.endswith("text"):
        recon.write_text(str(folder))
    else:
        recon.write_binary(str(folder))
    if fmt.startswith("legacy"):
        for extra in ("rigs", "frames"):
            for ext in ("bin", "txt"):
                (folder / f"{extra}.{ext}").unlink(missing_ok=True)
    return folder


@pytest.fixture(scope="session")
def colmap_writer():
    return write_colmap_model


# ----------------------------------------------------------------------------- the tiny scene


def plane_texture(points: np.ndarray) -> np.ndarray:
    """Smooth colour pattern on the plane (world x, y of the hit point) -> (N, 3) in [0, 1]."""
    x, y = points[:, 0], points[:, 1]
    r = 0.5 + 0.4 * np.sin(7.0 * x + 1.0) * np.cos(5.0 * y)
    g = 0.5 + 0.4 * np.cos(9.0 * x - 4.0 * y)
    b = 0.5 + 0.3 * np.sin(6.0 * y + 3.0 * x * x)
    return np.stack([r, g, b], axis=1)


def plane_hit(origin: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Intersection with the plane z = 3 + 0.3 x: n . X = 3 with n = (-0.3, 0, 1)."""
    normal = np.array([-0.3, 0.0, 1.0])
    depth = (3.0 - origin @ normal) / (directions @ normal)
    return origin + depth[:, None] * directions


def tiny_camera() -> pycolmap.Camera:
    return pycolmap.Camera(model="PINHOLE", width=TINY_WIDTH, height=TINY_HEIGHT,
                           params=[TINY_FOCAL, TINY_FOCAL, TINY_WIDTH / 2, TINY_HEIGHT / 2])


def tiny_poses(shift=(0.0, 0.0, 0.0), spacing: float = 0.12):
    poses = []
    for row in range(3):
        for col in range(3):
            centre = np.array([(col - 1) * spacing, (row - 1) * spacing, 0.0]) + np.asarray(shift)
            R = look_at_rotation(centre, TINY_LOOK_AT)
            poses.append((R, -R @ centre))
    return poses


def render_tiny_view(camera: pycolmap.Camera, R: np.ndarray, t: np.ndarray, supersample: int = 3) -> np.ndarray:
    """(H, W, 3) float image of the plane, box-filtered over supersample^2 samples per pixel."""
    width, height = int(camera.width), int(camera.height)
    fine_x = (np.arange(width * supersample) + 0.5) / supersample
    fine_y = (np.arange(height * supersample) + 0.5) / supersample
    gx, gy = np.meshgrid(fine_x, fine_y)
    pixels = np.stack([gx.ravel(), gy.ravel(), np.ones(gx.size)], axis=1)
    bearings = pixels @ np.linalg.inv(camera.calibration_matrix()).T
    colours = plane_texture(plane_hit(-R.T @ t, bearings @ R))
    colours = colours.reshape(height, supersample, width, supersample, 3).mean(axis=(1, 3))
    return np.clip(colours, 0, 1)


def make_tiny_scene(folder: Path, shift=(0.0, 0.0, 0.0), fmt: str = "binary") -> Path:
    folder = Path(folder)
    camera = tiny_camera()
    poses = tiny_poses(shift)
    names = [f"view_{i:02d}.png" for i in range(len(poses))]
    (folder / "images").mkdir(parents=True, exist_ok=True)
    for (R, t), name in zip(poses, names):
        rgb = render_tiny_view(camera, R, t)
        Image.fromarray(np.round(rgb * 255).astype(np.uint8)).save(folder / "images" / name)
    rng = np.random.default_rng(7)
    xy = rng.uniform(-0.8, 0.8, size=(60, 2))
    points = np.column_stack([xy, 3.0 + 0.3 * xy[:, 0]])
    write_colmap_model(folder / "sparse" / "0", camera, poses, names, points, fmt=fmt)
    return folder


@pytest.fixture(scope="session")
def extension_module(tmp_path_factory):
    """`load(name)`: neulf_blender's module `name` imported as the installed extension would be
    (the repository root as the package `neulf_ext`, whose modules import neulf_core relatively),
    without Blender: the modules that do not import bpy."""
    parent = tmp_path_factory.mktemp("pkg")
    (parent / "neulf_ext").symlink_to(Path(__file__).resolve().parents[1], target_is_directory=True)
    sys.path.insert(0, str(parent))
    try:
        yield lambda name: importlib.import_module(f"neulf_ext.neulf_blender.{name}")
    finally:
        sys.path.remove(str(parent))


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory) -> Path:
    """A 9-view synthetic COLMAP scene (read-only for the tests: copy it to change it)."""
    return make_tiny_scene(tmp_path_factory.mktemp("tiny_scene"))


@pytest.fixture(scope="session")
def tiny_scene_factory():
    return make_tiny_scene


@pytest.fixture(scope="session")
def benchmark_script():
    """Load a script of benchmarks/ as a module, with that folder on sys.path as the scripts
    import each other (seed_scatter imports stability)."""
    folder = Path(__file__).resolve().parents[1] / "benchmarks"
    if str(folder) not in sys.path:
        sys.path.insert(0, str(folder))

    def load(name: str):
        spec = importlib.util.spec_from_file_location(name, folder / f"{name}.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module

    return load


def assert_same_weights(a: Path, b: Path) -> None:
    """Two model folders' checkpoints hold the same step, weights and optimizer state, bit for bit."""
    import torch

    from neulf_core.checkpoint import load_checkpoint

    sa, sb = load_checkpoint(a), load_checkpoint(b)
    assert sa["progress"]["step"] == sb["progress"]["step"]
    assert sa["state_dict"].keys() == sb["state_dict"].keys()
    for key in sa["state_dict"]:
        assert torch.equal(sa["state_dict"][key], sb["state_dict"][key]), f"{key} differs"
    for group_a, group_b in zip(sa["optimizer"]["state"].values(), sb["optimizer"]["state"].values()):
        for key in group_a:
            assert torch.equal(torch.as_tensor(group_a[key]), torch.as_tensor(group_b[key])), f"optimizer {key} differs"


def losses_as_for_11_to_20_photos(monkeypatch, poses_off: bool) -> list:
    """The multi-view losses' rule for 11 to 20 photos on the tiny scene's 7 training views
    (the limit lowered to 3, the passes rule aside), the pose check's verdict forced to
    `poses_off`: returns a list that gets an item for every step trained with the losses."""
    import neulf_core.poses as poses_module
    import neulf_core.train as train_module
    import neulf_core.rules as rules_module

    monkeypatch.setattr(rules_module, "CONSISTENCY_ALWAYS_MAX_VIEWS", 3)
    monkeypatch.setattr(rules_module, "LOSSES_MIN_PASSES", 0.0)
    monkeypatch.setattr(poses_module, "poses_look_off", lambda degrees, second_look=False: poses_off)
    calls = []
    real = train_module.multiview_losses
    monkeypatch.setattr(train_module, "multiview_losses", lambda *a, **k: calls.append(1) or real(*a, **k))
    return calls


def png_header_only(width: int, height: int) -> bytes:
    """A PNG whose valid header claims width x height and whose pixels are all missing."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(b"\0" * 100)) + chunk(b"IEND", b"")

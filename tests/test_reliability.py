"""Reliability (issue #4): bad input and faults end in one clear line that says what to do,
never a traceback, and never lost work.

Each test drives the real command line (`neulf_core.cli.main` in-process, or
`python -m neulf_core` in a subprocess where a process must die or be measured) on the tiny
synthetic scene from conftest.py, and records what the user saw with
`record_property("message", ...)` -- measured numbers go in other properties.
scripts/reliability_report.py runs these tests (and the older ones that cover the same
cases) and writes docs/RELIABILITY.md from the junit XML.
"""

from __future__ import annotations

import ast
import json
import os
import platform
import re
import shutil
import signal
import socket
import struct
import subprocess
import sys
import time
import zipfile
import zlib
from pathlib import Path

import numpy as np
import pycolmap
import pytest
import torch
from PIL import Image

from conftest import (TINY_HEIGHT, TINY_WIDTH, look_at_rotation, png_header_only, tiny_camera, tiny_poses,
                      write_colmap_model)
from neulf_core.checkpoint import CHECKPOINT_NAME, METADATA_NAME, load_checkpoint
from neulf_core.cli import main

REPO = Path(__file__).resolve().parents[1]
VIEW_NAMES = [f"view_{i:02d}.png" for i in range(9)]
TRAIN_VIEWS = VIEW_NAMES[1:8]  # --holdout-every 8 holds out view_00 and view_08
QUICK_TRAIN = ["--steps", "2", "--batch-size", "256", "--validate-seconds", "1e9"]


# ----------------------------------------------------------------------------- running the CLI


def run_cli(argv, capfd) -> tuple[int, str, str]:
    capfd.readouterr()
    code = main([str(a) for a in argv])
    captured = capfd.readouterr()
    return code, captured.out, captured.err


def expect_error(argv, capfd, record_property, *expected) -> str:
    """Run the CLI, record what it printed, and check it is one `error:` line naming `expected`."""
    code, out, err = run_cli(argv, capfd)
    record_property("message", err.strip() or f"(nothing on stderr; exit {code})")
    assert "Traceback" not in out + err
    lines = err.splitlines()
    assert code == 2, err
    assert len(lines) == 1 and lines[0].startswith("error: "), f"stderr should be one error line: {err!r}"
    for text in expected:
        assert text in lines[0]
    return lines[0]


def subprocess_env() -> dict:
    # One thread: the test machines are shared, and timings should not depend on the core count.
    return dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""), OMP_NUM_THREADS="1")


def cli_process(argv, cwd: Path, **kwargs) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "neulf_core", *[str(a) for a in argv]], cwd=cwd,
                            env=subprocess_env(), text=True, **kwargs)


# ----------------------------------------------------------------------------- scenes to break


def copy_scene(tiny_scene: Path, destination: Path) -> Path:
    shutil.copytree(tiny_scene, destination)
    return destination


def plane_points(count: int = 60) -> np.ndarray:
    """3D points on the tiny scene's plane (z = 3 + 0.3 x), as conftest writes them."""
    xy = np.random.default_rng(7).uniform(-0.8, 0.8, size=(count, 2))
    return np.column_stack([xy, 3.0 + 0.3 * xy[:, 0]])


def rewrite_model(scene: Path, names: list[str], poses, points) -> None:
    shutil.rmtree(scene / "sparse")
    write_colmap_model(scene / "sparse" / "0", tiny_camera(), poses, names, points)


def ring_scene(folder: Path) -> Path:
    """Twelve cameras on a circle around an object, all looking at its centre."""
    names, poses = [], []
    for i, angle in enumerate(np.radians(np.arange(0, 360, 30))):
        centre = 3.0 * np.array([np.sin(angle), 0.0, -np.cos(angle)])
        R = look_at_rotation(centre, np.zeros(3))
        names.append(f"ring_{i:02d}.png")
        poses.append((R, -R @ centre))
    (folder / "images").mkdir(parents=True)
    for name in names:
        Image.fromarray(np.full((36, 48, 3), 120, np.uint8)).save(folder / "images" / name)
    points = np.random.default_rng(0).uniform(-0.5, 0.5, (50, 3))
    write_colmap_model(folder / "sparse" / "0", tiny_camera(), poses, names, points)
    return folder


def as_text(model: Path, keep_frames: bool) -> None:
    """The model rewritten in COLMAP's text format: 4.x's (with rigs.txt and frames.txt), or the
    legacy one of cameras, images and points alone."""
    pycolmap.Reconstruction(str(model)).write_text(str(model))
    for path in model.glob("*.bin"):
        path.unlink()
    if not keep_frames:
        for name in ("rigs.txt", "frames.txt"):
            (model / name).unlink()


def break_scene(scene: Path, how: str) -> None:
    model = scene / "sparse" / "0"
    if how == "no model":
        shutil.rmtree(scene / "sparse")
    elif how == "random cameras.bin":
        (model / "cameras.bin").write_bytes(np.random.default_rng(0).bytes(300))
    elif how.startswith("truncated"):
        path = model / how.split()[1]
        path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    elif how == "all images missing":
        for path in (scene / "images").iterdir():
            path.unlink()
    elif how == "some images missing":
        for name in ("view_03.png", "view_05.png"):
            (scene / "images" / name).unlink()
    elif how == "unreadable image":
        (scene / "images" / "view_04.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"not really")
    elif how == "absurd data count in frames.bin":
        patch_file(model / "frames.bin", frame_offset(model, 0) + 64, struct.pack("<I", 2 ** 31 - 1))  # its data count
    elif how == "zero rotation in frames.bin":
        patch_file(model / "frames.bin", frame_offset(model, 0) + 8, struct.pack("<4d", 0, 0, 0, 0))  # its quaternion
    elif how.startswith("zero rotation in") and how.endswith(".txt"):
        as_text(model, keep_frames=how.endswith("frames.txt"))
        name, column = ("frames.txt", 2) if how.endswith("frames.txt") else ("images.txt", 1)
        lines = (model / name).read_text().splitlines()
        first = next(i for i, line in enumerate(lines) if line and not line.startswith("#"))
        fields = lines[first].split()
        fields[column:column + 4] = ["0", "0", "0", "0"]  # (pycolmap reads it as the identity rotation)
        lines[first] = " ".join(fields)
        (model / name).write_text("\n".join(lines) + "\n")
    elif how == "two images of one name":
        path = model / "images.bin"
        path.write_bytes(path.read_bytes().replace(b"view_01.png\0", b"view_00.png\0"))
    elif how == "camera far off":
        patch_file(model / "frames.bin", frame_offset(model, 3) + 8 + 32, struct.pack("<d", 1e300))  # translation x
    elif how.startswith("camera width"):
        patch_file(model / "cameras.bin", 8 + 4 + 4, struct.pack("<q", int(how.split()[-1])))
    elif how == "photo header claiming 1200 MP":
        (scene / "images" / "view_03.png").write_bytes(png_header_only(40000, 30000))


def patch_file(path: Path, offset: int, raw: bytes) -> None:
    data = bytearray(path.read_bytes())
    data[offset:offset + len(raw)] = raw
    path.write_bytes(bytes(data))


def frame_offset(model: Path, index: int) -> int:
    """Where frames.bin's frame `index` (from 0) starts: frame id, rig id, 7 pose doubles, then
    a count of 16-byte data ids (COLMAP 4.x's layout)."""
    data, at = (model / "frames.bin").read_bytes(), 8
    for _ in range(index):
        at += 8 + 56 + 4 + 16 * struct.unpack_from("<I", data, at + 64)[0]
    return at


SCENE_PROBLEMS = {
    # how the folder is broken: text the one-line message must contain
    "no model": ("no camera model", "reconstruct"),
    "random cameras.bin": ("cannot read the COLMAP model", "export the model again"),
    # A truncated cameras.bin used to load with zero focal lengths, images.bin to hang, and
    # points3D.bin to allocate 16 GB for four minutes before failing (pycolmap reads past the end).
    "truncated cameras.bin": ("cameras.bin is truncated or corrupted", "export the model again"),
    "truncated images.bin": ("images.bin is truncated or corrupted", "export the model again"),
    "truncated points3D.bin": ("points3D.bin is truncated or corrupted", "export the model again"),
    "all images missing": ("9 of 9 images", "--images"),
    "some images missing": ("2 of 9 images", "view_03.png", "--images"),
    "unreadable image": ("cannot read image", "view_04.png", "Replace or remove"),
    # COLMAP 4.x's rigs.bin and frames.bin: a truncation or an absurd count had pycolmap spin
    # for one or two minutes before failing; a zero quaternion became the identity rotation.
    "truncated frames.bin": ("frames.bin is truncated or corrupted", "export the model again"),
    "truncated rigs.bin": ("rigs.bin is truncated or corrupted", "export the model again"),
    "absurd data count in frames.bin": ("frames.bin is truncated or corrupted", "export the model again"),
    "zero rotation in frames.bin": ("frames.bin gives frame 1 a rotation quaternion of length 0", "export the model again"),
    "zero rotation in images.txt": ("images.txt gives image 1 a rotation quaternion of length 0", "export the model again"),
    "zero rotation in frames.txt": ("frames.txt gives frame 1 a rotation quaternion of length 0", "export the model again"),
    # Two views had read one photo with two poses, without a word.
    "two images of one name": ("names two images view_00.png (ids 1 and 2)", "export the model again"),
    # Trained on NaN rays and wrote NaN scores (a held-out view), or blamed the 3D points (a training view).
    "camera far off": ("view_03.png's camera", "absurdly far from the other cameras", "export the model again"),
    # Were called another aspect ratio: "the model's camera is 18446744073709551568x36".
    "camera width -48": ("damaged camera 1", "-48x36", "export the model again"),
    "camera width 200000": ("damaged camera 1", "200000x36", "export the model again"),
    # Pillow's DecompressionBombError escaped as a traceback.
    "photo header claiming 1200 MP": ("view_03.png claims 40000x30000 pixels (1200 MP)", "downscale it"),
}


@pytest.mark.parametrize("how", list(SCENE_PROBLEMS))
def test_broken_scene_folder(how, tiny_scene, tmp_path, capfd, record_property):
    scene = copy_scene(tiny_scene, tmp_path / "scene")
    break_scene(scene, how)
    expect_error(["train", scene, "--out", tmp_path / "model", *QUICK_TRAIN], capfd, record_property, *SCENE_PROBLEMS[how])
    assert not (tmp_path / "model" / CHECKPOINT_NAME).exists()


def test_images_option_naming_a_file(tiny_scene, tmp_path, capfd, record_property):
    """--images given a photo, not its folder, had been told the folder 'does not exist'."""
    photo = tiny_scene / "images" / "view_00.png"
    expect_error(["train", tiny_scene, "--images", photo, "--out", tmp_path / "model", *QUICK_TRAIN], capfd,
                 record_property, "view_00.png is a file, not a folder", "--images the folder that holds the photos")


@pytest.mark.skipif(sys.platform == "win32", reason="chmod 000 does not make a file unreadable on Windows")
@pytest.mark.parametrize("name", ["frames.bin", "images.bin"])
def test_unreadable_model_file_is_a_permission_problem(name, tiny_scene, tmp_path, record_property):
    """A model file the user may not read had been called truncated or corrupted ('export the
    model again'), which would not help: it is a permission problem."""
    scene = copy_scene(tiny_scene, tmp_path / "scene")
    (scene / "sparse" / "0" / name).chmod(0)
    run_as = []
    if os.geteuid() == 0:  # root reads anything: run without the capabilities that let it
        if shutil.which("setpriv") is None:
            pytest.skip("running as root without setpriv: cannot make a file unreadable")
        run_as = ["setpriv", "--bounding-set=-dac_override,-dac_read_search"]
    argv = [sys.executable, "-m", "neulf_core", "train", scene, "--out", tmp_path / "model", *QUICK_TRAIN]
    proc = subprocess.run(run_as + [str(a) for a in argv], cwd=tmp_path, env=subprocess_env(), capture_output=True,
                          text=True, timeout=300)
    record_property("message", proc.stderr.strip())
    lines = proc.stderr.splitlines()
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert len(lines) == 1 and lines[0].startswith("error: cannot read "), proc.stderr
    assert f"{name}: permission denied" in lines[0] and "chmod u+r" in lines[0] and "export" not in lines[0]


# ----------------------------------------------------------------------------- photos in odd formats


def write_png16(path: Path, rgb16: np.ndarray) -> None:
    """A 16-bit RGB PNG (Pillow cannot write one), as raw PNG chunks."""
    height, width, _ = rgb16.shape

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    rows = b"".join(b"\x00" + row.astype(">u2").tobytes() for row in rgb16)
    header = struct.pack(">IIBBBBB", width, height, 16, 2, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(rows)) + chunk(b"IEND", b""))


def as_grayscale(path: Path, rgb: np.ndarray) -> np.ndarray:
    Image.fromarray(rgb).convert("L").save(path)
    gray = np.asarray(Image.open(path))
    return np.repeat(gray[..., None], 3, axis=2)


def as_rgba(path: Path, rgb: np.ndarray) -> np.ndarray:
    alpha = np.full(rgb.shape[:2], 255, np.uint8)
    alpha[:6, :6] = 0  # a transparent corner: no colour the camera saw, composited on black
    Image.fromarray(np.dstack([rgb, alpha])).save(path)
    expected = rgb.copy()
    expected[:6, :6] = 0
    return expected


def as_16_bit_rgb(path: Path, rgb: np.ndarray) -> np.ndarray:
    write_png16(path, rgb.astype(np.uint16) * 257)
    return rgb


def as_16_bit_gray(path: Path, rgb: np.ndarray) -> np.ndarray:
    gray = np.asarray(Image.fromarray(rgb).convert("L"))
    Image.fromarray(gray.astype(np.uint16) * 257).save(path)
    return np.repeat(gray[..., None], 3, axis=2)


def as_exif_rotated_jpeg(path: Path, rgb: np.ndarray) -> np.ndarray:
    """Stored portrait-for-landscape like a phone: turned a quarter, with EXIF orientation 6
    ("rotate 90 degrees clockwise to display"), so it displays as the camera saw it."""
    image = Image.fromarray(np.ascontiguousarray(np.rot90(rgb)))
    exif = image.getexif()
    exif[0x0112] = 6
    path.unlink()
    image.save(path.with_suffix(".jpg"), exif=exif.tobytes(), quality=98)
    return rgb


def as_half_size(path: Path, rgb: np.ndarray) -> np.ndarray:
    Image.fromarray(rgb).resize((24, 18), Image.BOX).save(path)
    return np.asarray(Image.open(path).convert("RGB"))


PHOTO_FORMATS = {
    # writer, expected trained size, tolerance of the mean colour (JPEG is lossy)
    "grayscale": (as_grayscale, (48, 36), 1e-4),
    "RGBA": (as_rgba, (48, 36), 1e-4),
    "16-bit RGB": (as_16_bit_rgb, (48, 36), 1e-4),
    "16-bit grayscale": (as_16_bit_gray, (48, 36), 1e-4),
    "EXIF-rotated JPEG": (as_exif_rotated_jpeg, (48, 36), 3e-3),
    "other size than the model": (as_half_size, (24, 18), 1e-4),
}


@pytest.mark.parametrize("kind", list(PHOTO_FORMATS))
def test_photos_in_other_formats_train(kind, tiny_scene, tmp_path, capfd, record_property):
    """The photos are rewritten in another format; training reads them as the camera saw
    them: the model's mean colour is the mean of the expected decoded pixels."""
    write, size, tolerance = PHOTO_FORMATS[kind]
    scene = copy_scene(tiny_scene, tmp_path / "scene")
    expected = {}
    for name in VIEW_NAMES:
        path = scene / "images" / name
        expected[name] = write(path, np.asarray(Image.open(path).convert("RGB")))
    code, out, err = run_cli(["train", scene, "--out", tmp_path / "model", "--preset", "planes", *QUICK_TRAIN], capfd)
    notes = [line for line in err.splitlines() if line.startswith(("note:", "warning:", "error:"))]
    record_property("message", " / ".join(notes) or f"trained (exit {code}); no message needed")
    assert code == 0 and "Traceback" not in err, err
    meta = json.loads((tmp_path / "model" / METADATA_NAME).read_text())
    assert (meta["rig"]["width"], meta["rig"]["height"]) == size
    pixels = np.concatenate([expected[name].reshape(-1, 3) for name in TRAIN_VIEWS]).astype(np.float64) / 255.0
    np.testing.assert_allclose(meta["scene"]["mean_colour"], pixels.mean(axis=0), atol=tolerance)
    if kind == "other size than the model":
        assert any("48x36" in note and "24x18" in note for note in notes), err


def test_photos_of_another_aspect_ratio(tiny_scene, tmp_path, capfd, record_property):
    scene = copy_scene(tiny_scene, tmp_path / "scene")
    for name in VIEW_NAMES:  # cropped square: not a resized copy of what the model calibrated
        path = scene / "images" / name
        Image.open(path).crop((6, 0, 42, 36)).save(path)
    expect_error(["train", scene, "--out", tmp_path / "model", *QUICK_TRAIN], capfd, record_property,
                 "36x36", "48x36", "aspect ratio")


# ----------------------------------------------------------------------------- captures a light field cannot use


def test_empty_point_cloud(tiny_scene, tmp_path, capfd, record_property):
    """No 3D points: the depth range is unknown.  The message names the options that supply
    it, and with them training works."""
    scene = copy_scene(tiny_scene, tmp_path / "scene")
    rewrite_model(scene, VIEW_NAMES, tiny_poses(), points=None)
    expect_error(["train", scene, "--out", tmp_path / "model", *QUICK_TRAIN], capfd, record_property,
                 "no usable 3D points", "--st-depth", "--near", "--far")
    assert not (tmp_path / "model").exists()
    code, _, err = run_cli(["train", scene, "--out", tmp_path / "model", "--st-depth", "3", "--near", "2.5", "--far", "3.5",
                            *QUICK_TRAIN], capfd)
    assert code == 0, err


def test_single_image(tiny_scene, tmp_path, capfd, record_property):
    scene = copy_scene(tiny_scene, tmp_path / "scene")
    rewrite_model(scene, ["view_04.png"], [tiny_poses()[4]], plane_points())
    message = expect_error(["train", scene, "--out", tmp_path / "model", *QUICK_TRAIN], capfd, record_property,
                           "only 1 registered photo", "add more")
    assert "hold out fewer" not in message  # holding out fewer cannot help with one photo
    code, _, err = run_cli(["train", scene, "--out", tmp_path / "model", "--holdout-every", "0", *QUICK_TRAIN], capfd)
    assert code == 2 and "only 1 registered photo" in err


def test_ring_capture_is_not_forward_facing(tmp_path, capfd, record_property):
    scene = ring_scene(tmp_path / "ring")
    expect_error(["train", scene, "--out", tmp_path / "model", *QUICK_TRAIN], capfd, record_property,
                 "not forward-facing", "360-degree")
    assert not (tmp_path / "model").exists()


# ----------------------------------------------------------------------------- a trained model to render and damage


@pytest.fixture(scope="module")
def model(tiny_scene, tmp_path_factory) -> Path:
    """The default preset trained for 3 small steps through the CLI (read-only: copy it)."""
    out = tmp_path_factory.mktemp("reliability") / "model"
    assert main(["train", str(tiny_scene), "--out", str(out), "--steps", "3", "--batch-size", "256",
                 "--progress", "json", "--validate-seconds", "1e9"]) == 0
    return out


def camera_json(path: Path, cameras: list[dict]) -> Path:
    path.write_text(json.dumps({"cameras": cameras}))
    return path


def pinhole(name: str, centre, target, width: int = 32, height: int = 24) -> dict:
    R = look_at_rotation(np.asarray(centre, float), np.asarray(target, float))
    return {"name": name, "K": [[40.0, 0, width / 2], [0, 40.0, height / 2], [0, 0, 1]], "width": width,
            "height": height, "R": R.tolist(), "t": (-R @ np.asarray(centre, float)).tolist()}


def test_render_camera_behind_the_uv_plane(model, tmp_path, capfd, record_property):
    """1.5 units behind the camera rig (the uv plane), looking at the scene: the rays still
    cross the slab, so it renders, and says how to get reliable results."""
    cams = camera_json(tmp_path / "c.json", [pinhole("behind", [0, 0, -1.5], [0, 0, 3])])
    code, out, err = run_cli(["render", model, "--cameras", cams, "--out", tmp_path / "out"], capfd)
    record_property("message", err.strip())
    assert code == 0 and "Traceback" not in err, err
    assert Image.open(tmp_path / "out" / "behind.png").size == (32, 24)
    lines = err.splitlines()
    assert lines and all(line.startswith("warning (behind): ") for line in lines), err
    assert any("move the camera closer to the capture positions" in line for line in lines)


def test_render_camera_looking_away(model, tmp_path, capfd, record_property):
    """A camera facing away from the scene sees only the background colour: it is reported,
    and the other cameras of the same file are still rendered."""
    cams = camera_json(tmp_path / "c.json", [pinhole("away", [0, 0, 0], [0, 0, -3])])
    expect_error(["render", model, "--cameras", cams, "--out", tmp_path / "out"], capfd, record_property,
                 "away", "look away from the captured scene", "Turn them")
    assert not (tmp_path / "out" / "away.png").exists()
    both = camera_json(tmp_path / "both.json", [pinhole("away", [0, 0, 0], [0, 0, -3]), pinhole("ok", [0, 0, 0], [0, 0, 3])])
    code, _, err = run_cli(["render", model, "--cameras", both, "--out", tmp_path / "out2"], capfd)
    assert code == 2 and "1 image(s) are in" in err.splitlines()[-1]
    assert (tmp_path / "out2" / "ok.png").is_file()


@pytest.mark.parametrize("size", [(0, 24), (32, 0)], ids=["zero width", "zero height"])
def test_render_camera_with_zero_size_image(size, model, tmp_path, capfd, record_property):
    cams = camera_json(tmp_path / "c.json", [pinhole("empty", [0, 0, 0], [0, 0, 3], *size)])
    expect_error(["render", model, "--cameras", cams, "--out", tmp_path / "out"], capfd, record_property,
                 f"{size[0]}x{size[1]}", "at least 1 pixel")


# ----------------------------------------------------------------------------- damaged checkpoints


def model_files(model_dir: Path) -> list[Path]:
    """Every weights file (checkpoint.pt, and model.pt where the trainer writes one)."""
    return sorted(model_dir.glob("*.pt"))


def flip_bytes_in_largest_tensor(path: Path) -> None:
    """Overwrite 64 bytes inside the largest tensor's data: the archive still opens."""
    with zipfile.ZipFile(path) as archive:
        member = max(archive.infolist(), key=lambda info: info.file_size)
        offset = member.header_offset + 30 + len(member.filename.encode()) + len(member.extra)
    data = bytearray(path.read_bytes())
    start = offset + member.file_size // 2
    data[start:start + 64] = bytes(255 - b for b in data[start:start + 64])
    path.write_bytes(bytes(data))


def damage(path: Path, how: str) -> None:
    if how == "truncated":
        path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    elif how == "empty":
        path.write_bytes(b"")
    elif how == "random bytes":
        path.write_bytes(np.random.default_rng(0).bytes(path.stat().st_size))
    elif how == "bytes flipped inside":
        flip_bytes_in_largest_tensor(path)
    elif how == "another version":
        payload = torch.load(path, map_location="cpu", weights_only=False)
        torch.save({**payload, "version": 99}, path)
    elif how == "not a NeuLF checkpoint":
        torch.save({"weights": [1, 2, 3]}, path)


CHECKPOINT_DAMAGE = {
    "truncated": "truncated or corrupted",
    "empty": "truncated or corrupted",
    "random bytes": "truncated or corrupted",
    "bytes flipped inside": "truncated or corrupted",
    "another version": "another version",
    "not a NeuLF checkpoint": "not a NeuLF checkpoint",
}
@pytest.mark.parametrize("how", list(CHECKPOINT_DAMAGE))
def test_damaged_checkpoint(how, model, tiny_scene, tmp_path, capfd, record_property):
    """Rendering and resuming both refuse a damaged model in one line, and leave the files as
    they were (the user may still restore or inspect them)."""
    damaged = shutil.copytree(model, tmp_path / "model")
    for path in model_files(damaged):
        damage(path, how)
    before = {path.name: path.read_bytes() for path in model_files(damaged)}
    cams = camera_json(tmp_path / "c.json", [pinhole("novel", [0, 0, 0], [0, 0, 3])])
    expect_error(["render", damaged, "--cameras", cams, "--out", tmp_path / "out"], capfd, record_property,
                 CHECKPOINT_DAMAGE[how])
    expect_error(["train", tiny_scene, "--out", damaged, "--resume", "--steps", "6"], capfd, record_property,
                 CHECKPOINT_DAMAGE[how])
    assert {path.name: path.read_bytes() for path in model_files(damaged)} == before


def test_damaged_checkpoint_message_names_a_way_out(model, tiny_scene, tmp_path, capfd, record_property):
    damaged = shutil.copytree(model, tmp_path / "model")
    for path in model_files(damaged):
        damage(path, "truncated")
    resume = expect_error(["train", tiny_scene, "--out", damaged, "--resume", "--steps", "6"], capfd, record_property)
    again = expect_error(["train", tiny_scene, "--out", damaged, "--steps", "6"], capfd, record_property)
    assert "--resume" in again  # plain `train` sends the user to --resume ...
    assert "--out" in resume or "delete" in resume  # ... so --resume must say how to start afresh


def test_checkpoint_of_another_scene(model, tiny_scene_factory, tmp_path, capfd, record_property):
    other = tiny_scene_factory(tmp_path / "other", shift=(0.05, 0.0, 0.0))
    expect_error(["render", model, "--scene", other, "--views", "all", "--out", tmp_path / "out"], capfd, record_property,
                 "another reconstruction")
    resumed = shutil.copytree(model, tmp_path / "model")
    expect_error(["train", other, "--out", resumed, "--resume", "--steps", "6"], capfd, record_property,
                 "another reconstruction", "train a new model")


def test_photos_replaced_since_training_are_said(model, tiny_scene, tmp_path, capfd, record_property):
    """Photos replaced by others of the same name and size (here: mirrored) had been scored and
    trained on without a word (eval 26.6 -> 10.9 dB on an auditor's scene): eval and resume say
    which photos are not the files the model trained on."""
    scene = Path(shutil.copytree(tiny_scene, tmp_path / "scene"))
    model_copy = Path(shutil.copytree(model, tmp_path / "model"))
    held_out = json.loads((model_copy / "model.json").read_text())["scene"]["held_out"]
    photo = scene / "images" / held_out[0]
    Image.open(photo).transpose(Image.Transpose.FLIP_LEFT_RIGHT).save(photo)
    code, _, err = run_cli(["eval", model_copy, "--scene", scene, "--out", tmp_path / "eval"], capfd)
    assert code == 0
    warnings = json.loads((tmp_path / "eval" / "eval.json").read_text())["warnings"]
    assert any(f"1 photo(s) ({held_out[0]}) are not the files the model trained on" in w for w in warnings), warnings
    assert "not the files the model trained on" in err
    trained_on = scene / "images" / json.loads((model_copy / "model.json").read_text())["scene"]["train"][0]
    Image.open(trained_on).transpose(Image.Transpose.FLIP_LEFT_RIGHT).save(trained_on)
    code, _, err = run_cli(["train", scene, "--out", model_copy, "--resume", "--steps", "4", "--batch-size", "256",
                            "--validate-seconds", "1e9"], capfd)
    record_property("message", err.strip().splitlines()[0] if err.strip() else "")
    assert code == 0 and "photo(s)" in err and "training goes on with them" in err, err
    assert "photo(s)" not in run_cli(["eval", model, "--scene", tiny_scene, "--out", tmp_path / "same"], capfd)[2]


def test_a_file_that_is_no_model_is_not_called_a_damaged_checkpoint(tiny_scene, tmp_path, capfd, record_property):
    """A photo or poses_bounds.npy given as the model: said to be no model (it had been called a
    corrupted checkpoint, with the advice to delete the user's own file)."""
    photo = next((Path(tiny_scene) / "images").iterdir())
    poses = tmp_path / "poses_bounds.npy"
    np.save(poses, np.zeros((3, 17)))
    for given in (photo, poses):
        message = expect_error(["render", given, "--scene", tiny_scene, "--views", "all", "--out", tmp_path / "out"],
                               capfd, record_property, "is not a NeuLF model", "train's --out")
        assert "delete" not in message and "corrupted" not in message
    assert photo.is_file() and poses.is_file()


def test_a_reconstruction_changed_in_place_is_said_so(model, tiny_scene, tmp_path, capfd, record_property):
    """COLMAP run again in the scene folder the model trained on (every camera 1 mm over): the
    refusal says the poses there changed (it had said "another reconstruction" and named the
    very folder given)."""
    import pycolmap

    scene = Path(shutil.copytree(tiny_scene, tmp_path / "scene"))
    model_copy = Path(shutil.copytree(model, tmp_path / "model"))
    meta = json.loads((model_copy / "model.json").read_text())
    for name in ("checkpoint.pt", "model.pt"):  # (the model as if trained on the copy: its recorded folder)
        payload = torch.load(model_copy / name, weights_only=False)
        payload["scene"]["root"] = str(scene)
        torch.save(payload, model_copy / name)
    meta["scene"]["root"] = str(scene)
    (model_copy / "model.json").write_text(json.dumps(meta))
    recon = pycolmap.Reconstruction(str(scene / "sparse" / "0"))
    for image in recon.images.values():
        pose = image.cam_from_world()
        image.frame.rig_from_world = pycolmap.Rigid3d(pose.rotation, pose.translation + np.array([0.001, 0.0, 0.0]))
    recon.write(str(scene / "sparse" / "0"))
    for command in (["eval", model_copy, "--scene", scene], ["train", scene, "--out", model_copy, "--resume", "--steps", "6"]):
        message = expect_error(command, capfd, record_property, "camera poses in", "changed since the model trained")
        assert "another reconstruction" not in message


# ----------------------------------------------------------------------------- processes that die


KILL_INTERVAL_S = 0.5  # --checkpoint-seconds for the killed run


def read_events(process: subprocess.Popen, until) -> list[dict]:
    """JSON progress events from the process's stdout until `until(events)` is true."""
    events = []
    for line in process.stdout:
        events.append(json.loads(line))
        if until(events):
            return events
    raise AssertionError(f"training ended before the test could act: {events[-3:]}")


def checkpoints_then_a_step(count: int):
    def until(events):
        saved = [i for i, e in enumerate(events) if e["event"] == "checkpoint"]
        return len(saved) >= count and any(e["event"] == "step" for e in events[saved[count - 1] + 1:])
    return until


def test_sigkill_during_training_loses_at_most_one_checkpoint_interval(tiny_scene, tmp_path, capfd, record_property):
    model = tmp_path / "model"
    process = cli_process(["train", tiny_scene, "--out", model, "--steps", "1000000", "--members", "1", "--max-passes", "0", "--batch-size", "256",
                           "--checkpoint-seconds", KILL_INTERVAL_S, "--validate-seconds", "1e9", "--progress", "json"],
                          tmp_path, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
    try:
        events = read_events(process, checkpoints_then_a_step(2))
        last = next(e for e in reversed(events) if e["event"] == "step")
        read_at = time.monotonic()
        process.send_signal(signal.SIGKILL)
        # Training time at the kill: the last reported step, plus what ran after it was read.
        elapsed_at_kill = last["elapsed"] + (time.monotonic() - read_at)
        process.wait(timeout=60)
    finally:
        if process.poll() is None:
            process.kill()
    assert process.returncode == -signal.SIGKILL
    saved = load_checkpoint(model)["progress"]  # loads: no half-written file
    reported = max(e["step"] for e in events if e["event"] == "checkpoint")
    assert saved["step"] >= reported
    lost_seconds = elapsed_at_kill - saved["elapsed"]
    record_property("sigkill_checkpoint_interval_s", KILL_INTERVAL_S)
    record_property("sigkill_lost_training_s", round(lost_seconds, 3))
    record_property("sigkill_lost_steps_at_least", last["step"] - saved["step"])
    # One interval, plus the step in flight and the checkpoint write (slow on a loaded machine).
    assert lost_seconds <= KILL_INTERVAL_S + 1.0, (elapsed_at_kill, saved)

    code, out, err = run_cli(["train", tiny_scene, "--out", model, "--resume", "--steps", saved["step"] + 5,
                              "--progress", "json"], capfd)
    assert code == 0, err
    resumed = [json.loads(line) for line in out.splitlines()]
    steps = [e["step"] for e in resumed if e["event"] in ("step", "validate")]
    assert steps[0] == saved["step"] + 1 and resumed[-1]["event"] == "finished"
    assert resumed[-1]["step"] == saved["step"] + 5
    record_property("message", f"killed at step >= {last['step']}; `train --resume` continued from the checkpoint "
                               f"at step {saved['step']} ({lost_seconds:.2f} s of training lost, interval "
                               f"{KILL_INTERVAL_S} s)")


def test_reader_of_progress_goes_away(tiny_scene, tmp_path, capfd, record_property):
    """Blender runs training as `train --progress json` with its stdout on a pipe; when
    Blender quits or crashes, the pipe closes.  Training must save at once (not at the next
    timed checkpoint, which may be a minute away, and not die on the next write), so that
    reopening finds the model and its progress."""
    model = tmp_path / "model"
    process = cli_process(["train", tiny_scene, "--out", model, "--steps", "1000000", "--members", "1", "--max-passes", "0", "--batch-size", "256",
                           "--checkpoint-seconds", "1e9", "--validate-seconds", "1e9", "--progress", "json"],
                          tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        events = read_events(process, lambda events: sum(e["event"] == "step" for e in events) >= 3)
        process.stdout.close()  # the reader (Blender) is gone
        process.stderr.close()
        process.wait(timeout=120)
    finally:
        if process.poll() is None:
            process.kill()
    assert (model / CHECKPOINT_NAME).is_file(), "training died without saving: the run was lost"
    saved = load_checkpoint(model)["progress"]
    last_seen = max(e["step"] for e in events if e["event"] == "step")
    assert saved["step"] >= last_seen and saved["status"] == "cancelled"
    code, out, err = run_cli(["train", tiny_scene, "--out", model, "--resume", "--steps", saved["step"] + 3,
                              "--progress", "json"], capfd)
    assert code == 0, err
    assert [json.loads(line) for line in out.splitlines()][-1]["step"] == saved["step"] + 3
    record_property("message", f"reader gone after step {last_seen}: checkpoint saved at step {saved['step']} "
                               f"(exit {process.returncode}); `train --resume` continued from it")


# ----------------------------------------------------------------------------- bounded memory


MEMORY_PROBE = """
import json, os, resource, sys
from neulf_core.cli import main
from neulf_core.render import LightField
import numpy as np

def status_kib(field):
    with open("/proc/self/status") as status:
        return next(int(line.split()[1]) for line in status if line.startswith(field + ":"))

def peak_bytes():
    # VmHWM: this process's own peak (ru_maxrss on Linux carries the parent's peak across exec).
    if os.path.exists("/proc/self/status"):
        return status_kib("VmHWM") * 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * (1 if sys.platform == "darwin" else 1024)

mode, model, width, height, out = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), sys.argv[5]
K = [[0.9 * width, 0, width / 2], [0, 0.9 * width, height / 2], [0, 0, 1]]
LightField.load(model, "cpu")  # imports and one model load: the baseline
if os.path.exists("/proc/self/clear_refs"):
    with open("/proc/self/clear_refs", "w") as handle:
        handle.write("5")  # reset the peak to the current size
base = peak_bytes()
if mode == "cli":  # the user's path: render and write the PNG
    cam = {"name": "frame", "K": K, "width": width, "height": height, "R": np.eye(3).tolist(), "t": [0, 0, 0]}
    open(out + ".json", "w").write(json.dumps([cam]))
    assert main(["render", model, "--cameras", out + ".json", "--out", out]) == 0
else:  # one chunk holding every ray: what rendering would cost without chunking
    LightField.load(model, "cpu").render(np.array(K), width, height, np.eye(3), np.zeros(3), depth=False,
                                         chunk=width * height)
print(json.dumps({"base": base, "peak": peak_bytes()}))
"""
SMALL_FRAME, LARGE_FRAME, UNCHUNKED_FRAME = (400, 300), (4000, 3000), (800, 600)
# What a frame must hold whatever the chunking: the float32 RGB render (12 B) and its
# validity mask (1 B), the 8-bit copy written to PNG (3 B) and Pillow's 4-byte RGBX copy.
FRAME_BYTES_PER_PIXEL = 20
ALLOCATOR_SLACK = 1.3  # heap fragmentation and page granularity; missing chunking costs 50x more
MIB = 1 << 20


def memory_probe(mode: str, model: Path, size, out: Path) -> dict:
    run = subprocess.run([sys.executable, "-c", MEMORY_PROBE, mode, str(model), str(size[0]), str(size[1]), str(out)],
                         cwd=out.parent, env=subprocess_env(), capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-3000:]
    return json.loads(run.stdout.splitlines()[-1])


@pytest.mark.slow  # two renders of 12 Mpx on one thread: 15-60 s on a shared machine
def test_large_render_has_bounded_peak_memory(model, tmp_path, record_property):
    """A 4000x3000 frame (12 Mpx) from the CLI: beyond the frame's own buffers, peak memory
    grows no more than for a 400x300 one.  Without chunking, every ray's intermediate values
    would be held at once."""
    started = time.monotonic()
    small = memory_probe("cli", model, SMALL_FRAME, tmp_path / "small")
    large = memory_probe("cli", model, LARGE_FRAME, tmp_path / "large")
    large_seconds = time.monotonic() - started
    unchunked = memory_probe("unchunked", model, UNCHUNKED_FRAME, tmp_path / "unchunked")
    pixels = lambda size: size[0] * size[1]  # noqa: E731
    per_pixel = (large["peak"] - small["peak"]) / (pixels(LARGE_FRAME) - pixels(SMALL_FRAME))
    unchunked_per_pixel = (unchunked["peak"] - unchunked["base"]) / pixels(UNCHUNKED_FRAME)
    measured = {
        "render_4000x3000_peak_MiB": round(large["peak"] / MIB, 1),
        "render_400x300_peak_MiB": round(small["peak"] / MIB, 1),
        "process_baseline_MiB": round(large["base"] / MIB, 1),
        "growth_bytes_per_pixel": round(per_pixel, 1),
        "frame_buffer_bytes_per_pixel": FRAME_BYTES_PER_PIXEL,
        "growth_limit_bytes_per_pixel": round(FRAME_BYTES_PER_PIXEL * ALLOCATOR_SLACK, 1),
        "unchunked_bytes_per_pixel": round(unchunked_per_pixel, 1),
        "unchunked_4000x3000_estimate_MiB": round(unchunked_per_pixel * pixels(LARGE_FRAME) / MIB),
        "seconds_both_cli_renders": round(large_seconds, 1),
    }
    for name, value in measured.items():
        record_property(name, value)
    record_property("message", f"4000x3000 rendered with a peak of {measured['render_4000x3000_peak_MiB']} MiB "
                               f"(400x300: {measured['render_400x300_peak_MiB']} MiB); unchunked it would need about "
                               f"{measured['unchunked_4000x3000_estimate_MiB']} MiB")
    assert Image.open(tmp_path / "large" / "frame.png").size == LARGE_FRAME
    assert per_pixel <= FRAME_BYTES_PER_PIXEL * ALLOCATOR_SLACK, measured
    assert unchunked_per_pixel > 2 * FRAME_BYTES_PER_PIXEL, measured  # the test can see a missing chunking


# ----------------------------------------------------------------------------- network


NETWORK_MODULES = {"socket", "ssl", "http", "urllib", "urllib3", "requests", "ftplib", "smtplib", "httpx", "aiohttp"}


def imported_modules(path: Path) -> set[str]:
    tree = ast.parse(path.read_text())
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            names.add(node.module.split(".")[0])
    return names


def install_operator(path: Path) -> ast.FunctionDef:
    tree = ast.parse(path.read_text())
    cls = next(n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == "NEULF_OT_install_dependencies")
    return next(n for n in cls.body if isinstance(n, ast.FunctionDef) and n.name == "execute")


def test_no_network_unless_the_user_installs(tiny_scene, tmp_path, capfd, monkeypatch, record_property):
    """Training and rendering open no connection; the only download (pip) is the install
    operator's, which first checks Blender's online access; the manifest declares it."""
    attempts = []

    def refuse(*args, **kwargs):
        attempts.append(args)
        raise OSError("network access attempted during a test that forbids it")

    monkeypatch.setattr(socket.socket, "connect", refuse)
    monkeypatch.setattr(socket, "getaddrinfo", refuse)
    model = tmp_path / "model"
    assert run_cli(["train", tiny_scene, "--out", model, *QUICK_TRAIN], capfd)[0] == 0
    assert run_cli(["render", model, "--scene", tiny_scene, "--views", "held-out", "--out", tmp_path / "out"], capfd)[0] == 0
    assert attempts == []

    sources = sorted((REPO / "neulf_core").rglob("*.py")) + sorted((REPO / "neulf_blender").glob("*.py"))
    offenders = {str(p.relative_to(REPO)): sorted(imported_modules(p) & NETWORK_MODULES) for p in sources}
    assert not {k: v for k, v in offenders.items() if v}, offenders
    callers = [p.name for p in sources if "pip_install_job(" in p.read_text() and p.name != "jobs.py"]
    assert callers == ["preferences.py"], callers
    execute = install_operator(REPO / "neulf_blender" / "preferences.py")
    guard = execute.body[0]
    assert isinstance(guard, ast.If) and "online_access" in ast.unparse(guard.test), ast.unparse(execute)[:300]
    assert any(isinstance(n, ast.Return) for n in guard.body)
    assert "network" in (REPO / "blender_manifest.toml").read_text().split("[permissions]", 1)[1]
    record_property("message", "no connection attempted by train/render; pip runs only from "
                               "NEULF_OT_install_dependencies after bpy.app.online_access is checked")


def test_a_second_training_of_the_same_model_folder_is_refused(tiny_scene, tmp_path):
    """Two processes must not write one checkpoint: the second is refused and names the first;
    a lock left by a process that no longer exists is taken over."""
    from neulf_core.errors import NeulfError
    from neulf_core.lock import LOCK_NAME, training_holder, training_lock
    from neulf_core.train import TrainConfig, train

    model = tmp_path / "m"
    config = TrainConfig(preset="planes", steps=2, batch_size=64, validate_seconds=1e9,
                         field_overrides={"spatial_res": [8, 16], "channels": 4})
    sleeper = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        model.mkdir()
        (model / LOCK_NAME).write_text(json.dumps({"pid": sleeper.pid, "host": platform.node()}))
        assert training_holder(model)["pid"] == sleeper.pid  # what Blender asks before it starts one
        with pytest.raises(NeulfError, match=f"being trained by process {sleeper.pid}"):
            train(tiny_scene, model, config)
    finally:
        sleeper.kill()
        sleeper.wait()
    assert training_holder(model) is None  # a lock whose process is gone holds nothing
    # A lock from another machine (a shared folder) cannot be checked: it holds, and the
    # message says which file to delete if that machine no longer trains the folder.
    (model / LOCK_NAME).write_text(json.dumps({"pid": 1, "host": "another-machine"}))
    with pytest.raises(NeulfError, match=f"on another-machine; .* delete {re.escape(str(model / LOCK_NAME))}"):
        train(tiny_scene, model, config)
    (model / LOCK_NAME).unlink()
    result = train(tiny_scene, model, config)  # the holder is gone: its lock is taken over
    assert result.step == 2 and not (model / LOCK_NAME).exists()
    with training_lock(tmp_path / "held"):
        assert (tmp_path / "held" / LOCK_NAME).is_file()
    assert not (tmp_path / "held").exists()  # nothing was written: no empty folder left behind


def test_a_lock_whose_process_number_was_given_again_is_stale(tmp_path):
    """A container restarted after a kill gives its new process the old one's number (often
    1): the lock then named a live process, itself, and refused every training for good. A
    process started after the lock was written is not its writer."""
    from neulf_core.lock import LOCK_NAME, _process_started_at, training_holder

    this_started = _process_started_at(os.getpid())
    if this_started is None:
        pytest.skip("no /proc: process start times cannot be read here")
    (tmp_path / LOCK_NAME).write_text(json.dumps({"pid": os.getpid(), "host": platform.node(),
                                                  "started": this_started - 100}))
    assert training_holder(tmp_path) is None
    (tmp_path / LOCK_NAME).write_text(json.dumps({"pid": os.getpid(), "host": platform.node(),
                                                  "started": this_started + 1}))
    assert training_holder(tmp_path)["pid"] == os.getpid()  # written by this very process: held


# ----------------------------------------------------------------------------- outputs and numbers


def test_output_that_is_a_file_is_said_before_rendering(model, tiny_scene, tmp_path, capfd, record_property):
    """--out naming a file (or a folder inside one): one line before anything is computed, for
    render, eval and video alike (they raised FileExistsError / NotADirectoryError)."""
    taken = tmp_path / "taken"
    taken.write_text("the user's file")
    cams = camera_json(tmp_path / "c.json", [pinhole("novel", [0, 0, 0], [0, 0, 3])])
    expect_error(["render", model, "--cameras", cams, "--out", taken], capfd, record_property, "is a file")
    expect_error(["render", model, "--cameras", cams, "--out", taken / "sub"], capfd, record_property, "cannot make")
    expect_error(["eval", model, "--scene", tiny_scene, "--out", taken], capfd, record_property, "is a file")
    expect_error(["video", model, "--out", taken / "spiral.mp4", "--frames", 2], capfd, record_property, "is a file")
    assert taken.read_text() == "the user's file"


@pytest.mark.parametrize("name", ["spiral", "a_folder"])
def test_video_needs_a_video_file_name(name, model, tmp_path, capfd, record_property):
    (tmp_path / "a_folder").mkdir()
    expect_error(["video", model, "--out", tmp_path / name, "--frames", 2], capfd, record_property,
                 "give a video file name ending in .mp4" if name == "spiral" else "is a folder: give a video file's name")


def test_a_full_disk_is_one_line():
    """The error a full disk raises (written to /dev/full, a real ENOSPC) becomes one line that
    says what to do, as main() prints it for any command."""
    from neulf_core.cli import _os_error_line

    if not Path("/dev/full").exists():
        pytest.skip("no /dev/full on this system")
    with pytest.raises(OSError) as caught:
        with open("/dev/full", "w") as full:
            full.write("x")
    line = _os_error_line(caught.value)
    assert line.startswith("the disk is full") and "--resume" in line, line


NOT_NUMBERS = {
    # options: what each took before (a traceback, or a run that did nothing)
    "train --scale nan": ["train", "SCENE", "--out", "OUT", "--steps", "2", "--scale", "nan"],  # ValueError
    "train --minutes nan": ["train", "SCENE", "--out", "OUT", "--minutes", "nan"],  # 0 steps, exit 0
    "train --checkpoint-seconds -5": ["train", "SCENE", "--out", "OUT", "--steps", "2", "--checkpoint-seconds", "-5"],
    "train --holdout-every -1": ["train", "SCENE", "--out", "OUT", "--steps", "2", "--holdout-every", "-1"],
    "train --depth-layers 100000": ["train", "SCENE", "--out", "OUT", "--steps", "2", "--depth-layers", "100000"],
    "train --scale 2": ["train", "SCENE", "--out", "OUT", "--steps", "2", "--scale", "2"],  # trained on enlarged photos
    "render --scale inf": ["render", "MODEL", "--scene", "SCENE", "--views", "all", "--out", "OUT", "--scale", "inf"],
    "render --aperture nan": ["render", "MODEL", "--cameras", "CAMS", "--out", "OUT", "--aperture", "nan",
                              "--focus-distance", "3"],
    "render --aperture inf": ["render", "MODEL", "--cameras", "CAMS", "--out", "OUT", "--aperture", "inf",
                              "--focus-distance", "3"],
    "video --frames -1": ["video", "MODEL", "--out", "OUT.mp4", "--frames", "-1"],
    "video --fps 0": ["video", "MODEL", "--out", "OUT.mp4", "--fps", "0"],  # wrote 24 fps
}


@pytest.mark.parametrize("case", list(NOT_NUMBERS))
def test_numbers_that_are_not_numbers(case, model, tiny_scene, tmp_path, capfd, record_property):
    cams = camera_json(tmp_path / "c.json", [pinhole("novel", [0, 0, 0], [0, 0, 3])])
    swap = {"SCENE": tiny_scene, "OUT": tmp_path / "out", "MODEL": model, "CAMS": cams, "OUT.mp4": tmp_path / "v.mp4"}
    argv = [swap.get(arg, arg) for arg in NOT_NUMBERS[case]]
    line = expect_error(argv, capfd, record_property)
    assert ("give a" in line and "number" in line) or "--depth-layers takes a count from 0 to" in line, line
    assert not (tmp_path / "out").exists() and not (tmp_path / "v.mp4").exists()


CAMERA_JSON_PROBLEMS = {
    # what is wrong: (how to break the file, text of the one line)
    "a folder": (lambda path: path.mkdir(), "is a folder"),
    "two cameras of one name": (lambda path: camera_json(path, [pinhole("same", [0, 0, 0], [0, 0, 3])] * 2),
                                "are named 'same'"),
    "K's last row not 0 0 1": (lambda path: camera_json(path, [dict(pinhole("k", [0, 0, 0], [0, 0, 3]),
                                                                    K=[[40, 0, 16], [0, 40, 12], [0, 0, 2]])]),
                               "K's last row must be [0, 0, 1]"),
    "a width of 32.5": (lambda path: camera_json(path, [dict(pinhole("w", [0, 0, 0], [0, 0, 3]), width=32.5)]),
                        "whole number of pixels"),
    "a width of true": (lambda path: camera_json(path, [dict(pinhole("w", [0, 0, 0], [0, 0, 3]), width=True)]),
                        "whole number of pixels"),
}


@pytest.mark.parametrize("how", list(CAMERA_JSON_PROBLEMS))
def test_camera_json_problems(how, model, tmp_path, capfd, record_property):
    """Each was a traceback (a folder), a lost image (two of one name: the second overwrote the
    first) or a silent misreading (K's last row ignored, 32.5 read as 32, true as 1)."""
    make, expected = CAMERA_JSON_PROBLEMS[how]
    path = tmp_path / "cameras.json"
    make(path)
    expect_error(["render", model, "--cameras", path, "--out", tmp_path / "out"], capfd, record_property, expected)


def test_train_refuses_a_scale_above_one(tiny_scene, tmp_path):
    """train() itself (the Python API) refuses to enlarge the photos, as the CLI does: 4 times
    the rays for no detail."""
    from neulf_core.errors import NeulfError
    from neulf_core.train import TrainConfig, train

    with pytest.raises(NeulfError, match="at most 1"):
        train(tiny_scene, tmp_path / "model", TrainConfig(steps=2, scale=2.0))
    assert not (tmp_path / "model").exists()


TRAIN_CONFIGS_REFUSED = {
    # TrainConfig values from Python (the CLI's parser refuses them first): what each did before
    "steps=-5": dict(steps=-5),  # trained forever
    "minutes=-1": dict(minutes=-1.0),  # trained forever
    "minutes=nan": dict(minutes=float("nan")),  # "finished" at step 0, an untrained model saved
    "steps=2.5": dict(steps=2.5),
    "batch_size=-1": dict(steps=2, batch_size=-1),  # torch's "negative dimension", after the photos were read
    "holdout_every=-1": dict(steps=2, holdout_every=-1),  # held out nothing, without a word
}


@pytest.mark.parametrize("case", list(TRAIN_CONFIGS_REFUSED))
def test_train_config_values_the_run_cannot_use(case, tiny_scene, tmp_path):
    from neulf_core.errors import NeulfError
    from neulf_core.train import TrainConfig, train

    with pytest.raises(NeulfError, match=r"\(TrainConfig\.\w+\) must be|training budget"):
        train(tiny_scene, tmp_path / "model", TrainConfig(**TRAIN_CONFIGS_REFUSED[case]))
    assert not (tmp_path / "model").exists()


def test_train_config_must_be_one(tiny_scene, tmp_path):
    from neulf_core.errors import NeulfError
    from neulf_core.train import train

    with pytest.raises(NeulfError, match="must be a TrainConfig"):
        train(tiny_scene, tmp_path / "model", None)


def test_ctrl_c_in_a_python_train_call_saves_and_resumes(tiny_scene, tmp_path):
    """From Python, Ctrl-C (KeyboardInterrupt) left nothing when it came before the first
    periodic checkpoint, and lost the steps since the last one after it: the run is now saved
    as a cancel is, the interrupt passed on, and resuming continues from that step."""
    from neulf_core.checkpoint import load_checkpoint
    from neulf_core.train import TrainConfig, train

    config = TrainConfig(steps=12, batch_size=256, validate_seconds=1e9, checkpoint_seconds=1e9)
    interrupted = []

    def ctrl_c_at_step_5(event):
        if event.get("event") == "step" and event["step"] >= 5 and not interrupted:
            interrupted.append(event["step"])
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        train(tiny_scene, tmp_path / "model", config, progress=ctrl_c_at_step_5)
    saved = load_checkpoint(tmp_path / "model")["progress"]
    assert saved["status"] == "cancelled" and saved["step"] == interrupted[0]
    result = train(tiny_scene, tmp_path / "model", config, resume=True)
    assert result.status == "finished" and result.step == 12


def test_ctrl_c_stops_a_python_train_call_between_steps(tiny_scene, tmp_path):
    """A real Ctrl-C (SIGINT to this process, Python's own handler in place) stops the run
    between two steps and is then passed on, so the saved run resumes to the very weights of a
    run never stopped (a KeyboardInterrupt could land halfway through a step)."""
    from conftest import assert_same_weights
    from neulf_core.train import TrainConfig, train

    if signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        pytest.skip("Python's own Ctrl-C handler is not in place here")
    config = TrainConfig(steps=12, batch_size=256, validate_seconds=1e9, checkpoint_seconds=1e9)
    train(tiny_scene, tmp_path / "whole", config)
    sent = []

    def ctrl_c_at_step_5(event):
        if event.get("event") == "step" and event["step"] >= 5 and not sent:
            sent.append(event["step"])
            os.kill(os.getpid(), signal.SIGINT)

    with pytest.raises(KeyboardInterrupt):
        train(tiny_scene, tmp_path / "stopped", config, progress=ctrl_c_at_step_5)
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # (put back)
    saved = load_checkpoint(tmp_path / "stopped")["progress"]
    assert saved["status"] == "cancelled" and sent[0] <= saved["step"] < 12
    train(tiny_scene, tmp_path / "stopped", config, resume=True)
    assert_same_weights(tmp_path / "whole", tmp_path / "stopped")


def test_ctrl_c_while_a_python_train_call_sets_up_stops_it_at_once(tiny_scene, tmp_path, monkeypatch):
    """A script's Ctrl-C while the run sets up (nothing trained yet) interrupts there, not after
    the first step; the folder is left without a model or a lock."""
    from neulf_core.train import TrainConfig, TrainingRun, train

    if signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        pytest.skip("Python's own Ctrl-C handler is not in place here")
    slept = []

    def ctrl_c_while_reading_the_photos(self, *args, **kwargs):
        slept.append("reading")
        os.kill(os.getpid(), signal.SIGINT)  # (its handler runs as os.kill returns)
        time.sleep(30)  # (a large capture's photos: never reached)
        slept.append("read")

    monkeypatch.setattr(TrainingRun, "_load_rays", ctrl_c_while_reading_the_photos)
    started = time.monotonic()
    with pytest.raises(KeyboardInterrupt):
        train(tiny_scene, tmp_path / "model", TrainConfig(steps=12, batch_size=256))
    assert time.monotonic() - started < 20 and slept == ["reading"]
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # (put back)
    assert not (tmp_path / "model" / CHECKPOINT_NAME).exists() and not (tmp_path / "model" / "training.lock").exists()


def test_numpy_numbers_in_a_train_config(tiny_scene, tmp_path):
    """A sweep's numbers are often numpy's: np.int64 steps were refused as "not 100"."""
    from neulf_core.train import TrainConfig, train

    result = train(tiny_scene, tmp_path / "model", TrainConfig(steps=np.int64(2), batch_size=np.int32(256),
                                                               scale=np.float32(0.5), validate_seconds=1e9))
    assert result.step == 2


def test_resume_with_nothing_to_resume_is_said(tiny_scene, tmp_path):
    from neulf_core.train import TrainConfig, train

    events = []
    train(tiny_scene, tmp_path / "model", TrainConfig(steps=2, batch_size=256, validate_seconds=1e9), resume=True,
          progress=events.append)
    assert any(e.get("event") == "warning" and "no model to resume yet" in e["message"] for e in events)


# ----------------------------------------------------------------------------- the Python render API


def novel_camera(centre=(0.05, 0.0, 0.0), target=(0.0, 0.0, 3.0), width=32, height=24):
    cam = pinhole("novel", centre, target, width, height)
    return np.array(cam["K"]), width, height, np.array(cam["R"]), np.array(cam["t"])


def test_a_render_stopped_by_on_chunk_says_so(model):
    """on_chunk returning False stopped the render and handed back uninitialised memory as the
    picture (garbage colours, garbage `valid`, bogus warnings)."""
    from neulf_core.render import LightField

    K, width, height, R, t = novel_camera()
    rendering = LightField.load(model, "cpu").render(K, width, height, R, t, chunk=width * 8,
                                                     on_chunk=lambda done, total: done < 8)
    assert not rendering.complete and any("stopped after 8 of 24 rows" in w for w in rendering.warnings)
    assert rendering.valid[:8].all() and not rendering.valid[8:].any()
    assert (rendering.rgb[8:] == 0).all() and np.isnan(rendering.depth[8:]).all()
    assert np.isfinite(rendering.rgb).all() and not any("look away" in w for w in rendering.warnings)


def test_a_camera_past_the_scene_sees_no_surface_behind_it(model):
    """A camera moved past the captured surface (the tiny scene's plane lies at z = 3): every
    pixel was "valid" with a negative depth; a surface behind the camera is not in view."""
    from neulf_core.render import LightField

    light_field = LightField.load(model, "cpu")
    K, width, height, R, t = novel_camera(centre=(0.0, 0.0, 6.0), target=(0.0, 0.0, 9.0))
    rendering = light_field.render(K, width, height, R, t)
    assert not rendering.valid.any() and np.isnan(rendering.depth).all()
    assert any("inside the scene's depth range" in w for w in rendering.warnings)
    assert any("100.0% of the pixels meet what the capture saw behind the camera" in w for w in rendering.warnings)
    assert not any("look away" in w for w in rendering.warnings)  # (they do not: every ray crosses the slab)
    assert np.allclose(rendering.rgb, light_field.background.cpu().numpy())
    no_depth = light_field.render(K, width, height, R, t, depth=False, pixel_samples=4)  # (found without depth asked)
    assert not no_depth.valid.any()
    K, width, height, R, t = novel_camera()  # at the rig: as before
    assert light_field.render(K, width, height, R, t).valid.all()


def test_a_refocused_pixel_takes_no_colour_from_a_surface_behind_the_camera(model):
    """A camera moved into the scene, refocused with a wide lens: each lens ray whose surface
    lies behind the camera counts as the background, as a pixel's centre ray does (only the
    centre ray was tested, so a surface the camera had moved past bled into the pixels beside
    it).  The reference is the mean over the lens rays, built here from the lens samples."""
    from neulf_core.rays import pinhole_rays
    from neulf_core.refocus import MAX_SAMPLES, lens_rays
    from neulf_core.render import LightField

    light_field = LightField.load(model, "cpu")
    K, width, height, R, t = novel_camera(centre=(0.0, 0.0, 2.8), target=(2.0, 0.0, 3.8))  # tilted, inside
    aperture, focus = 0.5, 1.0  # (its lens reaches past the learned surface near z = 3)
    assert light_field.camera_inside_scene(R, t)
    rendering = light_field.render(K, width, height, R, t, aperture=aperture, focus_distance=focus)
    origin, directions = pinhole_rays(K, R, light_field.slab.origin_relative_t(R, t), width, height)
    forward = torch.as_tensor(R[2], dtype=torch.float64)
    total, behind_rays = 0, 0
    for point in light_field._lens_plan(K, focus, aperture, MAX_SAMPLES):
        lens_origin, lens_directions = lens_rays(origin, directions, R, focus, aperture, point)
        rgb, slab_depth, valid, _ = light_field.query(lens_origin, lens_directions)
        rotation = torch.as_tensor(light_field.slab.rotation)
        length = (slab_depth - lens_origin @ rotation[2]) / (lens_directions @ rotation[2])
        behind = valid & (length * (lens_directions @ forward) <= 0)  # the surface point's side of the lens
        total = total + torch.where(behind[:, None], light_field.background, rgb)
        behind_rays += int(behind.reshape(height, width)[torch.as_tensor(rendering.valid)].sum())
    count = len(light_field._lens_plan(K, focus, aperture, MAX_SAMPLES))
    reference = (total / count).reshape(height, width, 3).numpy()
    assert behind_rays > 0.1 * count * rendering.valid.sum()  # (lens rays of pixels in view meet surfaces behind)
    assert np.abs(rendering.rgb[rendering.valid] - reference[rendering.valid]).max() < 1e-5


CAMERAS_REFUSED = {
    # what is wrong: (K, R, t) -> text of the one line (before: a torch error, or a wrong picture)
    "t of 4 numbers": (lambda K, R, t: (K, R, np.append(t, 1.0)), "t 3 numbers"),
    "K flat": (lambda K, R, t: (K.ravel(), R, t), "must be 3x3"),
    "[R|t] as R": (lambda K, R, t: (K, np.column_stack([R, t]), t), "must be 3x3"),
    "R scaled": (lambda K, R, t: (K, 2 * R, t), "not a rotation"),
    "R mirrored": (lambda K, R, t: (K, -R, t), "not a rotation"),
    "t NaN": (lambda K, R, t: (K, R, np.array([np.nan, 0, 0])), "NaN or infinity"),
    "K zero": (lambda K, R, t: (np.zeros((3, 3)), R, t), "positive focal lengths"),
    "K of text": (lambda K, R, t: ([["a"] * 3] * 3, R, t), "arrays of numbers"),
}


@pytest.mark.parametrize("case", list(CAMERAS_REFUSED))
def test_render_refuses_cameras_it_cannot_use(case, model):
    from neulf_core.errors import NeulfError
    from neulf_core.render import LightField

    K, width, height, R, t = novel_camera()
    change, expected = CAMERAS_REFUSED[case]
    K, R, t = change(K, R, t)
    with pytest.raises(NeulfError, match=re.escape(expected)):
        LightField.load(model, "cpu").render(K, width, height, R, t)


@pytest.mark.parametrize("size, expected", [
    ((80.7, 24), "whole numbers"),  # rendered 80 wide without a word
    (("80", True), "whole numbers"),
    ((0, 24), "at least 1 pixel"),
    ((400_000, 400_000), "a side is at most 65535 pixels"),  # (had been numpy's MemoryError, 2.7 TB)
    ((10**9, 24), "a side is at most 65535 pixels"),  # (numpy's "array is too big" ValueError)
], ids=["80.7 wide", "True high", "zero wide", "too large", "a billion wide"])
def test_render_refuses_image_sizes_it_cannot_make(size, expected, model):
    from neulf_core.errors import NeulfError
    from neulf_core.render import LightField

    K, _, _, R, t = novel_camera()
    with pytest.raises(NeulfError, match=expected):
        LightField.load(model, "cpu").render(K, *size, R, t)


def test_a_render_that_does_not_fit_in_memory_is_one_line(model, monkeypatch):
    """Within the largest side a frame can still be past the memory (65535 x 65535 is 73 GB of
    colour, depth and mask): numpy's MemoryError becomes a line that says to render a smaller
    one.  (Simulated: whether such a frame fits depends on the machine.)"""
    import neulf_core.render as render
    from neulf_core.errors import NeulfError

    light_field = render.LightField.load(model, "cpu")

    def no_memory(*args, **kwargs):
        raise MemoryError

    monkeypatch.setattr(render.np, "zeros", no_memory)
    K, _, _, R, t = novel_camera()
    with pytest.raises(NeulfError, match=r"a 65535 x 65535 image does not fit in memory \(73 GB .*render a smaller one"):
        light_field.render(K, 65535, 65535, R, t)


def test_running_out_of_memory_anywhere_is_one_line(monkeypatch, capsys):
    """torch's CPU allocator runs out with a RuntimeError, not a MemoryError: the CLI says
    what to do about it either way, and lets any other RuntimeError (a bug) show itself."""
    import neulf_core.cli as cli
    from neulf_core.errors import OUT_OF_MEMORY

    refusal = "[enforce fail at alloc_cpu.cpp:127] err == 0. DefaultCPUAllocator: can't allocate memory"
    for raised in (RuntimeError(refusal), MemoryError()):
        def running_out(args, raised=raised):
            raise raised
        monkeypatch.setattr(cli, "cmd_eval", running_out)
        assert cli.main(["eval", "model", "--scene", "scene"]) == 1
        assert capsys.readouterr().err == f"error: {OUT_OF_MEMORY}\n"

    def broken(args):
        raise RuntimeError("mat1 and mat2 shapes cannot be multiplied")
    monkeypatch.setattr(cli, "cmd_eval", broken)
    with pytest.raises(RuntimeError, match="shapes"):
        cli.main(["eval", "model", "--scene", "scene"])


def test_render_takes_t_as_a_column_or_a_row(model):
    from neulf_core.render import LightField

    light_field = LightField.load(model, "cpu")
    K, width, height, R, t = novel_camera()
    flat = light_field.render(K, width, height, R, t).rgb
    for shaped in (t.reshape(3, 1), t.reshape(1, 3), t.tolist()):
        assert np.array_equal(light_field.render(K, width, height, R, shaped).rgb, flat)


@pytest.mark.parametrize("options, expected", [
    (dict(aperture=float("nan"), focus_distance=3.0), "finite number of at least 0"),  # int(NaN) deep inside
    (dict(aperture=-1.0, focus_distance=3.0), "finite number of at least 0"),  # the pinhole, without a word
    (dict(aperture=0.05, focus_distance=3.0, max_samples=0), "max_samples"),  # one sample, the aperture ignored
], ids=["aperture nan", "aperture negative", "no lens samples"])
def test_refocus_values_it_cannot_use(options, expected, model):
    from neulf_core.errors import NeulfError
    from neulf_core.render import LightField

    K, width, height, R, t = novel_camera()
    with pytest.raises(NeulfError, match=expected):
        LightField.load(model, "cpu").render(K, width, height, R, t, **options)


def test_render_view_gives_the_camera_s_warnings(model, tiny_scene):
    """render_view's warnings were always empty; a view moved into the scene now gets them."""
    from dataclasses import replace as replaced

    from neulf_core.render import LightField
    from neulf_core.scene import load_scene

    light_field, view = LightField.load(model, "cpu"), load_scene(tiny_scene).views[0]
    assert light_field.render_view(view, 0.25).warnings == []
    inside = replaced(view, t=view.t - view.R @ np.array([0.0, 0.0, 2.8]))  # the camera 2.8 forward, near the plane
    assert any("inside the scene's depth range" in w for w in light_field.render_view(inside, 0.25).warnings)
    past = replaced(view, t=view.t - view.R @ np.array([0.0, 0.0, 6.0]))  # past the plane: as render, nothing ahead
    rendering = light_field.render_view(past, 0.25)
    assert not rendering.valid.any() and np.isnan(rendering.depth).all()


def test_render_cameras_past_the_scene_are_said(model, tmp_path, capfd, record_property):
    """A camera past what it looks at was called one that looks away, told to turn round."""
    cams = camera_json(tmp_path / "c.json", [pinhole("past", [0, 0, 6], [0, 0, 9])])
    line = expect_error(["render", model, "--cameras", cams, "--out", tmp_path / "out"], capfd, record_property,
                        "stand inside the captured scene, past what they look at")
    assert "look away" not in line


def test_a_scene_folder_given_as_the_model_is_said(tiny_scene, tmp_path, capfd, record_property):
    """It proposed training into the scene folder itself."""
    cams = camera_json(tmp_path / "c.json", [pinhole("novel", [0, 0, 0], [0, 0, 3])])
    line = expect_error(["render", tiny_scene, "--cameras", cams, "--out", tmp_path / "out"], capfd, record_property,
                        "is a scene folder (photos and camera poses), not a model")
    assert f"--out {tiny_scene}" not in line


def test_focus_pixel_takes_whole_pixels(model, tmp_path, capfd, record_property):
    """31.7 passed the image's bounds check and then aimed past its last column."""
    cams = camera_json(tmp_path / "c.json", [pinhole("novel", [0, 0, 0], [0, 0, 3])])
    expect_error(["render", model, "--cameras", cams, "--out", tmp_path / "out", "--aperture", "0.05",
                  "--focus-pixel", "31.7,10"], capfd, record_property, "whole numbers")


def test_focus_pixel_outside_the_image(model, tmp_path, capfd, record_property):
    cams = camera_json(tmp_path / "c.json", [pinhole("novel", [0, 0, 0], [0, 0, 3])])
    expect_error(["render", model, "--cameras", cams, "--out", tmp_path / "out", "--aperture", "0.05",
                  "--focus-pixel", "9999,10"], capfd, record_property, "outside novel's 32 x 24 image")


def test_focus_pixel_focuses_at_the_depth_map_s_pixel(model, tmp_path, capfd):
    """--focus-pixel X,Y takes the depth the depth map holds at [Y, X] (the pixel's centre);
    it took the corner between four pixels, a depth no surface has at a depth edge."""
    cams = camera_json(tmp_path / "c.json", [pinhole("novel", [0.05, 0, 0], [0.6, 0.3, 3])])  # (turned: depth varies)
    assert run_cli(["render", model, "--cameras", cams, "--out", tmp_path / "pin", "--depth"], capfd)[0] == 0
    depth = np.load(tmp_path / "pin" / "novel_depth.npy")
    for x, y in ((5, 7), (20, 3), (31, 23)):
        code, _, err = run_cli(["render", model, "--cameras", cams, "--out", tmp_path / "lens", "--aperture", "0.01",
                                "--focus-pixel", f"{x},{y}"], capfd)
        said = float(re.search(r"-> depth ([0-9.e+-]+)", err).group(1))
        assert code == 0 and said == pytest.approx(float(depth[y, x]), rel=2e-5), (x, y, err)


def test_a_focus_without_an_aperture_renders_the_plain_pinhole(model, tiny_scene, tmp_path, capfd):
    """Aperture 0 with --focus-pixel rendered the view's undistorted pinhole, unlike the same
    render without it or with --focus-distance; now all three are the same image."""
    from pycolmap import Camera, Reconstruction

    scene = copy_scene(tiny_scene, tmp_path / "scene")  # its camera given radial distortion, which the
    reconstruction = Reconstruction(scene / "sparse" / "0")  # undistorted pinhole leaves out
    camera = next(iter(reconstruction.cameras.values()))
    focal, cx, cy = camera.params[0], camera.params[2], camera.params[3]
    reconstruction.cameras[camera.camera_id] = Camera(camera_id=camera.camera_id, model="SIMPLE_RADIAL", width=camera.width,
                                                      height=camera.height, params=[focal, cx, cy, 0.2])
    reconstruction.write(scene / "sparse" / "0")
    views = ["render", model, "--scene", scene, "--views", "held-out"]
    assert run_cli([*views, "--out", tmp_path / "plain"], capfd)[0] == 0
    code, _, err = run_cli([*views, "--out", tmp_path / "focus", "--focus-pixel", "3,4"], capfd)
    assert code == 0 and "renders a pinhole" in err
    for image in (tmp_path / "plain").glob("*.png"):
        assert image.read_bytes() == (tmp_path / "focus" / image.name).read_bytes()


def test_render_cameras_at_a_scale(model, tmp_path, capfd):
    """--scale with --cameras was ignored without a word; it scales each camera's image and K,
    so the half-size image is the full one averaged down."""
    from PIL import Image

    cams = camera_json(tmp_path / "c.json", [pinhole("novel", [0.05, 0, 0], [0, 0, 3], width=64, height=48)])
    for scale, folder in ((1, "full"), (0.5, "half")):
        assert run_cli(["render", model, "--cameras", cams, "--out", tmp_path / folder, "--scale", scale,
                        "--pixel-samples", 1], capfd)[0] == 0
    full = np.asarray(Image.open(tmp_path / "full" / "novel.png"), np.float64)
    half = np.asarray(Image.open(tmp_path / "half" / "novel.png"), np.float64)
    assert half.shape == (24, 32, 3)
    averaged = full.reshape(24, 2, 32, 2, 3).mean(axis=(1, 3))
    assert np.abs(half - averaged).mean() < np.abs(half - np.roll(averaged, 1, axis=1)).mean()


REFOCUS_OPTIONS_IN_CONFLICT = {
    # options: what the line names (before: one of them dropped without a word)
    "a focus distance and a focus pixel": (["--aperture", "0.05", "--focus-distance", "3", "--focus-pixel", "3,4"],
                                           "not both"),
    "a focal length without an f-stop": (["--aperture", "0.05", "--focus-distance", "3", "--focal-length", "0.05"],
                                         "only with --f-stop"),
}


@pytest.mark.parametrize("case", list(REFOCUS_OPTIONS_IN_CONFLICT))
def test_refocus_options_in_conflict(case, model, tmp_path, capfd, record_property):
    options, expected = REFOCUS_OPTIONS_IN_CONFLICT[case]
    cams = camera_json(tmp_path / "c.json", [pinhole("novel", [0, 0, 0], [0, 0, 3])])
    expect_error(["render", model, "--cameras", cams, "--out", tmp_path / "out", *options], capfd, record_property,
                 expected)


def test_pixel_samples_while_refocusing_is_said(model, tmp_path, capfd):
    cams = camera_json(tmp_path / "c.json", [pinhole("novel", [0, 0, 0], [0, 0, 3])])
    code, _, err = run_cli(["render", model, "--cameras", cams, "--out", tmp_path / "out", "--aperture", "0.05",
                            "--focus-distance", "3", "--pixel-samples", "16"], capfd)
    assert code == 0 and "--pixel-samples is not used while refocusing" in err


def test_resume_says_which_asked_options_the_model_keeps(model, tiny_scene, tmp_path, capfd, record_property):
    """--resume continues the model as it was trained; options asked for that differ from its
    own are said (they were dropped without a word), and the run goes on."""
    resumed = shutil.copytree(model, tmp_path / "model")
    code, out, err = run_cli(["train", tiny_scene, "--out", resumed, "--resume", "--steps", "4", "--batch-size", "256",
                              "--validate-seconds", "1e9", "--preset", "planes", "--holdout-every", "4", "--progress",
                              "json"], capfd)
    assert code == 0, err
    warnings = [json.loads(line)["message"] for line in out.splitlines() if '"warning"' in line]
    warning = next(w for w in warnings if w.startswith("resuming continues the model as it was trained"))
    record_property("message", warning)
    assert "--preset (the model's: 'fast')" in warning and "--holdout-every (the model's: 8)" in warning, warning
    assert "--batch-size" not in warning  # (asked as the model has it: nothing to say)
    meta = json.loads((resumed / METADATA_NAME).read_text())
    assert meta["train_config"]["preset"] == "fast" and meta["progress"]["step"] == 4
    code, out, err = run_cli(["train", tiny_scene, "--out", tmp_path / "new", "--resume", *QUICK_TRAIN], capfd)
    assert code == 0 and (out + err).count("holds no model to resume yet: training a new one") == 1, out + err


def test_resume_from_python_says_which_options_the_model_keeps(model, tiny_scene, tmp_path):
    """train(resume=True) from Python keeps the model's own preset, scale, seed, ... as the
    command line does; the fields set otherwise are said in a warning event, by their own
    names (they were dropped without a word)."""
    from dataclasses import replace

    from neulf_core.train import TrainConfig, train

    resumed = shutil.copytree(model, tmp_path / "model")
    saved = json.loads((resumed / METADATA_NAME).read_text())["train_config"]
    same = TrainConfig(**{k: v for k, v in saved.items() if k in TrainConfig.__dataclass_fields__})
    events = []
    train(tiny_scene, resumed, replace(same, steps=saved["steps"] + 1, minutes=None, validate_seconds=1e9),
          resume=True, progress=events.append)
    assert not [e for e in events if e["event"] == "warning"]  # (as the model has them: nothing to say)
    asked = replace(same, steps=saved["steps"] + 2, minutes=None, validate_seconds=1e9, scale=saved["scale"] / 2,
                    seed=7, field_overrides={"geometry_layers": 1})
    train(tiny_scene, resumed, asked, resume=True, progress=events.append)
    warning = next(e["message"] for e in events if e["event"] == "warning")
    assert warning.startswith("resuming continues the model as it was trained"), warning
    assert f"scale (the model's: {saved['scale']!r})" in warning and "seed (the model's: 0)" in warning, warning
    assert "geometry_layers (the model's: the rule)" in warning, warning
    assert "preset" not in warning and "steps" not in warning  # (the budget may change: not kept)
    meta = json.loads((resumed / METADATA_NAME).read_text())
    assert meta["train_config"]["scale"] == saved["scale"] and meta["progress"]["step"] == saved["steps"] + 2


def test_eval_takes_all_and_held_out(model, tiny_scene, tmp_path, capfd):
    code, out, err = run_cli(["eval", model, "--scene", tiny_scene, "--views", "all", "--out", tmp_path / "all",
                              "--pixel-samples", "1"], capfd)
    assert code == 0, err
    assert len(json.loads((tmp_path / "all" / "eval.json").read_text())["views"]) == len(VIEW_NAMES)
    code, out, err = run_cli(["eval", model, "--scene", tiny_scene, "--views", "held-out", "--out", tmp_path / "held",
                              "--pixel-samples", "1"], capfd)
    assert code == 0, err
    assert [row["view"] for row in json.loads((tmp_path / "held" / "eval.json").read_text())["views"]] == \
        ["view_00.png", "view_08.png"]


def test_render_of_a_model_before_its_first_checkpoint(tmp_path, capfd, record_property):
    """A model folder whose training runs but has not saved yet: said so (it read 'holds no
    trained model; train one', which a second training would then be refused)."""
    from neulf_core.lock import LOCK_NAME

    folder = tmp_path / "m"
    folder.mkdir()
    sleeper = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        (folder / LOCK_NAME).write_text(json.dumps({"pid": sleeper.pid, "host": platform.node()}))
        cams = camera_json(tmp_path / "c.json", [pinhole("novel", [0, 0, 0], [0, 0, 3])])
        expect_error(["render", folder, "--cameras", cams, "--out", tmp_path / "out"], capfd, record_property,
                     f"is being trained (process {sleeper.pid}) and has no checkpoint yet")
    finally:
        sleeper.kill()
        sleeper.wait()


@pytest.fixture(scope="module")
def half_size_model(tiny_scene, tmp_path_factory):
    """The tiny scene with a second folder of its photos at half size (as LLFF's images_2/), and
    a model trained on that folder."""
    root = tmp_path_factory.mktemp("images_n")
    scene = shutil.copytree(tiny_scene, root / "scene")
    (scene / "images_2").mkdir()
    for photo in sorted((scene / "images").iterdir()):
        image = Image.open(photo)
        image.resize((image.width // 2, image.height // 2), Image.BOX).save(scene / "images_2" / photo.name)
    model = root / "model"
    assert main(["train", str(scene), "--images", str(scene / "images_2"), "--scale", "1", "--out", str(model),
                 *QUICK_TRAIN]) == 0
    return scene, model


def test_eval_render_and_resume_read_the_photos_the_model_trained_on(half_size_model, tmp_path, capfd, record_property):
    """A model trained on a scene's images_2/ is scored, rendered and resumed on those photos
    without --images (it had taken images/, four times the pixels, without a word); given the
    other folder, eval and render score and render at the size it trained at and say so, and
    resume refuses in one line."""
    scene, model = half_size_model
    trained = json.loads((model / METADATA_NAME).read_text())["scene"]
    assert trained["images"] == "images_2" and trained["photo_sizes"]["view_00.png"] == [TINY_WIDTH // 2, TINY_HEIGHT // 2]
    code, out, err = run_cli(["eval", model, "--scene", scene, "--out", tmp_path / "own", "--pixel-samples", "1"], capfd)
    report = json.loads((tmp_path / "own" / "eval.json").read_text())
    assert code == 0 and "warning" not in err and report["images"].endswith("images_2"), err
    assert {(row["width"], row["height"]) for row in report["views"]} == {(TINY_WIDTH // 2, TINY_HEIGHT // 2)}
    code, out, err = run_cli(["eval", model, "--scene", scene, "--images", scene / "images", "--out", tmp_path / "other",
                              "--pixel-samples", "1"], capfd)
    other = json.loads((tmp_path / "other" / "eval.json").read_text())
    assert code == 0 and "of another size than the model trained on" in err and other["warnings"], err
    record_property("message", err.strip())
    assert {(row["width"], row["height"]) for row in other["views"]} == {(TINY_WIDTH // 2, TINY_HEIGHT // 2)}
    assert abs(other["mean_psnr"] - report["mean_psnr"]) < 1.0  # (the same pictures, from photos box-resized again)
    code, out, err = run_cli(["render", model, "--scene", scene, "--images", scene / "images", "--views", "held-out",
                              "--out", tmp_path / "renders", "--pixel-samples", "1"], capfd)
    assert code == 0 and "of another size" in err, err
    assert Image.open(tmp_path / "renders" / "view_00.png").size == (TINY_WIDTH // 2, TINY_HEIGHT // 2)
    resumed = shutil.copytree(model, tmp_path / "resumed")
    code, out, err = run_cli(["train", scene, "--out", resumed, "--resume", "--images", scene / "images",
                              "--steps", "4", "--batch-size", "256", "--validate-seconds", "1e9"], capfd)
    assert code == 2 and err.count("\n") == 1 and "trained on photos of another size" in err and "--images" in err, err
    assert json.loads((resumed / METADATA_NAME).read_text())["progress"]["step"] == 2  # untouched
    code, out, err = run_cli(["train", scene, "--out", resumed, "--resume", "--steps", "4", "--batch-size", "256",
                              "--validate-seconds", "1e9"], capfd)
    meta = json.loads((resumed / METADATA_NAME).read_text())
    assert code == 0 and meta["progress"]["step"] == 4 and meta["scene"]["photo_sizes"] == trained["photo_sizes"], err


def test_eval_scores_each_view_once_and_takes_held_out_among_names(model, tiny_scene, tmp_path, capfd):
    code, out, err = run_cli(["eval", model, "--scene", tiny_scene, "--views", "view_03,held-out,view_03.png,view_00",
                              "--out", tmp_path / "e", "--pixel-samples", "1"], capfd)
    assert code == 0, err
    assert [row["view"] for row in json.loads((tmp_path / "e" / "eval.json").read_text())["views"]] == \
        ["view_03.png", "view_00.png", "view_08.png"]


# ----------------------------------------------------------------------------- the training lifecycle (audit, 2026-12-01)


def test_a_model_without_its_checkpoint_is_neither_trained_over_nor_resumed(tiny_scene, tmp_path, capfd, record_property):
    """checkpoint.pt deleted to save space, model.pt kept (what rendering needs): a new training
    had replaced the model without a word, and a resume had said there was nothing to resume,
    trained a new first member and continued the old second one beside it."""
    model = tmp_path / "model"
    assert main([str(a) for a in ["train", tiny_scene, "--out", model, "--steps", "4", "--batch-size", "256",
                                  "--validate-seconds", "1e9", "--members", "2"]]) == 0
    (model / CHECKPOINT_NAME).unlink()
    kept = {path: path.read_bytes() for path in sorted(model.rglob("*")) if path.is_file()}
    for extra in ([], ["--resume"], ["--resume", "--preset", "auto"], ["--preset", "auto"]):
        code, out, err = run_cli(["train", tiny_scene, "--out", model, *QUICK_TRAIN, *extra], capfd)
        assert code == 2 and err.count("\n") == 1 and "without its checkpoint.pt" in err, (extra, err)
        record_property("message", err.strip())
    assert {path: path.read_bytes() for path in sorted(model.rglob("*")) if path.is_file()} == kept


def test_a_new_model_does_not_take_an_older_one_s_members(tiny_scene, tmp_path):
    """What a deleted model's members left (members.json, members/2) is not the new model's."""
    from neulf_core.render import LightField

    model = tmp_path / "model"
    assert main([str(a) for a in ["train", tiny_scene, "--out", model, "--steps", "4", "--batch-size", "256",
                                  "--validate-seconds", "1e9", "--members", "2"]]) == 0
    for name in (CHECKPOINT_NAME, "model.pt", METADATA_NAME):
        (model / name).unlink()
    assert main([str(a) for a in ["train", tiny_scene, "--out", model, *QUICK_TRAIN, "--members", "1"]]) == 0
    assert not (model / "members.json").exists() and not (model / "members").exists()
    assert LightField.load(model, "cpu").meta.get("members") in (None, [1])


def test_the_auto_preset_refuses_a_trained_folder_before_its_search(model, tiny_scene, tmp_path, capfd):
    taken = shutil.copytree(model, tmp_path / "taken")
    started = time.perf_counter()
    code, out, err = run_cli(["train", tiny_scene, "--out", taken, "--preset", "auto", "--steps", "300",
                              "--batch-size", "256", "--validate-seconds", "1e9"], capfd)
    assert code == 2 and "already holds a trained model" in err and "candidate" not in out + err, out + err
    assert time.perf_counter() - started < 10


def test_resume_says_a_seed_a_split_or_a_batch_the_model_keeps(model, tiny_scene, tmp_path, capfd):
    """--seed, --batch-size and --members-split on --resume were dropped without a word."""
    resumed = shutil.copytree(model, tmp_path / "model")
    code, _, err = run_cli(["train", tiny_scene, "--out", resumed, "--resume", "--steps", "4", "--batch-size", "512",
                            "--validate-seconds", "1e9", "--seed", "7"], capfd)
    warning = next(line for line in err.splitlines() if line.startswith("warning: resuming continues"))
    assert code == 0 and "--seed (the model's: 0)" in warning and "--batch-size (the model's: 256)" in warning, err
    code, _, err = run_cli(["train", tiny_scene, "--out", resumed, "--resume", "--steps", "5", "--batch-size", "256",
                            "--validate-seconds", "1e9", "--seed", "0"], capfd)
    assert code == 0 and "warning: resuming continues" not in err, err


def test_a_failed_write_names_its_file(tmp_path, monkeypatch):
    """A write's OSError (a full disk, a FAT32 file past 4 GB) names no file; the message now does,
    and no temporary file is left."""
    import errno as errno_codes

    from neulf_core import files
    from neulf_core.cli import _os_error_line

    def full(_descriptor):
        raise OSError(errno_codes.ENOSPC, "No space left on device")

    monkeypatch.setattr(files.os, "fsync", full)
    with pytest.raises(OSError) as caught:
        files.atomic_write_bytes(tmp_path / "checkpoint.pt", b"x" * 100)
    line = _os_error_line(caught.value)
    assert line.startswith("the disk is full (writing ") and str(tmp_path / "checkpoint.pt") in line, line
    assert list(tmp_path.iterdir()) == []


def test_the_demo_fails_where_its_video_fails(tiny_scene, tmp_path, capfd):
    """The demo ignored its render's and video's exit status and reported a video it had not written."""
    from neulf_core.demo import run_demo
    from neulf_core.errors import NeulfError

    out = tmp_path / "demo"
    (out / "blender_scene" / "images").mkdir(parents=True)  # (--keep: the demo's Blender render is there)
    shutil.copytree(tiny_scene, out / "scene")
    (out / "spiral.mp4").mkdir()  # a folder in the way of the video
    with pytest.raises(NeulfError, match="rendering the video failed"):
        run_demo(out, minutes=0.02, keep=True)
    assert "is a folder" in capfd.readouterr().err


@pytest.mark.skipif(not hasattr(signal, "SIGHUP"), reason="no SIGHUP on this system")
def test_a_closed_terminal_saves_the_training(tiny_scene, tmp_path):
    """SIGHUP (the terminal closed, an ssh session dropped) ended the run unsaved, losing up to a
    checkpoint interval (60 s by default); it now saves as Ctrl-C does."""
    from test_checkpoint_cli import interrupt_training

    model = tmp_path / "model"
    code, _, err = interrupt_training(tiny_scene, model, signal_number=signal.SIGHUP)
    assert code == 128 + signal.SIGHUP, err
    saved = load_checkpoint(model)
    assert saved["progress"]["status"] == "cancelled" and saved["progress"]["step"] >= 1


# A training whose setting up takes long (a large capture's photos, the plane sweep): the child
# says SETTING_UP from inside it, then waits there until the signal comes.
SLOW_SETUP = """
import sys, time
import neulf_core.train as train
def slow_rays(self, *args, **kwargs):
    print("SETTING_UP", flush=True)
    time.sleep(120)
train.TrainingRun._load_rays = slow_rays
from neulf_core.cli import main
sys.exit(main(sys.argv[1:]))
"""


def stop_while_setting_up(scene, model: Path, signal_number: int, *options: str):
    """`train` stopped by `signal_number` while it sets up: (exit code, stdout, stderr, seconds
    from the signal to the end)."""
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    process = subprocess.Popen([sys.executable, "-c", SLOW_SETUP, "train", str(scene), "--out", str(model),
                                "--steps", "100000", "--batch-size", "64", "--progress", "json", *options],
                               cwd=model.parent, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        for line in process.stdout:
            if line.strip() == "SETTING_UP":
                break
        process.send_signal(signal_number)
        sent = time.monotonic()
        out, err = process.communicate(timeout=60)
        return process.returncode, out, err, time.monotonic() - sent
    finally:
        if process.poll() is None:
            process.kill()


def test_a_stop_while_setting_up_ends_the_training_at_once(tiny_scene, tmp_path, record_property):
    """SIGTERM while a new training sets up (its photos read, the plane sweep): it ends at once,
    not after the first step (12-18 s on a busy machine in the fault audit of 2026-12-07), says
    nothing was saved, and leaves no lock behind."""
    model = tmp_path / "model"
    code, out, err, seconds = stop_while_setting_up(tiny_scene, model, signal.SIGTERM)
    record_property("message", err.strip().splitlines()[-1])
    assert code == 128 + signal.SIGTERM, err
    assert seconds < 20 and "Traceback" not in err, err  # (the sleep it was in lasts 120 s)
    assert err.strip().splitlines()[-1] == ("cancelled before the first checkpoint; nothing was saved. Start again "
                                            "with the same command.")
    assert json.loads(out.strip().splitlines()[-1])["event"] == "cancelled"
    assert not (model / CHECKPOINT_NAME).exists() and not (model / "training.lock").exists()


def test_a_stop_while_setting_up_with_the_progress_bar_says_one_line(tiny_scene, tmp_path):
    """With the progress bar (a terminal's default), the stop while setting up ends in the one
    line, no traceback (the bar's line for a cancel wants the elapsed time of a run that had none)."""
    code, _, err, _ = stop_while_setting_up(tiny_scene, tmp_path / "model", signal.SIGINT, "--progress", "bar")
    assert code == 128 + signal.SIGINT and "Traceback" not in err, err
    assert err.strip().splitlines()[-1].startswith("cancelled before the first checkpoint; nothing was saved."), err


def test_a_stop_while_a_resumed_training_sets_up_keeps_the_model_as_it_was(model, tiny_scene, tmp_path,
                                                                           record_property):
    """Ctrl-C while a resumed training sets up: the saved model is left as it was, and the
    message says so and how to go on."""
    resumed = shutil.copytree(model, tmp_path / "model")
    before = (resumed / CHECKPOINT_NAME).read_bytes()
    code, out, err, seconds = stop_while_setting_up(tiny_scene, resumed, signal.SIGINT, "--resume")
    last = err.strip().splitlines()[-1]
    record_property("message", last)
    assert code == 128 + signal.SIGINT and seconds < 20 and "Traceback" not in err, err
    assert last.startswith("cancelled while setting up, before a step; the model is as it was last saved. "
                           "Continue with: python -m neulf_core train ") and "--resume" in last, last
    assert (resumed / CHECKPOINT_NAME).read_bytes() == before and not (resumed / "training.lock").exists()
    assert json.loads(out.strip().splitlines()[-1]) == {"event": "cancelled", "step": load_checkpoint(resumed)["progress"]["step"],
                                                       "setting_up": True}


@pytest.mark.skipif(not hasattr(signal, "SIGSTOP"), reason="no job control on this system")
def test_time_stopped_does_not_count_against_a_minutes_budget(tiny_scene, tmp_path, record_property):
    """A training stopped part-way (Ctrl-Z, `kill -STOP`, a scheduler's suspend) and continued
    trains its budget's minutes after all: the time it stood still is not training time (a run
    stopped longer than its budget ended the moment it was continued)."""
    budget, pause = 10.0, 6.0
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    model = tmp_path / "model"
    process = subprocess.Popen([sys.executable, "-m", "neulf_core", "train", str(tiny_scene), "--out", str(model),
                                "--minutes", str(budget / 60), "--batch-size", "64", "--progress", "json"],
                               cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        for line in process.stdout:
            event = json.loads(line)
            if event["event"] == "step":
                break
        else:
            pytest.fail(f"the training took no step: {process.communicate()[1]}")
        process.send_signal(signal.SIGSTOP)
        stopped_at = time.monotonic()
        time.sleep(pause)
        process.send_signal(signal.SIGCONT)
        out, err = process.communicate(timeout=120)
        wall = time.monotonic() - stopped_at
    finally:
        if process.poll() is None:
            process.kill()
    assert process.returncode == 0, err
    finished = json.loads(out.strip().splitlines()[-1])
    record_property("message", f"stopped {pause:g} s at {event['elapsed']:.1f} s of a {budget:g} s budget: "
                               f"{wall:.1f} s from the stop to the end, {finished['elapsed']:.1f} s trained")
    left = budget - event["elapsed"]  # (the budget left when it was stopped)
    assert wall >= pause + left - 1.0, (wall, left)  # (it had ended as soon as it was continued: wall ~ pause)
    assert finished["event"] == "finished" and budget - 0.5 <= finished["elapsed"] < budget + 3.0, finished


def test_the_step_clock_leaves_a_stop_out(monkeypatch):
    """The step in which a SIGCONT came: what lasted beyond the step before counts as stopped,
    and the budgets' clock leaves it out; a step without one counts whole."""
    from neulf_core import clock

    now = [100.0]
    monkeypatch.setattr(clock.time, "monotonic", lambda: now[0])
    monkeypatch.setattr(clock, "_stopped_seconds", [0.0])
    steps = clock.StepClock()
    now[0] += 0.5
    steps.tick()
    now[0] += 60.5  # a step of 0.5 s, and a minute stopped
    clock._continued[0] = True
    steps.tick()
    assert clock.stopped_seconds() == pytest.approx(60.0) and clock.running_time() == pytest.approx(101.0)
    now[0] += 2.0  # a slow step, with no SIGCONT: it counts whole
    steps.tick()
    assert clock.stopped_seconds() == pytest.approx(60.0)


def test_an_eval_stopped_between_its_two_tables_leaves_no_eval_json_of_another_run(model, tiny_scene, tmp_path,
                                                                                   monkeypatch):
    """eval.json is written last, and an older one is removed first: a run stopped between the two
    tables had left a new eval.json beside the eval.csv of an earlier run."""
    import neulf_core.evaluate as evaluate

    out = tmp_path / "eval"
    evaluate.evaluate_model(model, tiny_scene, out_dir=out, views=["view_00"], save_images=False, pixel_samples=1)
    real_write = evaluate.atomic_write_bytes

    def stopped_before_eval_json(path, data):
        if Path(path).name == "eval.json":
            raise KeyboardInterrupt
        real_write(path, data)

    monkeypatch.setattr(evaluate, "atomic_write_bytes", stopped_before_eval_json)
    with pytest.raises(KeyboardInterrupt):
        evaluate.evaluate_model(model, tiny_scene, out_dir=out, views=["view_03"], save_images=False, pixel_samples=1)
    assert not (out / "eval.json").exists() and "view_03" in (out / "eval.csv").read_text()
    monkeypatch.setattr(evaluate, "atomic_write_bytes", real_write)
    evaluate.evaluate_model(model, tiny_scene, out_dir=out, views=["view_03"], save_images=False, pixel_samples=1)
    assert [r["view"] for r in json.loads((out / "eval.json").read_text())["views"]] == ["view_03.png"]


def test_a_camera_edited_with_its_centre_kept_is_said(model, tiny_scene, tmp_path, capfd, record_property):
    """A focal length changed in the scene's model, the camera centres kept: the scene check
    (view names and centres) let --resume and render go on without a word."""
    scene = shutil.copytree(tiny_scene, tmp_path / "scene")
    camera = tiny_camera()
    camera.params = [52.0, 52.0, camera.params[2], camera.params[3]]  # (44 before)
    names = sorted(p.name for p in (scene / "images").iterdir())
    write_colmap_model(scene / "sparse" / "0", camera, tiny_poses(), names)
    resumed = shutil.copytree(model, tmp_path / "model")
    code, out, err = run_cli(["train", scene, "--out", resumed, "--resume", *QUICK_TRAIN[:1], "5", *QUICK_TRAIN[2:]],
                             capfd)
    record_property("message", err.strip())
    assert code == 2 and "have another camera" in err and err.count("\n") == 1, err
    code, out, err = run_cli(["render", model, "--scene", scene, "--views", "view_03", "--out", tmp_path / "r",
                              "--pixel-samples", "1"], capfd)
    assert code == 0 and "have another camera" in err, err
    code, out, err = run_cli(["render", model, "--scene", tiny_scene, "--views", "view_03", "--out", tmp_path / "r2",
                              "--pixel-samples", "1"], capfd)
    assert code == 0 and "another camera" not in err, err


def test_a_model_records_its_scene_folder_whole(tiny_scene, tmp_path, monkeypatch):
    """A scene given as a relative path was recorded as typed; Blender's Load Model, which imports
    that folder, read it from Blender's own working folder."""
    shutil.copytree(tiny_scene, tmp_path / "scene")
    monkeypatch.chdir(tmp_path)
    assert main(["train", "scene", "--out", "model", *QUICK_TRAIN]) == 0
    assert json.loads((tmp_path / "model" / METADATA_NAME).read_text())["scene"]["root"] == str(tmp_path / "scene")


def test_the_cancel_line_names_the_member_that_was_training(tmp_path):
    """members.json lists the members after the first that finished; the first's own progress
    says its.  Cancelled in member 2 it had said 'of member 1 of 2'."""
    from neulf_core.cli import _of_member

    (tmp_path / "members.json").write_text(json.dumps({"count": 2, "seed": 0, "split": "batch", "finished": []}))
    (tmp_path / METADATA_NAME).write_text(json.dumps({"progress": {"status": "finished", "step": 200}}))
    assert _of_member(tmp_path) == " of member 2 of 2"
    (tmp_path / METADATA_NAME).write_text(json.dumps({"progress": {"status": "cancelled", "step": 90}}))
    assert _of_member(tmp_path) == " of member 1 of 2"
    assert _of_member(tmp_path / "none") == ""


def test_blender_import_with_a_model_reads_its_photos(half_size_model):
    """Load Model imports the scene a model trained on: through the photos it trained on (its
    images_2/ here), not the scene's default folder, whose cameras are of another size."""
    from neulf_core.worker import Service

    scene, model = half_size_model
    description = Service().describe_scene(str(scene), model_dir=str(model))
    assert description["images_dir_from_model"].endswith("images_2")
    assert {(v["width"], v["height"]) for v in description["views"]} == {(TINY_WIDTH // 2, TINY_HEIGHT // 2)}
    assert Service().describe_scene(str(scene))["images_dir_from_model"] is None


def _reliability_report():
    import importlib.util

    path = Path(__file__).resolve().parents[1] / "scripts" / "reliability_report.py"
    spec = importlib.util.spec_from_file_location("reliability_report", path)
    report = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = report  # (its dataclasses look their module up)
    spec.loader.exec_module(report)
    return report


def test_the_reliability_report_expands_every_parameter_of_a_test():
    """"test[*]" in docs/RELIABILITY.md's case list stands for each parametrized case pytest
    collects, so a damaged file added to a test's cases joins its row; one with none stays as
    itself, and shows as not found."""
    report = _reliability_report()
    existing = ["a.py::t[1]", "a.py::tt[2]", "a.py::t[x, y]", "a.py::u"]
    assert report.expanded(["a.py::t[*]", "a.py::u"], existing) == ["a.py::t[1]", "a.py::t[x, y]", "a.py::u"]
    assert report.expanded(["a.py::gone[*]"], existing) == ["a.py::gone[*]"]


@pytest.mark.parametrize("text", ['{"format": "layers-model", "modelTopology": {}}', "not json {", "[1, 2]"])
def test_another_programs_model_json_is_not_trained_over(text, tiny_scene, tmp_path, capfd, record_property):
    """A folder holding a model.json that no NeuLF training wrote (a TensorFlow.js model, a
    damaged file): a new training, or a --resume that finds no checkpoint, had replaced it without
    a word (the Blender audit's lost work); it is refused, the file kept."""
    folder = tmp_path / "their_model"
    folder.mkdir()
    (folder / METADATA_NAME).write_text(text)
    for extra in ([], ["--resume"]):
        expect_error(["train", tiny_scene, "--out", folder, "--steps", "2", *extra], capfd, record_property,
                     "model.json that no NeuLF training wrote", "another --out folder")
    assert (folder / METADATA_NAME).read_text() == text and sorted(p.name for p in folder.iterdir()) == [METADATA_NAME]


@pytest.mark.parametrize("preset", ["fast", "auto"])
def test_a_scale_that_leaves_photos_of_a_few_pixels_is_refused(preset, tiny_scene, tmp_path, capfd, record_property):
    """--scale 1e-6 (Blender's Image Scale typed wrong) had trained on 1x1 photos and "finished"
    with a validation PSNR; now one line before anything is written."""
    argv = ["train", tiny_scene, "--out", tmp_path / "model", "--steps", "4", "--scale", "1e-6", "--preset", preset]
    expect_error(argv, capfd, record_property, "photos 1x1 pixels, too small to learn from", "larger --scale")
    code, _, err = run_cli([*argv, "--resume"], capfd)  # (nothing to resume: a new model, said in a warning first)
    assert code == 2 and err.splitlines()[-1].startswith("error: scale 1e-06 makes the 48x36 photos 1x1"), err
    assert not (tmp_path / "model" / CHECKPOINT_NAME).exists()


def test_a_member_started_by_a_resume_trains_on_the_first_members_views(tiny_scene, tmp_path, record_property):
    """A second member that a resume starts (the run stopped before its first checkpoint) took
    the options the resume was given: with --holdout-every 0 it trained on the first member's
    held-out photos, and the ensemble then failed at render ("another light slab").  It now
    trains with the first member's split, scale and preset, and this run's budget."""
    from neulf_core.render import LightField
    from neulf_core.train import TrainConfig, train

    model = tmp_path / "model"
    config = TrainConfig(steps=8, batch_size=256, validate_seconds=1e9, members=2, members_split="steps")
    train(tiny_scene, model, config)
    first = json.loads((model / METADATA_NAME).read_text())["scene"]
    assert first["held_out"], first  # (every 8th view held out)
    # As if stopped before the second member's first checkpoint.
    shutil.rmtree(model / "members" / "2")
    state = json.loads((model / "members.json").read_text())
    (model / "members.json").write_text(json.dumps({**state, "finished": []}))
    events = []
    train(tiny_scene, model, TrainConfig(steps=8, batch_size=256, validate_seconds=1e9, holdout_every=0, scale=0.5),
          resume=True, progress=events.append)
    second = json.loads((model / "members" / "2" / METADATA_NAME).read_text())
    assert second["scene"]["train"] == first["train"] and second["scene"]["held_out"] == first["held_out"], second
    assert second["scene"]["scale"] == first["scale"] and second["slab"] == json.loads(
        (model / METADATA_NAME).read_text())["slab"]
    warning = next(e["message"] for e in events if e["event"] == "warning")
    record_property("message", warning)
    assert "holdout_every (the model's: 8)" in warning, warning
    LightField.load(model)  # (the ensemble of one slab renders)

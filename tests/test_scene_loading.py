"""Loading scenes: COLMAP 4.x binary, legacy text/binary, LLFF poses; finding and rescaling
images; decoding odd photo formats; held-out splits."""

from __future__ import annotations

import os
import re
import shutil
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from PIL import Image

from conftest import look_at_rotation, png_header_only, scene_or_skip, write_colmap_model
from neulf_core.errors import NeulfError
from neulf_core.images import image_size, load_rgb, load_rgb_sizes, resolve_image_paths
from neulf_core.scene import Scene, View, find_model_dir, load_scene, scaled_size, split_views
from neulf_core.slab import fit_slab


def model_views(model_dir: Path) -> dict[str, pycolmap.Image]:
    recon = pycolmap.Reconstruction(str(model_dir))
    return recon, {image.name: image for image in recon.images.values()}


def assert_views_match_model(scene: Scene, model_dir: Path):
    recon, images = model_views(model_dir)
    assert [v.name for v in scene.views] == sorted(images)
    for view in scene.views:
        matrix = np.asarray(images[view.name].cam_from_world().matrix())
        np.testing.assert_allclose(view.R, matrix[:, :3], atol=1e-12)
        np.testing.assert_allclose(view.t, matrix[:, 3], atol=1e-12)
        np.testing.assert_allclose(view.center, images[view.name].projection_center(), atol=1e-9)
        np.testing.assert_allclose(view.forward, images[view.name].viewing_direction(), atol=1e-9)
    assert len(scene.points) == recon.num_points3D()


# ----------------------------------------------------------------------------- the reference scenes


def test_canclip_colmap4_binary(shared_data):
    root = scene_or_skip(shared_data, "canclip")
    scene = load_scene(root)
    assert scene.kind == "colmap" and scene.notes == [] and scene.depth_bounds is None
    assert len(scene.views) == 30
    assert_views_match_model(scene, root / "sparse" / "0")
    for view in scene.views:
        assert view.size == (960, 540)
        assert view.camera.model_name == "SIMPLE_RADIAL"
        assert view.camera.params[3] == pytest.approx(-0.18, abs=0.01)
        assert view.image_path == root / "images" / view.name
    assert scene.views[0].load_image().shape == (540, 960, 3)
    assert scene.views[0].load_image(0.25).shape == (135, 240, 3)
    assert scene.views[0].scaled_camera(0.25).width == 240
    fingerprint = scene.fingerprint()
    assert len(fingerprint) == 16 and fingerprint == load_scene(root).fingerprint()
    assert scene.view("img003").name == "img003.png" and scene.view("img003.png") is scene.view("img003")
    with pytest.raises(NeulfError, match="no view named 'nope'"):
        scene.view("nope")


def test_hci_text_model_81_views(shared_data):
    root = scene_or_skip(shared_data, "hci_antinous")
    scene = load_scene(root)
    assert len(scene.views) == 81
    assert_views_match_model(scene, root / "sparse" / "0")
    centres = np.stack([v.center for v in scene.views])
    for index, view in enumerate(scene.views):
        row, col = divmod(index, 9)
        assert view.name == f"input_Cam{index:03d}.png"
        assert view.camera.model_name == "PINHOLE" and view.size == (512, 512)
        fx, fy, cx, cy = view.camera.params
        assert fx == pytest.approx(1462.86) and fy == pytest.approx(1462.86)
        assert (cx, cy) == pytest.approx((256 + 8 * (col - 4), 256 + 8 * (row - 4)))
        np.testing.assert_allclose(view.R, np.eye(3), atol=1e-12)  # parallel optical axes
        np.testing.assert_allclose(centres[index], [0.01 * (col - 4), 0.01 * (row - 4), 0.0], atol=1e-12)


def test_statue_portrait(shared_data):
    root = scene_or_skip(shared_data, "statue")
    scene = load_scene(root)
    assert len(scene.views) == 27
    assert {v.size for v in scene.views} == {(540, 960)}
    assert scene.views[0].load_image().shape == (960, 540, 3)
    assert_views_match_model(scene, root / "sparse" / "0")


def test_fern_images_8_sorted_order_and_rescaled_intrinsics(shared_data):
    root = scene_or_skip(shared_data, "fern")
    recon, _ = model_views(root / "sparse" / "0")
    original = next(iter(recon.cameras.values()))
    assert (original.width, original.height) == (4032, 3024)
    scene = load_scene(root)  # images_8 is the default (images/ is absent)
    assert len(scene.views) == 20
    assert any("4032x3024" in note and "504x378" in note for note in scene.notes)
    files = sorted((root / "images_8").glob("*.png"))
    assert [v.image_path for v in scene.views] == files  # IMG_4026.JPG -> image000.png, ...
    assert scene.views[0].name == "IMG_4026.JPG" and scene.views[0].image_path.name == "image000.png"
    f, cx, cy, k = original.params
    for view in scene.views:
        assert view.size == (504, 378)
        params = view.camera.params
        assert params[0] == pytest.approx(f / 8, rel=1e-12)
        assert (params[1], params[2]) == pytest.approx((cx / 8, cy / 8), rel=1e-12)
        assert (params[1], params[2]) == pytest.approx((252.0, 189.0))
        assert params[3] == pytest.approx(k)  # the distortion is in normalised coordinates: unchanged
    # The model's own camera is left untouched (views got copies).
    assert recon.cameras[original.camera_id].width == 4032
    assert_views_match_model(scene, root / "sparse" / "0")
    assert scene.views[0].load_image().shape == (378, 504, 3)


def test_fern_images_16_by_stem(shared_data):
    root = scene_or_skip(shared_data, "fern")
    scene = load_scene(root, images_dir=root / "images_16")
    f = next(iter(pycolmap.Reconstruction(str(root / "sparse" / "0")).cameras.values())).params[0]
    for view in scene.views:
        assert view.image_path == root / "images_16" / (view.stem + ".png")
        assert view.size == (252, 189)
        assert view.camera.params[0] == pytest.approx(f / 16, rel=1e-12)
        assert tuple(view.camera.params[1:3]) == pytest.approx((126.0, 94.5))


def umeyama(source: np.ndarray, target: np.ndarray):
    """Similarity (s, Q, T) minimising |s Q source + T - target|."""
    mu_s, mu_t = source.mean(0), target.mean(0)
    xs, xt = source - mu_s, target - mu_t
    U, S, Vt = np.linalg.svd(xt.T @ xs / len(source))
    D = np.eye(3)
    D[2, 2] = np.sign(np.linalg.det(U @ Vt))
    Q = U @ D @ Vt
    s = np.trace(np.diag(S) @ D) / ((xs ** 2).sum() / len(source))
    return s, Q, mu_t - s * Q @ mu_s


def test_llff_poses_bounds_agree_with_colmap(shared_data, tmp_path):
    root = scene_or_skip(shared_data, "canclip")
    llff = tmp_path / "canclip_llff"
    (llff / "images").mkdir(parents=True)
    shutil.copy(root / "poses_bounds.npy", llff)
    for path in sorted((root / "images").iterdir()):
        os.symlink(path, llff / "images" / path.name)
    scene = load_scene(llff)
    reference = load_scene(root)
    assert scene.kind == "llff" and len(scene.views) == 30 and len(scene.points) == 0
    assert scene.depth_bounds.shape == (30, 2) and np.all(scene.depth_bounds[:, 0] < scene.depth_bounds[:, 1])
    assert [v.name for v in scene.views] == [v.name for v in reference.views]
    for view in scene.views:
        assert view.camera.model_name == "PINHOLE" and view.size == (960, 540)
        assert tuple(view.camera.params[2:]) == pytest.approx((480.0, 270.0))
        np.testing.assert_allclose(view.R @ view.R.T, np.eye(3), atol=1e-6)
        assert np.linalg.det(view.R) == pytest.approx(1.0, abs=1e-6)
    # Same capture: the camera centres agree up to a similarity transform ...
    llff_centres = np.stack([v.center for v in scene.views])
    colmap_centres = np.stack([v.center for v in reference.views])
    s, Q, T = umeyama(colmap_centres, llff_centres)
    residual = np.linalg.norm(s * colmap_centres @ Q.T + T - llff_centres, axis=1)
    baseline = np.linalg.norm(llff_centres - llff_centres.mean(0), axis=1).mean()
    assert residual.max() < 0.05 * baseline, (residual.max(), baseline)
    # ... and so do the orientations (the LLFF axis convention was converted correctly).
    for a, b in zip(scene.views, reference.views):
        relative = a.R.T @ (b.R @ Q.T)
        angle = np.degrees(np.arccos(np.clip((np.trace(relative) - 1) / 2, -1, 1)))
        assert angle < 2.0, f"{a.name}: orientation differs by {angle:.2f} degrees"
    # The focal length agrees with COLMAP's within a few percent.
    assert scene.views[0].camera.params[0] == pytest.approx(reference.views[0].camera.params[0], rel=0.05)


def test_llff_image_count_mismatch(shared_data, tmp_path):
    root = scene_or_skip(shared_data, "canclip")
    llff = tmp_path / "llff"
    (llff / "images").mkdir(parents=True)
    shutil.copy(root / "poses_bounds.npy", llff)
    for path in sorted((root / "images").iterdir())[:5]:
        os.symlink(path, llff / "images" / path.name)
    with pytest.raises(NeulfError, match="5 images but poses_bounds.npy has 30 poses"):
        load_scene(llff)


@pytest.mark.parametrize("fmt", ["legacy_text", "legacy_binary", "text"])
def test_models_written_by_pycolmap_load_identically(shared_data, tmp_path, fmt):
    root = scene_or_skip(shared_data, "canclip")
    recon = pycolmap.Reconstruction(str(root / "sparse" / "0"))
    scene_dir = tmp_path / fmt
    model_dir = scene_dir / "sparse" / "0"
    model_dir.mkdir(parents=True)
    if fmt.endswith("text"):
        recon.write_text(str(model_dir))
    else:
        recon.write_binary(str(model_dir))
    if fmt.startswith("legacy"):
        for name in ("rigs", "frames"):
            for ext in ("bin", "txt"):
                (model_dir / f"{name}.{ext}").unlink(missing_ok=True)
        assert sorted(p.stem for p in model_dir.iterdir()) == ["cameras", "images", "points3D"]
    os.symlink(root / "images", scene_dir / "images")
    loaded = load_scene(scene_dir)
    reference = load_scene(root)
    assert [v.name for v in loaded.views] == [v.name for v in reference.views]
    for a, b in zip(loaded.views, reference.views):
        assert a.camera.model_name == b.camera.model_name and a.size == b.size
        np.testing.assert_allclose(a.camera.params, b.camera.params, rtol=1e-12)
        np.testing.assert_allclose(a.R, b.R, atol=1e-12)
        np.testing.assert_allclose(a.t, b.t, atol=1e-9)
    np.testing.assert_allclose(np.sort(loaded.points, axis=0), np.sort(reference.points, axis=0), atol=1e-9)
    assert loaded.fingerprint() == reference.fingerprint()


# ----------------------------------------------------------------------------- finding the model


def test_model_folder_locations(tmp_path, tiny_scene):
    for layout in ("sparse", "flat", "sparse/1"):
        scene_dir = tmp_path / layout.replace("/", "_")
        target = {"sparse": scene_dir / "sparse", "flat": scene_dir, "sparse/1": scene_dir / "sparse" / "1"}[layout]
        shutil.copytree(tiny_scene / "sparse" / "0", target, dirs_exist_ok=True)
        shutil.copytree(tiny_scene / "images", scene_dir / "images")
        assert find_model_dir(scene_dir) == target
        assert len(load_scene(scene_dir).views) == 9


def test_scene_folder_errors(tmp_path, tiny_scene):
    with pytest.raises(NeulfError, match="does not exist"):
        load_scene(tmp_path / "missing")
    (tmp_path / "file.txt").write_text("x")
    with pytest.raises(NeulfError, match="not a folder"):
        load_scene(tmp_path / "file.txt")
    (tmp_path / "empty").mkdir()
    with pytest.raises(NeulfError, match="no camera model"):
        load_scene(tmp_path / "empty")
    with pytest.raises(NeulfError, match="images folder .* does not exist"):
        load_scene(tiny_scene, images_dir=tmp_path / "nowhere")
    with pytest.raises(NeulfError, match="view_00.png is a file, not a folder"):
        load_scene(tiny_scene, images_dir=tiny_scene / "images" / "view_00.png")
    with pytest.raises(NeulfError, match="is the COLMAP model's folder: give the scene folder above it"):
        load_scene(tiny_scene / "sparse")  # (it read "no camera model" and proposed reconstructing into it)
    no_images = tmp_path / "no_images"
    shutil.copytree(tiny_scene / "sparse", no_images / "sparse")
    with pytest.raises(NeulfError, match="no images folder"):
        load_scene(no_images)
    incomplete = tmp_path / "incomplete"
    shutil.copytree(tiny_scene, incomplete)
    (incomplete / "sparse" / "0" / "images.bin").unlink()
    with pytest.raises(NeulfError, match="images file missing"):
        load_scene(incomplete)


# ----------------------------------------------------------------------------- image lookup and rescaling


NAMES = ["b_view.jpg", "a_view.jpg", "c_view.jpg"]


def lookup_scene(folder: Path, camera=None) -> Path:
    """A three-view model naming NAMES, with an empty images/ folder to fill."""
    camera = camera or pycolmap.Camera(model="SIMPLE_RADIAL", width=48, height=36, params=[40.0, 24.0, 18.0, -0.05])
    poses = []
    for i in range(len(NAMES)):
        centre = np.array([0.1 * i, 0.0, 0.0])
        R = look_at_rotation(centre, np.array([0.0, 0.0, 3.0]))
        poses.append((R, -R @ centre))
    points = np.column_stack([np.random.default_rng(0).uniform(-1, 1, (20, 2)), np.full(20, 3.0)])
    write_colmap_model(folder / "sparse" / "0", camera, poses, NAMES, points)
    (folder / "images").mkdir(parents=True, exist_ok=True)
    return folder


def write_image(path: Path, size, value=0):
    path.parent.mkdir(parents=True, exist_ok=True)
    rgb = np.full((size[1], size[0], 3), value, np.uint8)
    rgb[..., 0] = np.arange(size[0], dtype=np.uint8)[None, :] * 3
    Image.fromarray(rgb).save(path)


def test_exact_names(tmp_path):
    folder = lookup_scene(tmp_path)
    for i, name in enumerate(NAMES):
        write_image(folder / "images" / name, (48, 36), value=10 * i)
    scene = load_scene(folder)
    assert [v.name for v in scene.views] == sorted(NAMES)
    assert all(v.image_path == folder / "images" / v.name for v in scene.views)
    assert scene.notes == []
    assert scene.view("b_view").load_image()[0, 0, 1] == 0


def test_same_stem_other_extension(tmp_path):
    folder = lookup_scene(tmp_path)
    for name in NAMES:
        write_image(folder / "images" / (Path(name).stem + ".PNG"), (48, 36))
    write_image(folder / "images" / "unrelated.png", (48, 36))
    scene = load_scene(folder)
    assert [v.image_path.name for v in scene.views] == ["a_view.PNG", "b_view.PNG", "c_view.PNG"]


def test_sorted_order_pairing(tmp_path):
    folder = lookup_scene(tmp_path)
    for i in range(3):  # LLFF-style copies: numbered in the sorted order of the originals
        write_image(folder / "images" / f"image{i:03d}.png", (48, 36), value=50 * i)
    scene = load_scene(folder)
    assert [(v.name, v.image_path.name) for v in scene.views] == [
        ("a_view.jpg", "image000.png"), ("b_view.jpg", "image001.png"), ("c_view.jpg", "image002.png")]
    assert scene.view("c_view").load_image()[0, 0, 1] == 100


def test_missing_images_are_counted(tmp_path):
    folder = lookup_scene(tmp_path)
    write_image(folder / "images" / "a_view.jpg", (48, 36))
    with pytest.raises(NeulfError) as info:
        load_scene(folder)
    message = str(info.value)
    assert "2 of 3 images" in message and "b_view.jpg" in message and "c_view.jpg" in message
    # Too many unrelated images for sorted pairing: all three are missing.
    for i in range(4):
        write_image(tmp_path / "other" / f"x{i}.png", (48, 36))
    with pytest.raises(NeulfError, match="3 of 3 images"):
        load_scene(folder, images_dir=tmp_path / "other")
    found = resolve_image_paths(tmp_path / "other", NAMES)
    assert found == {name: None for name in NAMES}


def test_another_aspect_ratio_is_rejected(tmp_path):
    folder = lookup_scene(tmp_path)
    for name in NAMES:
        write_image(folder / "images" / name, (36, 48))  # rotated
    with pytest.raises(NeulfError, match="aspect ratio"):
        load_scene(folder)


def test_smaller_copies_rescale_the_intrinsics(tmp_path):
    folder = lookup_scene(tmp_path)
    for name in NAMES:
        write_image(folder / "images" / name, (24, 18))
    scene = load_scene(folder)
    assert any("48x36" in note and "24x18" in note for note in scene.notes)
    recon = pycolmap.Reconstruction(str(folder / "sparse" / "0"))
    original = next(iter(recon.cameras.values()))
    rng = np.random.default_rng(1)
    points = np.column_stack([rng.uniform(-0.3, 0.3, (50, 2)), rng.uniform(1, 4, 50)])
    for view in scene.views:
        assert view.size == (24, 18)
        # The same 3D point lands on the same place in the picture: pixel coordinates halve.
        full = np.asarray(original.img_from_cam(points))
        small = np.asarray(view.camera.img_from_cam(points))
        np.testing.assert_allclose(small, full * 0.5, atol=1e-9)
        assert view.load_image().shape == (18, 24, 3)
        # Loading at a scale rescales again, consistently.
        half = view.scaled_camera(0.5)
        assert (half.width, half.height) == (12, 9)
        np.testing.assert_allclose(np.asarray(half.img_from_cam(points)), full * 0.25, atol=1e-9)


def test_model_cameras_at_a_shared_camera_are_rescaled_per_view(tmp_path):
    """Two views share one camera but their files differ in size: each view gets its own."""
    folder = lookup_scene(tmp_path)
    write_image(folder / "images" / NAMES[0], (24, 18))
    write_image(folder / "images" / NAMES[1], (48, 36))
    write_image(folder / "images" / NAMES[2], (96, 72))
    scene = load_scene(folder)
    assert {v.name: v.size for v in scene.views} == {"b_view.jpg": (24, 18), "a_view.jpg": (48, 36), "c_view.jpg": (96, 72)}
    assert scene.view("c_view").camera.params[0] == pytest.approx(80.0)
    assert scene.view("b_view").camera.params[0] == pytest.approx(20.0)


# ----------------------------------------------------------------------------- decoding photos


def test_load_rgb_grayscale(tmp_path):
    gray = np.arange(20 * 10, dtype=np.uint8).reshape(10, 20)
    Image.fromarray(gray, mode="L").save(tmp_path / "g.png")
    rgb = load_rgb(tmp_path / "g.png")
    assert rgb.shape == (10, 20, 3) and rgb.dtype == np.uint8
    for c in range(3):
        np.testing.assert_array_equal(rgb[..., c], gray)


def test_load_rgb_rgba_composites_on_black(tmp_path):
    rgba = np.zeros((4, 5, 4), np.uint8)
    rgba[..., 0] = 200
    rgba[..., 1] = 100
    rgba[..., 3] = 255
    rgba[0, 0, 3] = 0
    rgba[1, 1, 3] = 128
    Image.fromarray(rgba, mode="RGBA").save(tmp_path / "a.png")
    rgb = load_rgb(tmp_path / "a.png")
    assert rgb.shape == (4, 5, 3)
    np.testing.assert_array_equal(rgb[0, 0], [0, 0, 0])
    np.testing.assert_array_equal(rgb[2, 2], [200, 100, 0])
    np.testing.assert_allclose(rgb[1, 1].astype(int), [100, 50, 0], atol=1)


def test_load_rgb_palette(tmp_path):
    rgb = np.zeros((6, 8, 3), np.uint8)
    rgb[:, :4] = [255, 0, 0]
    rgb[:, 4:] = [0, 0, 255]
    image = Image.fromarray(rgb).convert("P", palette=Image.ADAPTIVE, colors=4)
    image.save(tmp_path / "p.png")
    assert Image.open(tmp_path / "p.png").mode == "P"
    np.testing.assert_array_equal(load_rgb(tmp_path / "p.png"), rgb)
    # A palette with a transparent entry: that colour becomes black.
    image.info["transparency"] = image.getpixel((0, 0))
    image.save(tmp_path / "pt.png", transparency=image.getpixel((0, 0)))
    loaded = load_rgb(tmp_path / "pt.png")
    np.testing.assert_array_equal(loaded[:, :4], 0)
    np.testing.assert_array_equal(loaded[:, 4:], np.broadcast_to([0, 0, 255], (6, 4, 3)))


def test_load_rgb_16_bit_is_scaled_not_clipped(tmp_path):
    values = np.array([[0, 257, 1000, 32768, 65535]], dtype=np.uint16)
    Image.fromarray(values).save(tmp_path / "sixteen.png")
    assert Image.open(tmp_path / "sixteen.png").mode.startswith("I")
    rgb = load_rgb(tmp_path / "sixteen.png")
    assert rgb.shape == (1, 5, 3)
    np.testing.assert_array_equal(rgb[0, :, 0], np.round(values[0] / 65535 * 255).astype(np.uint8))
    np.testing.assert_array_equal(rgb[0, :, 0], [0, 1, 4, 128, 255])
    # A dark 16-bit photo (all values below 256) is still 16-bit: not brightened 257-fold.
    dark = np.array([[0, 100, 200, 255]], dtype=np.uint16)
    Image.fromarray(dark).save(tmp_path / "dark16.png")
    np.testing.assert_array_equal(load_rgb(tmp_path / "dark16.png")[0, :, 0], [0, 0, 1, 1])


def test_exif_rotated_jpeg(tmp_path):
    stored = np.full((20, 40, 3), 255, np.uint8)  # stored landscape 40x20 ...
    stored[:6, :6] = [255, 0, 0]                   # red block at the stored top-left
    image = Image.fromarray(stored)
    exif = image.getexif()
    exif[0x0112] = 6                               # ... displayed rotated 90 degrees clockwise
    image.save(tmp_path / "rotated.jpg", exif=exif.tobytes(), quality=95)
    assert image_size(tmp_path / "rotated.jpg") == (20, 40)
    rgb = load_rgb(tmp_path / "rotated.jpg")
    assert rgb.shape == (40, 20, 3)
    assert rgb[2, 17, 0] > 200 and rgb[2, 17, 1] < 60   # top-left goes to the top-right corner
    assert rgb[2, 2].min() > 200                         # the displayed top-left is white
    resized = load_rgb(tmp_path / "rotated.jpg", (10, 20))
    assert resized.shape == (20, 10, 3)


def test_photos_past_pillows_bomb_limit_are_read_up_to_400_mp(tmp_path, monkeypatch):
    """Pillow refuses more than 179 MP with a traceback (DecompressionBombError); real photos go
    to 400 MP (pixel-shift stills), so those are read and only more is refused, naming the photo.
    Pillow's own limit is left as it was for everyone else."""
    limit = Image.MAX_IMAGE_PIXELS
    large, bomb = tmp_path / "large.jpg", tmp_path / "bomb.png"
    Image.new("RGB", (48, 36)).save(large)
    jpeg = bytearray(large.read_bytes())
    frame = jpeg.index(b"\xff\xc0")  # baseline frame header: length, precision, height, width
    jpeg[frame + 5:frame + 9] = (15000).to_bytes(2, "big") + (20000).to_bytes(2, "big")
    large.write_bytes(bytes(jpeg))  # claims 300 MP; image_size reads the header alone
    bomb.write_bytes(png_header_only(40000, 30000))
    assert image_size(large) == (20000, 15000)
    with pytest.raises(NeulfError, match=r"bomb.png claims 40000x30000 pixels \(1200 MP\).*downscale it"):
        image_size(bomb)
    with pytest.raises(NeulfError, match=r"bomb.png claims 40000x30000 pixels"):
        load_rgb(bomb)
    assert Image.MAX_IMAGE_PIXELS == limit


def test_unreadable_image(tmp_path):
    bad = tmp_path / "broken.png"
    bad.write_bytes(b"\x89PNG\r\n\x1a\n" + os.urandom(64))
    with pytest.raises(NeulfError, match="cannot read image"):
        load_rgb(bad)
    with pytest.raises(NeulfError, match="cannot read image"):
        image_size(bad)
    (tmp_path / "text.jpg").write_text("not a photo")
    with pytest.raises(NeulfError, match="cannot read image"):
        load_rgb(tmp_path / "text.jpg")


def test_one_decode_gives_each_size_as_its_own_read_would(tmp_path):
    rng = np.random.default_rng(0)
    Image.fromarray(rng.integers(0, 256, (36, 48, 3), dtype=np.uint8)).save(tmp_path / "p.jpg", quality=90)
    sizes = [(24, 18), (12, 9), None, (96, 72)]
    for got, size in zip(load_rgb_sizes(tmp_path / "p.jpg", sizes), sizes):
        np.testing.assert_array_equal(got, load_rgb(tmp_path / "p.jpg", size))


def test_load_rgb_resizes_with_box_filter(tmp_path):
    rgb = np.zeros((4, 4, 3), np.uint8)
    rgb[::2, ::2] = 200  # one bright pixel per 2x2 block
    Image.fromarray(rgb).save(tmp_path / "c.png")
    small = load_rgb(tmp_path / "c.png", (2, 2))
    np.testing.assert_array_equal(small, np.full((2, 2, 3), 50, np.uint8))


def test_saved_renders_round_to_the_nearest_level(tmp_path):
    """A render's float colours are written rounded, not truncated (which darkens every pixel by half a level)."""
    from neulf_core.images import save_rgb, to_uint8

    levels = np.array([0.0, 0.4, 0.5, 0.6, 100.6, 254.51, 255.0]) / 255.0
    rgb = np.repeat(levels[None, :, None], 3, axis=2)
    expected = np.array([0, 0, 0, 1, 101, 255, 255])
    np.testing.assert_array_equal(to_uint8(rgb)[0, :, 0], expected)
    save_rgb(tmp_path / "r.png", rgb)
    np.testing.assert_array_equal(load_rgb(tmp_path / "r.png")[0, :, 0], expected)


# ----------------------------------------------------------------------------- held-out split


def named_scene(count: int) -> Scene:
    camera = pycolmap.Camera(model="PINHOLE", width=8, height=6, params=[8.0, 8.0, 4.0, 3.0])
    views = [View(f"v{i:02d}.png", camera, np.eye(3), np.array([-0.1 * i, 0.0, 0.0])) for i in range(count)]
    return Scene(Path("x"), views, np.zeros((0, 3)), "colmap")


def test_split_every_eighth_from_the_first():
    scene = named_scene(20)
    train, held = split_views(scene)
    assert [v.name for v in held] == ["v00.png", "v08.png", "v16.png"]
    assert len(train) == 17 and not set(v.name for v in train) & set(v.name for v in held)
    train, held = split_views(scene, holdout_every=5)
    assert [v.name for v in held] == ["v00.png", "v05.png", "v10.png", "v15.png"]


def test_split_exclude_and_none():
    scene = named_scene(10)
    train, held = split_views(scene, exclude=["v03", "v07.png"])
    assert [v.name for v in held] == ["v03.png", "v07.png"] and len(train) == 8
    train, held = split_views(scene, holdout_every=0)
    assert held == [] and len(train) == 10
    with pytest.raises(NeulfError, match="no view named 'v99'"):
        split_views(scene, exclude=["v99"])
    with pytest.raises(NeulfError, match="training views remain"):
        split_views(named_scene(3), exclude=["v00", "v01"])
    with pytest.raises(NeulfError, match="training views remain"):
        split_views(named_scene(2), holdout_every=1)


# ----------------------------------------------------------------------------- damaged poses and scales


def llff_scene(folder: Path, count: int = 4, columns: int = 17) -> Path:
    """A small LLFF scene: `count` 48x36 photos and their poses_bounds.npy (rows of a 3x5
    [down, right, backwards, centre, (h, w, f)] matrix, then near and far when columns is 17)."""
    rows = []
    for i in range(count):
        centre = np.array([0.1 * i, 0.05 * (i % 2), 0.0])
        R = look_at_rotation(centre, np.array([0.0, 0.0, 3.0]))
        right, down, forward = R  # the rows of world-to-camera are the camera axes in the world
        pose = np.column_stack([down, right, -forward, centre, [36.0, 48.0, 40.0]])
        rows.append(np.concatenate([pose.ravel(), [2.0, 5.0]])[:columns])
        write_image(folder / "images" / f"img{i:03d}.png", (48, 36), value=20 * i)
    np.save(folder / "poses_bounds.npy", np.array(rows))
    return folder


def damage_llff(folder: Path, change) -> None:
    data = np.load(folder / "poses_bounds.npy")
    change(data)
    np.save(folder / "poses_bounds.npy", data)


def test_llff_poses_are_read_in_colmap_convention(tmp_path):
    scene = load_scene(llff_scene(tmp_path))
    assert scene.kind == "llff" and len(scene.views) == 4 and scene.depth_bounds.shape == (4, 2)
    for i, view in enumerate(scene.views):
        centre = np.array([0.1 * i, 0.05 * (i % 2), 0.0])
        np.testing.assert_allclose(view.center, centre, atol=1e-12)
        np.testing.assert_allclose(view.R, look_at_rotation(centre, np.array([0.0, 0.0, 3.0])), atol=1e-12)
        # (h, w, f) = (36, 48, 40): a pinhole with its principal point at the image's centre
        assert view.size == (48, 36) and view.camera.model_name == "PINHOLE"
        np.testing.assert_allclose(view.camera.params, [40.0, 40.0, 24.0, 18.0])


def test_the_full_resolution_most_llff_copies_are_read(tmp_path):
    """No images/: of LLFF's images_2/ and images_8/ the larger photos are read (images_8's intrinsics scale)."""
    folder = llff_scene(tmp_path)
    (folder / "images").rename(folder / "images_2")
    for i in range(4):
        write_image(folder / "images_8" / f"img{i:03d}.png", (12, 9), value=20 * i)
    scene = load_scene(folder)
    assert scene.images_dir == folder / "images_2"
    assert all(view.size == (48, 36) for view in scene.views)
    np.testing.assert_allclose(scene.views[0].camera.params, [40.0, 40.0, 24.0, 18.0])
    assert load_scene(folder, folder / "images_8").views[0].camera.params[0] == pytest.approx(10.0)


@pytest.mark.parametrize("change, message", [
    (lambda a: a.__setitem__((2, 4), np.nan), r"row 2 .*height, width and focal length as nan, 48, 40"),
    (lambda a: a.__setitem__((1, 14), 0.0), r"row 1 .*height, width and focal length as 36, 48, 0"),
    (lambda a: a.__setitem__((3, 3), np.nan), r"row 3 .*rotation or centre that is not finite"),
    (lambda a: a.__setitem__((0, 8), np.inf), r"row 0 .*rotation or centre that is not finite"),
    (lambda a: a.__setitem__((1, 0), 3.0), r"row 1 .*not a rotation"),
    # A finite centre past float32, or a billion units off a rig 0.1 wide: training had run on NaN rays.
    (lambda a: a.__setitem__((2, 3), 1e300), r"img002.png's camera at \(1e\+300, .*absurdly far.*regenerate poses_bounds"),
    (lambda a: a.__setitem__((2, 3), 1e9), r"img002.png's camera at \(1e\+09, .*absurdly far.*regenerate poses_bounds"),
], ids=["nan height", "zero focal", "nan centre", "inf rotation", "not a rotation", "centre 1e300", "centre 1e9 off"])
def test_damaged_llff_rows_are_named(tmp_path, change, message):
    folder = llff_scene(tmp_path)
    damage_llff(folder, change)
    with pytest.raises(NeulfError, match=message):
        load_scene(folder)


@pytest.mark.parametrize("change, said", [
    (lambda a: a.__setitem__((2, 16), np.nan), r"1 of its 4 rows \(row 2 \(2, nan\)"),
    (lambda a: a.__setitem__((2, 15), 6.0), r"1 of its 4 rows \(row 2 \(6, 5\)"),
    (lambda a: a.__setitem__((2, 15), -1.0), r"1 of its 4 rows \(row 2 \(-1, 5\)"),
], ids=["nan far", "near past far", "negative near"])
def test_one_llff_row_of_unusable_bounds_is_left_out(tmp_path, change, said):
    """A row whose near/far are unusable no longer refuses the whole file (the poses are
    fine): the depth range comes from the other rows, and the scene's notes say which row."""
    folder = llff_scene(tmp_path)
    data = np.load(folder / "poses_bounds.npy")
    data[1, 15:17] = [1.5, 7.0]  # the widest range, in a usable row
    np.save(folder / "poses_bounds.npy", data)
    damage_llff(folder, change)
    scene = load_scene(folder)
    assert len(scene.views) == 4 and np.isnan(scene.depth_bounds[2]).all()
    assert any(re.search(said, note) and "other rows" in note for note in scene.notes), scene.notes
    slab = fit_slab(scene, scene.views)
    assert (slab.z_near, slab.z_far) == pytest.approx((0.9 * 1.5, 1.1 * 7.0))  # (the slab's 10 % margins)


def test_llff_bounds_unusable_in_every_row_need_the_depths_given(tmp_path):
    folder = llff_scene(tmp_path)
    damage_llff(folder, lambda a: a.__setitem__((slice(None), 15), -1.0))
    scene = load_scene(folder)
    assert scene.depth_bounds is None and [n for n in scene.notes if "--near" in n and "in 4 of its 4 rows" in n]
    with pytest.raises(NeulfError, match="no usable near/far depths"):
        fit_slab(scene, scene.views)
    slab = fit_slab(scene, scene.views, st_depth=3.0, near=2.0, far=5.0)  # as the message says
    assert (slab.z_near, slab.z_far) == pytest.approx((0.9 * 2.0, 1.1 * 5.0))


@pytest.mark.parametrize("array", [np.zeros((4, 16)), np.zeros(17), np.zeros((0, 17)), np.array([["a"] * 17] * 4)],
                         ids=["16 columns", "one dimension", "no rows", "text"])
def test_llff_arrays_of_another_shape_are_refused(tmp_path, array):
    folder = llff_scene(tmp_path)
    np.save(folder / "poses_bounds.npy", array)
    with pytest.raises(NeulfError, match=r"poses_bounds.npy is an \(N, 17\) array"):
        load_scene(folder)


def test_llff_poses_without_bounds_load_without_depths(tmp_path):
    """An (N, 15) file (poses, no near/far) loads; the slab then needs the depths given
    (test_geometry: test_llff_scene_without_bounds_needs_the_depths_given)."""
    scene = load_scene(llff_scene(tmp_path, columns=15))
    assert scene.kind == "llff" and len(scene.views) == 4 and scene.depth_bounds is None


@pytest.mark.parametrize("damage, message", [
    ("pose", r"image c_view.jpg a pose that is not finite"),
    ("nan focal", r"unusable camera 1 \(SIMPLE_RADIAL, 48x36, params nan"),
    ("negative focal", r"unusable camera 1 \(SIMPLE_RADIAL, 48x36, params -40"),
], ids=["pose", "nan focal", "negative focal"])
def test_colmap_models_with_non_finite_poses_or_intrinsics_are_refused(tmp_path, damage, message):
    camera = None
    if damage != "pose":
        focal = np.nan if damage == "nan focal" else -40.0
        camera = pycolmap.Camera(model="SIMPLE_RADIAL", width=48, height=36, params=[focal, 24.0, 18.0, -0.05])
    folder = lookup_scene(tmp_path, camera)
    for name in NAMES:
        write_image(folder / "images" / name, (48, 36))
    if damage == "pose":
        recon = pycolmap.Reconstruction(str(folder / "sparse" / "0"))
        image = next(im for im in recon.images.values() if im.name == "c_view.jpg")
        R = np.asarray(image.cam_from_world().matrix())[:, :3]
        recon.frames[image.frame_id].rig_from_world = pycolmap.Rigid3d(np.column_stack([R, [np.nan, 0.0, 0.0]]))
        recon.write_binary(str(folder / "sparse" / "0"))
    with pytest.raises(NeulfError, match=message):
        load_scene(folder)


@pytest.mark.parametrize("scale", [float("nan"), float("inf"), -float("inf"), 0.0, -0.5, "half"])
def test_scales_that_are_not_finite_and_positive_are_refused(tmp_path, scale):
    folder = lookup_scene(tmp_path)
    for name in NAMES:
        write_image(folder / "images" / name, (48, 36))
    view = load_scene(folder).views[0]
    with pytest.raises(NeulfError, match="image scale"):
        scaled_size(view.size, scale)
    with pytest.raises(NeulfError, match="image scale"):
        view.scaled_camera(scale)
    with pytest.raises(NeulfError, match="image scale"):
        view.load_image(scale)
    assert scaled_size(view.size, 0.5) == (24, 18) and scaled_size(view.size, np.float32(2.0)) == (96, 72)
    # Rounded, not cut: 1/8 of LLFF's 4032x3024 is 504x378, 1/3 of 1000x563 is 333x188 (188 from
    # 187.67: what LLFF's own images_N and every other reader of the scale give)
    assert scaled_size((4032, 3024), 1 / 8) == (504, 378) and scaled_size((1000, 563), 1 / 3) == (333, 188)


def test_photos_renamed_are_not_paired_by_their_order(tmp_path):
    """Photos renamed after the reconstruction ('canclip (1).png' ... from a file manager) sort
    otherwise than the model's names: paired in sorted order, most views had had another
    view's photo without a word (CanClip scored 19.6 dB instead of 33.8).  Only LLFF's
    numbered copies are paired by order; anything else is refused, with the likely cause."""
    folder = lookup_scene(tmp_path)
    for i, name in enumerate(("renamed (10).png", "renamed (2).png", "renamed (1).png")):
        write_image(folder / "images" / name, (48, 36), value=50 * i)
    with pytest.raises(NeulfError, match=r"3 of 3 images .*photos renamed since the reconstruction"):
        load_scene(folder)

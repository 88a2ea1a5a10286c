"""Tests for neulf_core.reconstruct on a synthetic forward-facing capture (CPU, no bpy).

The capture is rendered here with numpy: two textured planes at different depths (so the
views are not related by a single homography) seen by 8 pinhole cameras on a 4x2 grid that
all look at one point, like a handheld forward-facing light-field capture.
"""

from pathlib import Path

import numpy as np
import pytest
from PIL import Image

import pycolmap

from neulf_core import reconstruct as reconstruct_module
from neulf_core.errors import NeulfError
from neulf_core.reconstruct import find_photos, reconstruct, stage_photos

WIDTH, HEIGHT = 200, 150
FOCAL_PX = 170.0
SUPERSAMPLE = 2  # render at 2x and average down, against aliasing of the texture
LOOK_AT = np.array([0.0, 0.0, 4.0])
# (depth along +z, half side of the square plane, texture seed): a card in front of a wall.
PLANES = [(3.0, 0.9, 1), (5.0, 6.0, 2)]
GRID_COLUMNS, GRID_ROWS, GRID_SPACING = 4, 2, 0.3


# ------------------------------------------------------------------ synthetic capture


def blurred_noise(rng, size, sigma):
    """White noise low-passed by a Gaussian of ``sigma`` texels (via FFT: no scipy needed)."""
    noise = rng.standard_normal((size, size))
    fy = np.fft.fftfreq(size)[:, None]
    fx = np.fft.rfftfreq(size)[None, :]
    gaussian = np.exp(-2 * (np.pi * sigma) ** 2 * (fx**2 + fy**2))
    blurred = np.fft.irfft2(np.fft.rfft2(noise) * gaussian, s=(size, size))
    return blurred / blurred.std()


def plane_texture(seed, size):
    """Multi-scale blob texture in [0, 1]: plenty of SIFT features at every octave."""
    rng = np.random.default_rng(seed)
    texture = sum(blurred_noise(rng, size, sigma) for sigma in (1.0, 2.5, 6.0))
    return np.clip(0.5 + texture / (6 * texture.std()), 0, 1)


def world_to_camera_rotation(centre):
    """OpenCV-style camera (x right, y down, z forward) at ``centre`` looking at LOOK_AT."""
    forward = LOOK_AT - centre
    forward /= np.linalg.norm(forward)
    right = np.cross([0.0, 1.0, 0.0], forward)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    return np.stack([right, down, forward])


def sample_bilinear(texture, u, v):
    """Texture value at normalised coordinates (u, v) in [0, 1]."""
    n = texture.shape[0]
    x = np.clip(u * (n - 1), 0, n - 1.001)
    y = np.clip(v * (n - 1), 0, n - 1.001)
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = x - x0, y - y0
    return (
        texture[y0, x0] * (1 - fx) * (1 - fy)
        + texture[y0, x0 + 1] * fx * (1 - fy)
        + texture[y0 + 1, x0] * (1 - fx) * fy
        + texture[y0 + 1, x0 + 1] * fx * fy
    )


def render_view(centre, textures):
    """Ray-cast the planes (nearest hit wins) into an 8-bit grey image."""
    width, height, focal = WIDTH * SUPERSAMPLE, HEIGHT * SUPERSAMPLE, FOCAL_PX * SUPERSAMPLE
    xs, ys = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    rays_camera = np.stack([(xs - width / 2) / focal, (ys - height / 2) / focal, np.ones_like(xs)], -1)
    rays = rays_camera @ world_to_camera_rotation(centre)  # rotate camera rays into the world
    image = np.zeros((height, width))
    nearest = np.full((height, width), np.inf)
    for (depth, half_side, _), texture in zip(PLANES, textures):
        distance = (depth - centre[2]) / rays[..., 2]
        hit = centre[:2] + distance[..., None] * rays[..., :2]
        visible = (np.abs(hit) < half_side).all(-1) & (distance < nearest)
        uv = (hit + half_side) / (2 * half_side)
        image[visible] = sample_bilinear(texture, uv[..., 0], uv[..., 1])[visible]
        nearest[visible] = distance[visible]
    image = image.reshape(HEIGHT, SUPERSAMPLE, WIDTH, SUPERSAMPLE).mean(axis=(1, 3))
    return (image * 255).astype(np.uint8)


def grid_camera_centres():
    xs = (np.arange(GRID_COLUMNS) - (GRID_COLUMNS - 1) / 2) * GRID_SPACING
    ys = (np.arange(GRID_ROWS) - (GRID_ROWS - 1) / 2) * GRID_SPACING
    return np.array([[x, y, 0.0] for y in ys for x in xs])


def write_synthetic_capture(folder):
    """Write the 8 views as view_NN.png; returns {file name: true camera centre}."""
    folder.mkdir(parents=True, exist_ok=True)
    # Texture resolution about one texel per pixel of the view, so every blob scale survives.
    textures = [
        plane_texture(seed, int(2 * half_side * FOCAL_PX / depth)) for depth, half_side, seed in PLANES
    ]
    centres = {}
    for index, centre in enumerate(grid_camera_centres()):
        name = f"view_{index:02d}.png"
        Image.fromarray(render_view(centre, textures)).convert("RGB").save(folder / name)
        centres[name] = centre
    return centres


def write_noise_photos(folder, count, seed=0):
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    for index in range(count):
        pixels = rng.integers(0, 256, (HEIGHT, WIDTH, 3), dtype=np.uint8)
        Image.fromarray(pixels).save(folder / f"noise_{index:02d}.png")


def similarity_residuals(source, target):
    """Distances left after the best similarity transform source -> target (Umeyama 1991)."""
    source_mean, target_mean = source.mean(0), target.mean(0)
    source_centred, target_centred = source - source_mean, target - target_mean
    u, singular_values, vt = np.linalg.svd(target_centred.T @ source_centred / len(source))
    sign = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])  # a rotation, never a reflection
    rotation = u @ sign @ vt
    scale = np.trace(np.diag(singular_values) @ sign) / source_centred.var(0).sum()
    aligned = scale * source_centred @ rotation.T + target_mean
    return np.linalg.norm(aligned - target, axis=1)


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    """A folder of synthetic photos and their true camera centres (rendered once per module)."""
    folder = tmp_path_factory.mktemp("capture") / "photos"
    return folder, write_synthetic_capture(folder)


def copy_photos(names, source, destination):
    destination.mkdir(parents=True, exist_ok=True)
    for name in names:
        (destination / name).write_bytes((source / name).read_bytes())
    return destination


# -------------------------------------------------------------------------- success


def test_reconstructs_synthetic_capture(capture, tmp_path, capfd):
    photos, true_centres = capture
    events = []

    model_dir = reconstruct(photos, tmp_path / "scene", progress=events.append)

    assert model_dir == tmp_path / "scene" / "sparse" / "0"
    assert {"cameras.bin", "images.bin", "points3D.bin"} <= {p.name for p in model_dir.iterdir()}
    assert (tmp_path / "scene" / "database.db").is_file()
    assert sorted(p.name for p in (tmp_path / "scene" / "images").iterdir()) == sorted(true_centres)

    model = pycolmap.Reconstruction(model_dir)
    assert model.num_reg_images() == len(true_centres)
    assert model.num_cameras() == 1  # single_camera: one shared intrinsics
    focal = next(iter(model.cameras.values())).params[0]
    assert focal == pytest.approx(FOCAL_PX, rel=0.05)
    names = sorted(true_centres)
    recovered = np.array([model.find_image_with_name(name).projection_center() for name in names])
    expected = np.array([true_centres[name] for name in names])
    baseline = np.linalg.norm(expected[:, None] - expected[None], axis=-1).max()
    assert similarity_residuals(recovered, expected).max() < 0.02 * baseline

    stages = [event["stage"] for event in events]
    assert stages[0] == "features" and stages[-1] == "done"
    assert set(stages) == {"features", "matching", "mapping", "done"}
    assert stages.index("matching") < stages.index("mapping")
    mapping_counts = [event["registered"] for event in events if event["stage"] == "mapping"]
    assert mapping_counts[-1] == len(true_centres)  # per-image progress during mapping
    assert events[-1]["registered"] == events[-1]["total"] == len(true_centres)
    assert all(isinstance(event["message"], str) and event["message"] for event in events)

    assert capfd.readouterr().err == ""  # pycolmap's glog INFO/WARNING output is silenced


def test_rerun_in_place_reuses_scene_images(capture, tmp_path):
    # A SCENE_DIR whose images/ is the input: photos stay, the old model is replaced.
    photos, true_centres = capture
    scene = tmp_path / "scene"
    copy_photos(sorted(true_centres), photos, scene / "images")
    (scene / "sparse" / "0").mkdir(parents=True)
    (scene / "sparse" / "0" / "stale.txt").write_text("old")

    model_dir = reconstruct(scene / "images", scene)

    assert not (model_dir / "stale.txt").exists()
    assert pycolmap.Reconstruction(model_dir).num_reg_images() == len(true_centres)


def test_per_photo_cameras_and_sequential_matching(capture, tmp_path):
    photos, true_centres = capture
    model_dir = reconstruct(photos, tmp_path / "scene", single_camera=False, matcher="sequential")
    model = pycolmap.Reconstruction(model_dir)
    assert model.num_reg_images() == len(true_centres)
    assert model.num_cameras() == len(true_centres)

def test_find_photos_filters_by_extension_case_insensitively(tmp_path):
    for name in ["a.JPG", "b.jpeg", "c.Png", "d.tif", "e.TIFF", "f.bmp", "g.webp", "notes.txt", ".h.jpg"]:
        (tmp_path / name).write_bytes(b"x")
    (tmp_path / "sub.png").mkdir()
    expected = ["a.JPG", "b.jpeg", "c.Png", "d.tif", "e.TIFF", "f.bmp", "g.webp"]
    assert [p.name for p in find_photos(tmp_path)] == expected


def test_stage_photos_keeps_names_and_links(tmp_path):
    source = tmp_path / "in"
    source.mkdir()
    photos = []
    for name in ["one.jpg", "two.png"]:
        (source / name).write_bytes(name.encode())
        photos.append(source / name)

    images = stage_photos(photos, tmp_path / "scene" / "images")
    stage_photos(photos, images)  # idempotent

    assert sorted(p.name for p in images.iterdir()) == ["one.jpg", "two.png"]
    assert (images / "one.jpg").read_bytes() == b"one.jpg"
    assert (images / "one.jpg").samefile(source / "one.jpg")  # tmp_path is one file system: hard link


# --------------------------------------------------------------------------- errors


def test_missing_folder(tmp_path):
    with pytest.raises(NeulfError, match="does not exist"):
        reconstruct(tmp_path / "nope", tmp_path / "scene")


def test_unwritable_output(capture, tmp_path):
    (tmp_path / "scene").write_text("a file where the scene folder should go")
    with pytest.raises(NeulfError, match="Cannot write the scene folder"):
        reconstruct(capture[0], tmp_path / "scene")


def test_file_instead_of_folder(tmp_path):
    (tmp_path / "photo.jpg").write_bytes(b"x")
    with pytest.raises(NeulfError, match="not a folder"):
        reconstruct(tmp_path / "photo.jpg", tmp_path / "scene")


def test_folder_without_photos_lists_accepted_extensions(tmp_path):
    (tmp_path / "photos").mkdir()
    (tmp_path / "photos" / "readme.txt").write_text("hi")
    with pytest.raises(NeulfError, match=r"No photos found.*\.png.*\.jpg"):
        reconstruct(tmp_path / "photos", tmp_path / "scene")


def test_photos_in_a_camera_s_own_format_are_named(capture, tmp_path):
    """An iPhone's HEIC photos (or raw files) are not read: a folder of only those is said to
    hold them, with what to do (it had said only "no photos found"), and a folder mixing them
    with JPEGs says that they are left out before reconstructing the rest."""
    only_heic = tmp_path / "heic"
    only_heic.mkdir()
    for i in range(5):
        (only_heic / f"IMG_{i:04d}.HEIC").write_bytes(b"not decoded")
    with pytest.raises(NeulfError, match=r"5 \.HEIC photo\(s\), which cannot be read: export them as JPEG"):
        reconstruct(only_heic, tmp_path / "scene_heic")

    class Stop(Exception):
        pass

    def first_event(event):
        seen.append(event["message"])
        raise Stop()

    photos, true_centres = capture
    mixed = copy_photos(sorted(true_centres), photos, tmp_path / "mixed")
    for name in ("IMG_9001.HEIC", "IMG_9002.dng"):
        (mixed / name).write_bytes(b"not decoded")
    seen = []
    with pytest.raises(Stop):
        reconstruct(mixed, tmp_path / "scene_mixed", progress=first_event)
    assert seen[0].startswith("warning: 2 photo(s) in a camera format that cannot be read are left out (IMG_9001.HEIC"), \
        seen


def test_two_photos_are_not_enough(capture, tmp_path):
    photos, true_centres = capture
    two = copy_photos(sorted(true_centres)[:2], photos, tmp_path / "photos")
    with pytest.raises(NeulfError, match="Only 2 photo.*at least 3 overlapping photos"):
        reconstruct(two, tmp_path / "scene")


def test_unreadable_photo(capture, tmp_path):
    photos, true_centres = capture
    folder = copy_photos(sorted(true_centres)[:3], photos, tmp_path / "photos")
    (folder / "broken.jpg").write_bytes(b"not a jpeg")
    with pytest.raises(NeulfError, match="Could not read 1 photo.*broken.jpg"):
        reconstruct(folder, tmp_path / "scene")


def test_photo_of_another_size_with_single_camera(capture, tmp_path):
    photos, true_centres = capture
    folder = copy_photos(sorted(true_centres)[:3], photos, tmp_path / "photos")
    Image.open(photos / "view_00.png").resize((120, 90)).save(folder / "small.png")
    # Worded for the CLI, which has no single_camera option, and for Python callers.
    expected = r"small.png differ\(s\) in size from the other photos \(200x150\).*resize these to 200x150"
    with pytest.raises(NeulfError, match=expected) as caught:
        reconstruct(folder, tmp_path / "scene")
    assert "pass single_camera=False" not in str(caught.value)
    assert "reconstruct(..., single_camera=False)" in str(caught.value)


def test_photos_that_cannot_match(tmp_path):
    write_noise_photos(tmp_path / "photos", 4)
    with pytest.raises(NeulfError, match="No two photos could be matched: the photos need to overlap"):
        reconstruct(tmp_path / "photos", tmp_path / "scene")


def test_too_few_registered(capture, tmp_path):
    photos, true_centres = capture
    folder = copy_photos(sorted(true_centres), photos, tmp_path / "photos")
    write_noise_photos(folder, 1)
    with pytest.raises(NeulfError, match=r"Only 8 of 9 photos.*more overlap"):
        reconstruct(folder, tmp_path / "scene", min_registered_fraction=1.0)
    assert not (tmp_path / "scene" / "sparse" / "0").exists()  # no model that looks valid


@pytest.mark.parametrize(
    "options, message",
    [
        ({"matcher": "fancy"}, "Unknown matcher 'fancy'"),
        ({"camera_model": "FISH"}, "Unknown camera model 'FISH'"),
    ],
)
def test_bad_options(capture, tmp_path, options, message):
    with pytest.raises(NeulfError, match=message):
        reconstruct(capture[0], tmp_path / "scene", **options)


def test_pycolmap_failure_is_wrapped(capture, tmp_path, monkeypatch):
    def failing_match(*args, **kwargs):
        raise RuntimeError("[matching.cc:1] Check failed:\n something broke")

    monkeypatch.setattr(reconstruct_module.pycolmap, "match_exhaustive", failing_match)
    with pytest.raises(NeulfError, match="COLMAP failed during matching: .*something broke") as caught:
        reconstruct(capture[0], tmp_path / "scene")
    assert "\n" not in str(caught.value)


def test_progress_callback_exception_passes_through(capture, tmp_path):
    class Cancelled(Exception):
        pass

    def cancel_during_mapping(event):
        if event["stage"] == "mapping" and event["registered"] >= 3:
            raise Cancelled()

    with pytest.raises(Cancelled):
        reconstruct(capture[0], tmp_path / "scene", progress=cancel_during_mapping)



# ------------------------------------------------ an existing scene folder is kept safe


def scene_snapshot(scene):
    """Every path under ``scene`` with its bytes (None for folders), hidden ones included."""
    return {
        str(path.relative_to(scene)): None if path.is_dir() else path.read_bytes()
        for path in sorted(scene.rglob("*"))
    }


def fake_existing_scene(capture, folder):
    """A scene folder from an earlier run: its photos, a model and a database (stand-ins)."""
    photos, true_centres = capture
    copy_photos(sorted(true_centres), photos, folder / "images")
    (folder / "sparse" / "0").mkdir(parents=True)
    (folder / "sparse" / "0" / "cameras.bin").write_bytes(b"the old model")
    (folder / "database.db").write_bytes(b"the old database")
    return folder


def test_photo_of_same_name_never_overwritten(capture, tmp_path):
    # The user's audit: new photos, one named like a photo of the scene but another picture,
    # and some of another size. The old code deleted the model and replaced the user's photo.
    photos, true_centres = capture
    scene = fake_existing_scene(capture, tmp_path / "scene")
    before = scene_snapshot(scene)
    new = copy_photos(sorted(true_centres)[1:4], photos, tmp_path / "new")
    write_noise_photos(tmp_path / "noise", 1)
    (tmp_path / "noise" / "noise_00.png").rename(new / "view_00.png")  # same name, another photo
    Image.open(photos / "view_05.png").resize((120, 90)).save(new / "small.png")

    expected = r"already holds another photo named view_00.png.*choose a new --out"
    with pytest.raises(NeulfError, match=expected) as caught:
        reconstruct(new, scene)
    assert "\n" not in str(caught.value)
    assert scene_snapshot(scene) == before  # nothing changed: photos, model, database, no leftovers


def test_failed_run_leaves_existing_scene_untouched(capture, tmp_path):
    photos, true_centres = capture
    scene = fake_existing_scene(capture, tmp_path / "scene")
    before = scene_snapshot(scene)
    new = copy_photos(sorted(true_centres)[:3], photos, tmp_path / "new")
    Image.open(photos / "view_05.png").resize((120, 90)).save(new / "small.png")

    with pytest.raises(NeulfError, match="differ"):
        reconstruct(new, scene)
    assert scene_snapshot(scene) == before  # the old model and database stay; small.png not added


def test_failed_run_into_new_folder_leaves_nothing(capture, tmp_path):
    class Cancelled(Exception):
        pass

    def cancel(event):
        if event["stage"] == "mapping":
            raise Cancelled()

    with pytest.raises(Cancelled):
        reconstruct(capture[0], tmp_path / "scene", progress=cancel)
    assert not (tmp_path / "scene").exists()


def test_rerun_same_photos_into_same_scene(capture, tmp_path):
    # Re-running on the same photos (here copies: other files, the same bytes) is normal use.
    photos, true_centres = capture
    scene = tmp_path / "scene"
    reconstruct(photos, scene)
    first_photo = (scene / "images" / "view_00.png").stat().st_ino
    model_dir = reconstruct(copy_photos(sorted(true_centres), photos, tmp_path / "copies"), scene)
    assert pycolmap.Reconstruction(model_dir).num_reg_images() == len(true_centres)
    assert (scene / "images" / "view_00.png").stat().st_ino == first_photo  # kept, not replaced
    assert sorted(p.name for p in scene.iterdir()) == ["database.db", "images", "sparse"]  # no leftovers


# ------------------------------------------------------------------------------ WebP


def capture_with_webp(capture, folder, webp_names=("view_03.png", "view_06.png")):
    photos, true_centres = capture
    copy_photos(sorted(true_centres), photos, folder)
    for name in webp_names:
        Image.open(folder / name).save((folder / name).with_suffix(".webp"), lossless=True)
        (folder / name).unlink()
    return folder


def test_webp_photos_are_staged_as_png(capture, tmp_path):
    photos, true_centres = capture
    folder = capture_with_webp(capture, tmp_path / "photos")
    scene = tmp_path / "scene"

    model_dir = reconstruct(folder, scene)

    model = pycolmap.Reconstruction(model_dir)
    assert model.num_reg_images() == len(true_centres)
    assert model.find_image_with_name("view_03.png") is not None
    assert sorted(p.name for p in (scene / "images").iterdir()) == sorted(true_centres)  # no .webp
    staged = np.asarray(Image.open(scene / "images" / "view_03.png"))
    assert np.array_equal(staged, np.asarray(Image.open(photos / "view_03.png")))

    # Again in place, from the scene's own images/: the PNG copies stand for the WebP photos.
    copy_photos(["view_03.webp"], folder, scene / "images")
    model_dir = reconstruct(scene / "images", scene)
    assert pycolmap.Reconstruction(model_dir).num_reg_images() == len(true_centres)


def test_failed_run_with_webp_leaves_no_photos(capture, tmp_path):
    folder = capture_with_webp(capture, tmp_path / "photos")
    (folder / "broken.jpg").write_bytes(b"not a jpeg")
    scene = tmp_path / "scene"
    (scene / "images").mkdir(parents=True)

    with pytest.raises(NeulfError, match="Could not read 1 photo.*broken.jpg"):
        reconstruct(folder, scene)
    assert list((scene / "images").iterdir()) == []
    assert sorted(p.name for p in scene.iterdir()) == ["images"]


# --------------------------------------------------------------- camera model failures


def test_camera_model_named_when_matches_do_not_fit_it(capture, tmp_path):
    # The photos match with the default model; with a fisheye one no pair verifies.
    with pytest.raises(NeulfError, match="camera model OPENCV_FISHEYE, the likely cause.*--camera-model"):
        reconstruct(capture[0], tmp_path / "scene", camera_model="OPENCV_FISHEYE")


@pytest.mark.parametrize(
    "camera_model, message",
    [
        pytest.param("SIMPLE_RADIAL", r"28 photo pair\(s\) matched, but no pair could start a model: .*different positions",
                     id="default-model"),
        pytest.param("OPENCV", r"28 photo pair\(s\) matched, but no pair could start a model with the camera model OPENCV",
                     id="distortion-model"),
    ],
)
def test_no_model_despite_matches(capture, tmp_path, monkeypatch, camera_model, message):
    monkeypatch.setattr(reconstruct_module.pycolmap, "incremental_mapping", lambda *args, **kwargs: {})
    with pytest.raises(NeulfError, match=message):
        reconstruct(capture[0], tmp_path / "scene", camera_model=camera_model)


# ------------------------------------------------------------ runs killed outright, runs at once


def work_folders(scene):
    return sorted(scene.glob(reconstruct_module.WORK_PREFIX + "*"))


def test_a_run_killed_outright_leaves_nothing_after_the_next(capture, tmp_path):
    """SIGKILL (or a power cut) cannot clean up: its hidden work folder stays until the next
    run into the folder, which removes it, and the scene is made as usual."""
    import os
    import signal
    import subprocess
    import sys
    import time

    scene = tmp_path / "scene"
    script = f"from neulf_core.reconstruct import reconstruct; reconstruct({str(capture[0])!r}, {str(scene)!r})"
    process = subprocess.Popen([sys.executable, "-c", script], cwd=Path(__file__).resolve().parent.parent)
    deadline = time.monotonic() + 120
    while not any((folder / "database.db").is_file() for folder in work_folders(scene)):
        assert process.poll() is None and time.monotonic() < deadline, "the run ended before it was killed"
        time.sleep(0.05)
    os.kill(process.pid, signal.SIGKILL)
    process.wait()
    assert len(work_folders(scene)) == 1  # what the kill left

    model_dir = reconstruct(capture[0], scene)

    assert work_folders(scene) == []
    assert pycolmap.Reconstruction(model_dir).num_reg_images() == len(capture[1])


def test_a_run_stopped_by_sigterm_says_so_and_exits_143(capture, tmp_path, record_property):
    """SIGTERM (kill, a scheduler's limit, Blender's Cancel) ends a reconstruction with one line
    naming it and exit 128 + 15, as train, render and video end; its work folder is removed.
    (It had said "interrupted" and exited 130, Ctrl-C's code: a script could not tell them apart.)"""
    import os
    import signal
    import subprocess
    import sys
    import time

    scene = tmp_path / "scene"
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parent.parent))
    process = subprocess.Popen([sys.executable, "-m", "neulf_core", "reconstruct", str(capture[0]), "--out", str(scene)],
                               env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        while not any((folder / "database.db").is_file() for folder in work_folders(scene)):
            assert process.poll() is None and time.monotonic() < deadline, "the run ended before it was stopped"
            time.sleep(0.05)
        process.send_signal(signal.SIGTERM)
        _, err = process.communicate(timeout=120)
    finally:
        if process.poll() is None:
            process.kill()
    last = err.strip().splitlines()[-1]
    record_property("message", last)
    assert process.returncode == 128 + signal.SIGTERM, err
    assert last == "stopped by SIGTERM" and "Traceback" not in err, err
    assert work_folders(scene) == [] and not (scene / "sparse").exists()


def test_a_run_into_a_folder_another_run_reconstructs_is_refused(capture, tmp_path):
    """Two runs into one folder would install their models over each other: the second is
    refused, naming the first's process, and leaves the first's work alone."""
    import subprocess
    import sys
    import time

    scene = tmp_path / "scene"
    other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        busy = scene / (reconstruct_module.WORK_PREFIX + "other")
        busy.mkdir(parents=True)
        (busy / reconstruct_module.WORK_OWNER).write_text(
            f'{{"pid": {other.pid}, "host": "{__import__("platform").node()}", "started": {time.time()}}}')
        with pytest.raises(NeulfError, match=f"being reconstructed by process {other.pid}"):
            reconstruct(capture[0], scene)
        assert work_folders(scene) == [busy] and not (scene / "images").exists()
    finally:
        other.kill()
        other.wait()


def test_unclaimed_work_folders_are_removed_only_when_old(capture, tmp_path):
    """A work folder with no owner record (an earlier version's, or a kill in a run's first
    instant) is removed once it is an hour old, and left alone before: it may be a run's start."""
    import os
    import time

    scene = tmp_path / "scene"
    old, young = scene / (reconstruct_module.WORK_PREFIX + "old"), scene / (reconstruct_module.WORK_PREFIX + "young")
    for folder in (old, young):
        folder.mkdir(parents=True)
    hours_ago = time.time() - 2 * reconstruct_module.UNCLAIMED_WORK_SECONDS
    os.utime(old, (hours_ago, hours_ago))

    reconstruct(capture[0], scene)

    assert work_folders(scene) == [young]


def test_a_run_killed_between_its_two_renames_leaves_its_new_model_in_place(capture, tmp_path, record_property):
    """Killed after moving the old sparse/0 into its work folder and before moving the new one in
    (two renames apart): the next run found no sparse/0 and deleted the dead work folder holding
    both models.  The new, complete one is put in place first."""
    import json
    import platform
    import shutil
    import subprocess
    import sys
    import time

    scene = tmp_path / "scene"
    reconstruct(capture[0], scene)
    model = scene / "sparse" / "0"
    registered = pycolmap.Reconstruction(model).num_reg_images()
    work = scene / (reconstruct_module.WORK_PREFIX + "killed")
    work.mkdir()
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    (work / reconstruct_module.WORK_OWNER).write_text(json.dumps({"pid": int(dead.stdout), "host": platform.node(),
                                                                   "started": time.time() - 5}))
    shutil.copytree(model, work / "old-model")  # (the first rename done)
    model.rename(work / "sparse")  # (a work folder's sparse/ is the new model itself; the second rename not done)
    assert not model.exists()
    assert reconstruct_module._other_runs(scene) == []
    assert pycolmap.Reconstruction(model).num_reg_images() == registered and work_folders(scene) == []
    record_property("message", "the new model put in place, then the dead run's folder removed")


def test_a_relative_scene_folder(capture, tmp_path, monkeypatch):
    """From Python 3.12 tempfile.mkdtemp returns an absolute path where the folder given is
    relative, and the run took its own work folder for another run's and refused itself."""
    import os
    import tempfile

    absolute_mkdtemp = tempfile.mkdtemp
    monkeypatch.setattr(reconstruct_module.tempfile, "mkdtemp",
                        lambda *args, **kwargs: os.path.abspath(absolute_mkdtemp(*args, **kwargs)))
    monkeypatch.chdir(tmp_path)
    model_dir = reconstruct(capture[0], Path("relative_scene"))
    assert pycolmap.Reconstruction(model_dir).num_reg_images() == len(capture[1])
    assert work_folders(tmp_path / "relative_scene") == []


# -------------------------------------------------------------------------- a capture filmed


def test_a_video_gives_its_sharpest_frames_and_they_reconstruct(capture, tmp_path, capfd):
    """A capture filmed: each of the 8 views held for three frames, the first and last blurred
    as a moving camera blurs them.  `frames --count 8` keeps the sharp one of each stretch, in
    order, and the photos reconstruct with every view registered."""
    from PIL import ImageFilter

    from neulf_core.cli import main
    from neulf_core.video import write_video

    photos, true_centres = capture
    names = sorted(true_centres)
    sharp = [np.asarray(Image.open(photos / name).convert("RGB")) for name in names]
    blurred = [np.asarray(Image.fromarray(view).filter(ImageFilter.GaussianBlur(2.5))) for view in sharp]
    clip = tmp_path / "walk.mp4"
    write_video([frame for s, b in zip(sharp, blurred) for frame in (b, s, b)], clip, fps=6)
    assert main(["frames", str(clip), "--out", str(tmp_path / "frames"), "--count", "8"]) == 0
    picked = sorted((tmp_path / "frames").iterdir())
    assert [p.name for p in picked] == [f"frame_{i:04d}.png" for i in range(1, 9)]
    for path, s, b in zip(picked, sharp, blurred):
        frame = np.asarray(Image.open(path), dtype=np.float32)[:HEIGHT, :WIDTH]  # (H.264 pads to even sizes)
        assert np.abs(frame - s).mean() < 0.5 * np.abs(frame - b).mean(), path.name  # the sharp frame, each stretch
    assert "next: python -m neulf_core reconstruct" in capfd.readouterr().out
    model = pycolmap.Reconstruction(reconstruct(tmp_path / "frames", tmp_path / "scene"))
    assert model.num_reg_images() == len(names)


def test_frames_refuses_what_it_cannot_use(capture, tmp_path):
    from neulf_core.frames import extract_frames, upright

    with pytest.raises(NeulfError, match="does not exist"):
        extract_frames(tmp_path / "missing.mp4", tmp_path / "out")
    not_video = tmp_path / "notes.mp4"
    not_video.write_text("not a video")
    with pytest.raises(NeulfError, match="cannot read .* as a video"):
        extract_frames(not_video, tmp_path / "out")
    with pytest.raises(NeulfError, match="already holds photos"):  # (frames would be reconstructed with them)
        extract_frames(not_video, capture[0])
    with pytest.raises(NeulfError, match="is a video: pick its sharpest frames"):  # reconstruct given the video
        reconstruct(not_video, tmp_path / "scene")
    photo = next(Path(capture[0]).iterdir())  # a photo given as the video (Blender's Reconstruct Video on a PNG)
    with pytest.raises(NeulfError, match="is a still image, not a video"):
        extract_frames(photo, tmp_path / "out")
    assert not (tmp_path / "out").exists()
    # A phone's portrait clip is stored sideways with a turn to apply (PyAV's rotation: counter-
    # clockwise degrees): -90 turns the stored frame a quarter clockwise.
    stored = np.zeros((2, 3, 3), np.uint8)
    stored[0, 0] = 255  # top left
    shown = upright(stored, -90)
    assert shown.shape == (3, 2, 3) and shown[0, 1, 0] == 255  # top right
    assert upright(stored, 0) is stored


def _with_display_matrix(clip: Path, matrix: list[int]) -> None:
    """Write `matrix` (QuickTime's 3x3 display matrix: a, b, u, c, d, v, tx, ty, w; 16.16 fixed
    point, u, v and w 2.30) into the MP4's video track header ('tkhd'), as a phone does."""
    import struct

    data = bytearray(clip.read_bytes())
    at = data.find(b"tkhd")
    start = at + 4 + (40 if data[at + 4] == 0 else 52)  # (version 1 keeps 64-bit times)
    data[start:start + 36] = struct.pack(">9i", *matrix)
    clip.write_bytes(bytes(data))


def test_a_portrait_phone_clip_gives_upright_photos(tmp_path):
    """A phone filming in portrait stores its frames sideways and a display matrix in the MP4's
    track header that turns them: a quarter turn clockwise (x' = tx - y, y' = x, QuickTime's
    matrix [0, 1, 0; -1, 0, 0; tx, 0, 1]).  The photos are as the clip is shown: tall, with the
    stored frame's left edge on top."""
    from neulf_core.frames import extract_frames
    from neulf_core.video import write_video

    stored = np.zeros((32, 64, 3), np.uint8)
    stored[:, :8] = 255  # the stored frame's left edge
    clip = tmp_path / "portrait.mp4"
    write_video([stored] * 6, clip, fps=6)
    _with_display_matrix(clip, [0, 1 << 16, 0, -(1 << 16), 0, 0, 32 << 16, 0, 1 << 30])
    photos = extract_frames(clip, tmp_path / "photos", count=3)
    shown = np.asarray(Image.open(photos[0]).convert("L"), np.float32)
    assert shown.shape == (64, 32)  # tall, as shown
    assert shown[:6].mean() > 200 and shown[10:].mean() < 30  # the stored left edge on top
    _with_display_matrix(clip, [1 << 16, 0, 0, 0, 1 << 16, 0, 0, 0, 1 << 30])  # (no turn: as stored)
    assert np.asarray(Image.open(extract_frames(clip, tmp_path / "as_stored", count=3)[0])).shape[:2] == (32, 64)


def test_frames_of_a_clip_cut_short_leave_no_photos(capture, tmp_path):
    """A copy of a clip cut off part-way, and a clip of two frames: one line each, and no photos
    left behind for reconstruct to take as a capture."""
    from neulf_core.frames import extract_frames
    from neulf_core.video import write_video

    photos, true_centres = capture
    views = [np.asarray(Image.open(photos / name).convert("RGB")) for name in sorted(true_centres)]
    clip = tmp_path / "clip.mp4"
    write_video(views * 4, clip, fps=8)
    data = clip.read_bytes()
    cut = tmp_path / "cut.mp4"
    cut.write_bytes(data[:len(data) // 2])  # (the index at the end of an MP4 is gone)
    with pytest.raises(NeulfError, match="cut|could not be read|cannot read"):
        extract_frames(cut, tmp_path / "out_cut", count=8)
    assert not (tmp_path / "out_cut").exists()
    write_video(views[:2], tmp_path / "short.mp4", fps=8)
    with pytest.raises(NeulfError, match="gave 2 frame"):
        extract_frames(tmp_path / "short.mp4", tmp_path / "out_short", count=8)
    assert not (tmp_path / "out_short").exists()


def test_a_webp_photo_past_pillows_bomb_limit_is_staged(tmp_path, monkeypatch):
    """WebP photos are converted to PNG when staged; one past Pillow's decompression-bomb limit
    (179 MP; real stills reach 400) ended reconstruct in Pillow's DecompressionBombError, which
    training's own reading admits.  Simulated small: Pillow's limit lowered under the photo."""
    import neulf_core.images as images

    photo = tmp_path / "photos" / "big.webp"
    photo.parent.mkdir()
    Image.fromarray(np.full((64, 64, 3), 90, np.uint8)).save(photo, lossless=True)
    monkeypatch.setattr(Image, "MAX_IMAGE_PIXELS", 1000)  # (Pillow refuses past twice that: 4096 pixels here)
    staged = stage_photos([photo], tmp_path / "scene" / "images")
    assert images.load_rgb(staged / "big.png").shape == (64, 64, 3)
    assert Image.MAX_IMAGE_PIXELS == 1000  # (Pillow's limit put back)
    monkeypatch.setattr(images, "PHOTO_PIXEL_LIMIT", 1000)  # (past the project's own: one line naming it)
    with pytest.raises(NeulfError, match="big.webp claims 64x64 pixels"):
        stage_photos([photo], tmp_path / "other" / "images")

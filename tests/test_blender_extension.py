"""The Blender extension end to end, under the real bpy module (headless).

pytest builds the repository into an extension zip with Blender's own builder, validates
it, and then runs tests/blender_story.py in a fresh Python (BLENDER_USER_RESOURCES isolated
to a temp folder before bpy is imported) that installs the zip as a user extension and
walks through the artist's story on a tiny synthetic capture: import, check every camera
against pycolmap, train through the operator (blocking and timer paths, cancel, Train again
after Cancel), render, focus (by image point and by a click in the camera view), F12, a
spiral video, save and reload, the .blend and its model moved elsewhere and opened by a new
Blender, Blender quit or killed while training and a new Blender reopening the .blend and
continuing the model, reconstruct a folder of photos, dependency status and install; where
the reference scenes (../shared/data) are present, each is imported and its cameras checked
against pycolmap, and HCI's is rendered through a model the CLI trained.  The
steps that need Blender started again run blender_story.py's sessions in new bpy processes
(same user folder, so the installed extension).  Each step's outcome is written to a JSON
file and checked by its own test below.

bpy 5.0.1 (this venv) runs neulf_core in-process.  With NEULF_BPY42_PYTHON set to a Python
that has bpy 4.2 (and no torch), the same story runs there with neulf_core in a worker
process of this Python, as for a user of a stock Blender 4.2 LTS (docs/BLENDER_42.md).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from blender_story import CX, CY, FX, FY, HEIGHT, STEPS, WIDTH, K_matrix, photo_bytes, scene_views, trace

REPO = Path(__file__).resolve().parents[1]
STORY = Path(__file__).resolve().parent / "blender_story.py"
BL_PKG_CLI = "scripts/addons_core/bl_pkg/cli/blender_ext.py"
BPY42_ENV = "NEULF_BPY42_PYTHON"

# ----------------------------------------------------------------------------- the synthetic capture


def make_scene(out: Path) -> Path:
    """A COLMAP scene folder (images/, sparse/0) of the plane seen by a 3x3 rig."""
    import pycolmap
    from PIL import Image

    (out / "images").mkdir(parents=True, exist_ok=True)
    recon = pycolmap.Reconstruction()
    recon.add_camera_with_trivial_rig(pycolmap.Camera(model="PINHOLE", width=WIDTH, height=HEIGHT,
                                                      params=[FX, FY, CX, CY], camera_id=1))
    rng = np.random.default_rng(0)
    for image_id, view in enumerate(scene_views(), start=1):
        rgb, depth = trace(view["R"], view["t"])
        Image.fromarray(photo_bytes(rgb)).save(out / "images" / view["name"])
        recon.add_image_with_trivial_frame(pycolmap.Image(name=view["name"], camera_id=1, image_id=image_id),
                                           pycolmap.Rigid3d(pycolmap.Rotation3d(view["R"]), view["t"]))
        rows, cols = rng.integers(0, HEIGHT, 30), rng.integers(0, WIDTH, 30)
        K = K_matrix()
        cam = np.stack([(cols + 0.5 - K[0, 2]) / K[0, 0], (rows + 0.5 - K[1, 2]) / K[1, 1], np.ones(30)], 1)
        cam *= depth[rows, cols][:, None]
        for xyz, colour in zip((cam - view["t"]) @ view["R"], rgb[rows, cols]):
            recon.add_point3D(xyz, pycolmap.Track(), (colour * 255).astype(np.uint8))
    (out / "sparse" / "0").mkdir(parents=True, exist_ok=True)
    recon.write_binary(str(out / "sparse" / "0"))
    return out


def reference_values(scene_dir: Path) -> dict:
    """What the story checks Blender against, computed here with pycolmap and neulf_core."""
    import pycolmap

    from neulf_core.scene import load_scene, split_views
    from neulf_core.slab import fit_slab

    recon = pycolmap.Reconstruction(str(scene_dir / "sparse" / "0"))
    points = np.array([p.xyz for p in recon.points3D.values()])
    camera = recon.cameras[1]
    colmap_px = [np.asarray(camera.img_from_cam(points @ v["R"].T + v["t"])).tolist() for v in scene_views()]
    scene = load_scene(scene_dir)
    slab = fit_slab(scene, split_views(scene, 8)[0])
    return {"points": points.tolist(), "colmap_px": colmap_px,
            "slab_corners": {plane: np.asarray(slab.plane_corners(plane)).tolist() for plane in ("uv", "st")}}


# The reference scenes (../shared/data) the story imports where they are present: the folder, the
# photos' folder, and at most this many of the scene's points projected into each view.
REAL_CAPTURES = {"canclip": "images", "statue": "images", "fern": "images_8", "hci_antinous": "images"}
REAL_POINTS = 150


def real_capture_references() -> list[dict]:
    """Each reference scene present, with each photo's pinhole projection of some of its points,
    computed here with pycolmap alone (not neulf_core): its camera's K scaled to the photo files
    (fern's model is of the 4032x3024 originals, its images_8/ 504x378), its R and t.  A Blender
    camera has no lens distortion, so the distortion-free projection is what it must match."""
    import pycolmap
    from PIL import Image

    from conftest import shared_data_dir

    references = []
    for name, images in REAL_CAPTURES.items():
        scene_dir = shared_data_dir() / name
        if not (scene_dir / images).is_dir():
            continue
        recon = pycolmap.Reconstruction(str(scene_dir / "sparse" / "0"))
        points = np.array([p.xyz for p in recon.points3D.values()])
        points = points[np.random.default_rng(0).permutation(len(points))[:REAL_POINTS]]
        file_width, file_height = Image.open(sorted((scene_dir / images).iterdir())[0]).size
        views = {}
        for image in recon.images.values():
            camera = recon.cameras[image.camera_id]
            K = np.diag([file_width / camera.width, file_height / camera.height, 1.0]) @ camera.calibration_matrix()
            pose = image.cam_from_world()
            cam = points @ pose.rotation.matrix().T + pose.translation
            px = np.where(cam[:, 2:] > 0, (cam @ K.T)[:, :2] / cam[:, 2:], np.nan)
            views[image.name] = {"width": file_width, "height": file_height, "px": px.tolist()}
        references.append({"name": name, "scene_dir": str(scene_dir), "images_dir": str(scene_dir / images),
                           "points": points.tolist(), "views": views})
    return references


def hci_setup(folder: Path) -> dict:
    from conftest import shared_data_dir

    hci = shared_data_dir() / "hci_antinous"
    return {"hci": hci_renders(hci, folder / "hci")} if (hci / "images").is_dir() else {}


# HCI's grid (PINHOLE, each camera's sensor shifted) trained briefly by the CLI, and two of its views
# rendered by the CLI: Blender's Render Camera through its imported cameras must give the same images.
HCI_RENDER_VIEWS = ("input_Cam000.png", "input_Cam013.png")  # held out (every 8th), trained on


def hci_renders(scene_dir: Path, out: Path) -> dict:
    model = out / "hci_model"
    for argv in (["train", str(scene_dir), "--out", str(model), "--steps", "150", "--progress", "json"],
                 ["render", str(model), "--scene", str(scene_dir), "--views", ",".join(HCI_RENDER_VIEWS),
                  "--out", str(out / "hci_renders")]):
        run = subprocess.run([sys.executable, "-m", "neulf_core", *argv], capture_output=True, text=True, timeout=900)
        assert run.returncode == 0, run.stderr[-3000:]
    return {"model_dir": str(model),
            "renders": {view: str(out / "hci_renders" / f"{Path(view).stem}.png") for view in HCI_RENDER_VIEWS}}


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> dict:
    """The story's inputs, shared by the bpy 5.0 and 4.2 runs (read-only for them)."""
    pytest.importorskip("torch")
    from test_reconstruct import FOCAL_PX, write_synthetic_capture  # the SfM tests' own photos

    folder = tmp_path_factory.mktemp("capture")
    scene_dir = make_scene(folder / "scene")
    write_synthetic_capture(folder / "photos")
    from PIL import Image

    from neulf_core.video import write_video

    # The same capture filmed: each photo held for two frames (Reconstruct Video picks one of each).
    frames = [np.asarray(Image.open(photo).convert("RGB")) for photo in sorted((folder / "photos").iterdir())]
    write_video([frame for frame in frames for _ in range(2)], folder / "walk.mp4", fps=4)
    return {"scene_dir": str(scene_dir), "reference": reference_values(scene_dir), "photos": str(folder / "photos"),
            "photos_focal": FOCAL_PX, "video": str(folder / "walk.mp4"), "video_photos": len(frames),
            "real_captures": real_capture_references()} | hci_setup(folder)


# ----------------------------------------------------------------------------- pytest side


def blender_ext_cli(python: str | None = None) -> Path:
    """Blender's extension builder/validator inside the bpy wheel of `python` (default: this one)."""
    if python is None:
        import importlib.util

        spec = importlib.util.find_spec("bpy")
        if spec is None or spec.origin is None:
            pytest.skip("bpy is not installed")
        bpy_dir = Path(spec.origin).parent
    else:
        # find_spec, not import: once imported, 4.2's bpy names its scripts/modules package.
        code = "import importlib.util, os; print(os.path.dirname(importlib.util.find_spec('bpy').origin))"
        run = subprocess.run([python, "-c", code],
                             capture_output=True, text=True, timeout=120, env=dict(os.environ, PYTHONPATH=""))
        assert run.returncode == 0, run.stderr[-2000:]
        bpy_dir = Path(run.stdout.strip().splitlines()[-1])
    clis = sorted(bpy_dir.glob(f"*/{BL_PKG_CLI}"))
    if not clis:
        pytest.skip(f"Blender's extension CLI not found under {bpy_dir}")
    return clis[-1]


def build_extension(out_dir: Path, python: str = sys.executable) -> Path:
    cli = blender_ext_cli(None if python == sys.executable else python)
    run = subprocess.run([python, str(cli), "build", "--source-dir", str(REPO), "--output-dir", str(out_dir)],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stdout + run.stderr
    zips = list(out_dir.glob("*.zip"))
    assert len(zips) == 1, run.stdout
    return zips[0]


def validate(python: str, cli: Path, targets) -> None:
    for target in targets:
        run = subprocess.run([python, str(cli), "validate", str(target)], capture_output=True, text=True,
                             timeout=120)
        assert run.returncode == 0 and "error" not in (run.stdout + run.stderr).lower(), run.stdout + run.stderr


def check_zip_contents(extension_zip: Path) -> None:
    import zipfile

    names = set(zipfile.ZipFile(extension_zip).namelist())
    assert {"blender_manifest.toml", "__init__.py", "neulf_blender/operators.py", "neulf_blender/focus.py",
            "neulf_core/worker.py", "neulf_core/render.py",
            "neulf_core/fields/starts/statue_v1.npz"} <= names  # the fast field's learned colour start
    for excluded in ("tests/", "neulf_synth/", "benchmarks/", "scripts/", ".venv/", ".ci/", "docs/"):
        assert not any(n.startswith(excluded) for n in names), excluded
    assert not any(n.endswith((".sh", ".pyc")) or n == "pyproject.toml" for n in names)
    # Blender's tool packs whatever lies in the folder apart from its exclude list: a demo's output
    # or a file dropped into neulf_core/ went into the zip (275 KB -> 7.3 MB).  Only the
    # repository's own files may.
    files = {n for n in names if not n.endswith("/")}
    assert files <= {"blender_manifest.toml", "__init__.py", "README.md", "LICENSE"} | {
        n for n in files if n.startswith(("neulf_core/", "neulf_blender/"))}, sorted(files)
    tracked = subprocess.run(["git", "ls-files", "neulf_core", "neulf_blender"], cwd=REPO, capture_output=True,
                             text=True)
    if tracked.returncode == 0 and tracked.stdout.strip():  # (a checkout without git: no list to hold it to)
        strays = sorted(n for n in files if n.startswith(("neulf_core/", "neulf_blender/"))
                        and n not in set(tracked.stdout.split()))
        assert not strays, f"files the repository does not hold went into the zip: {strays}"


@pytest.fixture(scope="module")
def extension_zip(tmp_path_factory) -> Path:
    return build_extension(tmp_path_factory.mktemp("build"))


def test_build_validate_and_contents(extension_zip):
    validate(sys.executable, blender_ext_cli(), (REPO, extension_zip))
    check_zip_contents(extension_zip)


def run_story(python: str, extension_zip: Path, capture: dict, work: Path, worker_python: str | None = None) -> dict:
    """Run tests/blender_story.py in `python` (a fresh process, its own Blender user folder)."""
    results = work / "results.json"
    setup = dict(capture, zip=str(extension_zip), work=str(work), results=str(results), worker_python=worker_python)
    (work / "setup.json").write_text(json.dumps(setup))
    env = dict(os.environ, BLENDER_USER_RESOURCES=str(work / "blender_user"), PYTHONPATH="")
    started = time.monotonic()
    run = subprocess.run([python, str(STORY), str(work / "setup.json")], env=env, capture_output=True, text=True,
                         timeout=1200)
    if not results.is_file():
        pytest.fail(f"the Blender script did not run (exit {run.returncode}):\n{run.stdout[-3000:]}\n{run.stderr[-5000:]}")
    data = json.loads(results.read_text())
    data["_log"] = run.stdout[-4000:] + run.stderr[-4000:]
    data["_seconds"] = time.monotonic() - started
    data["_real_captures"] = [reference["name"] for reference in capture["real_captures"]]
    return data


@pytest.fixture(scope="module")
def story(extension_zip, capture, tmp_path_factory):
    return run_story(sys.executable, extension_zip, capture, tmp_path_factory.mktemp("story"))


def check_step(story: dict, step: str) -> None:
    if step == "real_captures" and not story.get("_real_captures"):
        from conftest import shared_data_dir

        pytest.skip(f"reference scenes not found in {shared_data_dir()} (set NEULF_SHARED_DATA)")
    outcome = story.get(step)
    assert outcome is not None, f"step {step} did not run; log:\n{story['_log']}"
    assert outcome["ok"], f"{step}: {outcome['detail']}"
    print(f"{step}: {outcome['detail']}")


@pytest.mark.slow
@pytest.mark.parametrize("step", STEPS)
def test_blender_story(story, step):
    check_step(story, step)


# ----------------------------------------------------------------------------- Blender 4.2 LTS


@pytest.fixture(scope="module")
def bpy42() -> str:
    python = os.environ.get(BPY42_ENV)
    if not python:
        pytest.skip(f"{BPY42_ENV} is not set: point it at a Python with bpy 4.2 to check Blender 4.2 LTS "
                    "(see docs/BLENDER_42.md)")
    run = subprocess.run([python, "-c", "import bpy; print(bpy.app.version_string)"], capture_output=True, text=True,
                         timeout=120, env=dict(os.environ, PYTHONPATH=""))
    assert run.returncode == 0, f"{python} cannot import bpy: {run.stderr[-2000:]}"
    version = run.stdout.strip().splitlines()[-1]
    assert version.startswith("4.2"), f"{BPY42_ENV}={python} has bpy {version}, not 4.2"
    return python


@pytest.fixture(scope="module")
def extension_zip_42(bpy42, tmp_path_factory) -> Path:
    return build_extension(tmp_path_factory.mktemp("build42"), python=bpy42)


@pytest.mark.slow
def test_blender42_build_validate_and_contents(bpy42, extension_zip_42):
    validate(bpy42, blender_ext_cli(bpy42), (REPO, extension_zip_42))
    check_zip_contents(extension_zip_42)


@pytest.fixture(scope="module")
def story42(bpy42, extension_zip_42, capture, tmp_path_factory):
    # Blender 4.2 has no torch: neulf_core runs in this Python, chosen in the preferences.
    return run_story(bpy42, extension_zip_42, capture, tmp_path_factory.mktemp("story42"), worker_python=sys.executable)


@pytest.mark.slow
@pytest.mark.parametrize("step", STEPS)
def test_blender42_story(story42, step):
    check_step(story42, step)

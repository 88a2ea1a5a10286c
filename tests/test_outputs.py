"""What render, eval and video write (audit 75): never over the scene's own photos, one file per
view (a rig's photos share their stems), each file whole or not at all, an earlier video kept
when a new one is stopped, SIGTERM said in one line, `~` as the home folder, and no eval/
folder left in a folder that is not a model.

Each test drives the real command line, in-process (`neulf_core.cli.main`) or, where a
process must be stopped by a signal, as `python -m neulf_core` in a subprocess.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import av
import numpy as np
import pytest
from PIL import Image

from conftest import tiny_camera, tiny_poses, write_colmap_model
from neulf_core.cli import main
from test_reliability import expect_error, run_cli  # (the CLI run as the reliability tests run it)

REPO = Path(__file__).resolve().parents[1]
QUICK_TRAIN = ["--steps", "2", "--batch-size", "256", "--validate-seconds", "1e9", "--progress", "json"]


def cli_process(argv, **kwargs) -> subprocess.Popen:
    """The CLI in a process of its own, with Ctrl-C's SIGINT as a terminal's foreground command has
    it: the tests run as a background job of a non-interactive shell (`cmd &`) inherit SIGINT
    ignored, which Python then keeps, and a video sent SIGINT had rendered on past the test's time."""
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""), OMP_NUM_THREADS="1")
    return subprocess.Popen([sys.executable, "-m", "neulf_core", *[str(a) for a in argv]], env=env, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL), **kwargs)


def digests(folder: Path) -> dict[str, str]:
    return {p.relative_to(folder).as_posix(): hashlib.md5(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def hidden_leftovers(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.rglob(".*"))


@pytest.fixture(scope="module")
def model(tiny_scene, tmp_path_factory) -> Path:
    """The default preset trained for 2 small steps (read-only: copy it to change it)."""
    out = tmp_path_factory.mktemp("outputs") / "model"
    assert main(["train", str(tiny_scene), "--out", str(out), *QUICK_TRAIN]) == 0
    return out


def pinhole_json(path: Path, model: Path, names, width: int = 32, height: int = 24) -> Path:
    """Cameras at the rig's centre camera, looking along the slab's axis, named `names`."""
    meta = json.loads((model / "model.json").read_text())
    K = np.array(meta["rig"]["K"], float)
    K[0] *= width / int(meta["rig"]["width"])
    K[1] *= height / int(meta["rig"]["height"])
    centre = np.asarray(meta["rig"]["centres"])[4]
    R = np.asarray(meta["slab"]["rotation"], float)
    path.write_text(json.dumps([{"name": name, "K": K.tolist(), "R": R.tolist(), "t": (-R @ centre).tolist(),
                                 "width": width, "height": height} for name in names]))
    return path


# ----------------------------------------------------------------------------- the scene's photos


@pytest.mark.parametrize("case", ["render into images", "eval into images", "render from inside images",
                                  "render cameras into images"])
def test_renders_never_replace_the_scene_s_photos(case, model, tiny_scene, tmp_path, monkeypatch, capfd,
                                                  record_property):
    scene = tmp_path / "scene"
    shutil.copytree(tiny_scene, scene)
    before = digests(scene / "images")
    if case == "render cameras into images":  # (no --scene: the folder the model trained on, as model.json says)
        model = tmp_path / "model"
        assert main(["train", str(scene), "--out", str(model), *QUICK_TRAIN]) == 0
    argv = {"render into images": ["render", model, "--scene", scene, "--views", "all", "--out", scene / "images"],
            "eval into images": ["eval", model, "--scene", scene, "--views", "all", "--out", scene / "images"],
            "render from inside images": ["render", model, "--scene", "..", "--views", "all", "--out", "."],
            "render cameras into images": ["render", model, "--cameras",
                                           pinhole_json(tmp_path / "cams.json", model, ["view_00"]),
                                           "--out", scene / "images"]}[case]
    if case == "render from inside images":
        monkeypatch.chdir(scene / "images")
    expect_error([*argv, "--pixel-samples", "1"], capfd, record_property, "the scene's photos",
                 "give --out another folder")
    assert digests(scene / "images") == before


@pytest.mark.parametrize("command", ["render", "eval"])
def test_renders_never_replace_another_photo_folder_of_the_scene(command, model, tiny_scene, tmp_path, capfd,
                                                                 record_property):
    """A scene with LLFF-style copies beside the photos the model read (images_2/): those are the
    scene's photos too (a model trained on fern's images_8 had rendered over images_16's)."""
    scene = tmp_path / "scene"
    shutil.copytree(tiny_scene, scene)
    shutil.copytree(scene / "images", scene / "images_2")
    before = digests(scene / "images_2")
    argv = [command, model, "--scene", scene, "--views", "all", "--out", scene / "images_2", "--pixel-samples", "1"]
    expect_error(argv, capfd, record_property, "the scene's photos", "give --out another folder")
    assert digests(scene / "images_2") == before


def test_eval_of_a_model_file_writes_beside_it(model, tiny_scene, tmp_path, capfd):
    """eval given the model file itself (model.pt): its eval/ beside it (it had failed at the end,
    after scoring, on 'model.pt/eval: Not a directory')."""
    folder = Path(shutil.copytree(model, tmp_path / "model"))
    code, _, err = run_cli(["eval", folder / "model.pt", "--scene", tiny_scene, "--pixel-samples", "1"], capfd)
    assert code == 0, err
    assert (folder / "eval" / "eval.json").is_file()


# ----------------------------------------------------------------------------- a rig's views


@pytest.fixture(scope="module")
def rig(tiny_scene, tmp_path_factory) -> tuple[Path, Path]:
    """The tiny scene as a rig names its photos (left/f1.png, right/f1.png, ...) and a model of it."""
    scene = tmp_path_factory.mktemp("rig") / "scene"
    shutil.copytree(tiny_scene, scene)
    names = [f"{'left' if i % 2 == 0 else 'right'}/f{i // 2}.png" for i in range(9)]
    for i, name in enumerate(names):
        (scene / "images" / name).parent.mkdir(exist_ok=True)
        (scene / "images" / f"view_{i:02d}.png").rename(scene / "images" / name)
    points = np.column_stack([np.random.default_rng(7).uniform(-0.8, 0.8, size=(60, 2)), np.zeros(60)])
    points[:, 2] = 3.0 + 0.3 * points[:, 0]
    shutil.rmtree(scene / "sparse")
    write_colmap_model(scene / "sparse" / "0", tiny_camera(), tiny_poses(), names, points)
    model = scene.parent / "model"
    assert main(["train", str(scene), "--out", str(model), *QUICK_TRAIN]) == 0
    return scene, model


def test_a_rig_s_views_that_share_a_stem_each_get_their_own_render(rig, tmp_path, capfd):
    scene, model = rig
    code, out, err = run_cli(["render", model, "--scene", scene, "--views", "all", "--out", tmp_path / "all",
                              "--depth", "--pixel-samples", "1"], capfd)
    assert code == 0, err
    stems = ["left_f0", "right_f0", "left_f1", "right_f1", "left_f2", "right_f2", "left_f3", "right_f3", "left_f4"]  # (every view
    # by its folder and stem, left/f4.png too, whose stem no other photo has)
    assert sorted(p.name for p in (tmp_path / "all").iterdir()) == sorted(
        f"{stem}{end}" for stem in stems for end in (".png", "_depth.png", "_depth.npy"))
    # the same name whichever views are rendered with it, and eval's the same as render's
    assert run_cli(["render", model, "--scene", scene, "--views", "right/f1.png", "--out", tmp_path / "one",
                    "--pixel-samples", "1"], capfd)[0] == 0
    assert sorted(p.name for p in (tmp_path / "one").iterdir()) == ["right_f1.png"]
    code, out, err = run_cli(["eval", model, "--scene", scene, "--views", "all", "--out", tmp_path / "eval",
                              "--pixel-samples", "1"], capfd)
    assert code == 0, err
    assert sorted(p.name for p in (tmp_path / "eval").glob("*.png")) == sorted(f"{stem}.png" for stem in stems)
    for stem in stems:  # (each file is its own view's render, not another's written over it)
        assert np.array_equal(np.asarray(Image.open(tmp_path / "eval" / f"{stem}.png")),
                              np.asarray(Image.open(tmp_path / "all" / f"{stem}.png")))


def test_a_rig_s_photo_folder_is_refused_as_out(rig, capfd, record_property):
    scene, model = rig
    before = digests(scene / "images")
    expect_error(["render", model, "--scene", scene, "--views", "all", "--out", scene / "images" / "left"], capfd,
                 record_property, "the scene's photos")
    assert digests(scene / "images") == before


# ----------------------------------------------------------------------------- whole files


def test_renders_and_eval_files_are_replaced_whole(model, tiny_scene, tmp_path, capfd):
    """Each file is written beside its final name and then replaces it in one step (a new inode),
    as checkpoints are: a render stopped while writing had left a truncated PNG under the
    finished one's name (PIL wrote into the file in place)."""
    render = ["render", model, "--scene", tiny_scene, "--views", "view_00,view_08", "--out", tmp_path / "r",
              "--depth", "--exr", "--pixel-samples", "1"]
    evaluate = ["eval", model, "--scene", tiny_scene, "--out", tmp_path / "e", "--pixel-samples", "1"]
    for argv in (render, evaluate):
        assert run_cli(argv, capfd)[0] == 0
    folders = [tmp_path / "r", tmp_path / "e"]
    first = {p: p.stat().st_ino for folder in folders for p in folder.iterdir()}
    assert {p.name for p in first} >= {"view_00.png", "view_00_depth.npy", "view_00_depth.png", "view_00.exr",
                                        "eval.json", "eval.csv"}
    held = {p: open(p, "rb") for p in first}  # (a reader of the earlier files)
    try:
        for argv in (render, evaluate):
            assert run_cli(argv, capfd)[0] == 0
        for path, inode in first.items():
            assert path.stat().st_ino != inode, f"{path.name} was written in place"
    finally:
        for handle in held.values():
            handle.close()
    assert not hidden_leftovers(tmp_path)


def test_a_render_stopped_by_sigterm_says_one_line_and_leaves_whole_files(model, tmp_path):
    """SIGTERM (kill, a scheduler's time limit) as a render writes: `import pycolmap` had put
    glog's handler on SIGTERM, which printed a 34-line C stack dump."""
    cameras = pinhole_json(tmp_path / "cams.json", model, ["big_a", "big_b"], width=1200, height=900)
    out = tmp_path / "out"
    process = cli_process(["render", model, "--cameras", cameras, "--out", out, "--depth", "--pixel-samples", "1"],
                          stderr=subprocess.PIPE)
    deadline = time.monotonic() + 120
    while not (out / "big_a.png").exists() and process.poll() is None and time.monotonic() < deadline:
        time.sleep(0.001)
    process.send_signal(signal.SIGTERM)  # (as the first camera's files are written; the second is to come)
    _, err = process.communicate(timeout=120)
    assert process.returncode == 128 + signal.SIGTERM, err
    assert err.strip().splitlines() == ["stopped by SIGTERM"]
    for path in out.iterdir():  # each file there is whole
        if path.suffix == ".png":
            Image.open(path).load()
        elif path.suffix == ".npy":
            assert np.load(path).shape == (900, 1200)
    assert not hidden_leftovers(out)


# ----------------------------------------------------------------------------- video


def read_until(process: subprocess.Popen, text: str, seconds: float = 120) -> str:
    """stderr read a character at a time until `text` shows (progress is drawn with \\r, no newline)."""
    seen, deadline = "", time.monotonic() + seconds
    while text not in seen and time.monotonic() < deadline:
        char = process.stderr.read(1)
        if not char:
            break
        seen += char
    return seen


def frame_count(path: Path) -> int:
    with av.open(str(path)) as container:
        return sum(1 for _ in container.decode(video=0))


@pytest.mark.parametrize("stop", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_a_video_stopped_part_way_keeps_the_earlier_video(stop, model, tmp_path, capfd):
    """A video stopped part-way had replaced an earlier one with a 48-byte stub (SIGTERM, with a
    C stack dump) or with a shorter video that played as finished (Ctrl-C)."""
    target = tmp_path / "spiral.mp4"
    assert run_cli(["video", model, "--out", target, "--frames", "3", "--pixel-samples", "1"], capfd)[0] == 0
    earlier = target.read_bytes()
    process = cli_process(["video", model, "--out", target, "--frames", "100000", "--pixel-samples", "1"],
                          stderr=subprocess.PIPE)
    seen = read_until(process, "frame 5/")
    assert "frame 5/" in seen, seen
    process.send_signal(stop)
    _, rest = process.communicate(timeout=120)
    lines = [line for line in (seen + rest).replace("\r", "\n").splitlines() if line and not line.startswith("frame ")]
    assert process.returncode == 128 + stop, lines
    assert target.read_bytes() == earlier
    assert len(lines) == 1 and lines[0].startswith("stopped by SIGTERM: " if stop == signal.SIGTERM else "interrupted: ")
    assert "unfinished" in lines[0] and f"the earlier {target} is kept" in lines[0], lines[0]
    partial = tmp_path / "spiral.partial.mp4"
    if "the frames made are in" in lines[0]:  # (stopped between two frames, as nearly always: they are kept)
        assert lines[0].endswith(f"the frames made are in {partial}.")
        said = int(lines[0].split(" frame(s)")[0].rsplit(" ", 1)[1])
        assert said >= 5 and frame_count(partial) == said
    else:
        assert not partial.exists()
    assert not hidden_leftovers(tmp_path)


# ----------------------------------------------------------------------------- ~ and eval/


def test_tilde_is_the_home_folder_for_every_output(model, tiny_scene, tmp_path, monkeypatch, capfd):
    home, here = tmp_path / "home", tmp_path / "here"
    here.mkdir()
    shutil.copytree(model, home / "model")
    pinhole_json(home / "cams.json", model, ["novel"])
    monkeypatch.setenv("HOME", str(home))
    monkeypatch.chdir(here)
    for argv in (["render", "~/model", "--scene", tiny_scene, "--views", "view_00", "--out", "~/views"],
                 ["render", "~/model", "--cameras", "~/cams.json", "--out", "~/cameras"],
                 ["eval", "~/model", "--scene", tiny_scene],
                 ["video", "~/model", "--out", "~/spiral.mp4", "--frames", "2"]):
        code, out, err = run_cli([*argv, "--pixel-samples", "1"], capfd)
        assert code == 0, err
        assert "~" not in out + err
    assert (home / "views" / "view_00.png").is_file() and (home / "cameras" / "novel.png").is_file()
    assert (home / "model" / "eval" / "eval.json").is_file() and (home / "spiral.mp4").is_file()
    assert list(here.iterdir()) == []  # (no folder named ~ here)


@pytest.mark.parametrize("given", ["scene", "photos", "empty"])
def test_eval_of_a_folder_that_is_not_a_model_leaves_nothing_in_it(given, tiny_scene, tmp_path, capfd,
                                                                   record_property):
    scene = tmp_path / "scene"
    shutil.copytree(tiny_scene, scene)
    folder = {"scene": scene, "photos": scene / "images", "empty": tmp_path / "empty"}[given]
    folder.mkdir(exist_ok=True)
    before = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*"))
    expect_error(["eval", folder, "--scene", scene], capfd, record_property)
    expect_error(["eval", folder, "--scene", scene, "--out", tmp_path / "scores"], capfd, record_property)
    assert sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*")) == before


def test_a_video_killed_outright_leaves_no_temporary_after_the_next(tmp_path):
    """SIGKILL gives no chance to clean up: the killed run's hidden temporary stays until the next
    run writing that video, which removes it (they had stayed for good, as big as their frames);
    a live run's temporary is left alone."""
    import os

    from neulf_core.video import write_video

    frame = np.zeros((16, 16, 3), np.uint8)
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    abandoned = tmp_path / f".spiral.{dead.pid}.0badf00d.tmp.mp4"
    live = tmp_path / f".spiral.{os.getppid()}.1badf00d.tmp.mp4"
    for leftover in (abandoned, live):
        leftover.write_bytes(b"frames of a run")
    write_video([frame] * 3, tmp_path / "spiral.mp4", fps=10)
    assert not abandoned.exists() and live.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == [live.name, "spiral.mp4"]

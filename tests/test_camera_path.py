"""A camera path's frames that see past the capture: counted before rendering, as the renderer
counts them, and the lens that keeps every frame inside (Blender's Spiral Camera Path, and the
CLI's video).  A wide lens on a spiral had been said only frame by frame at render time."""

from __future__ import annotations

import re

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from neulf_core.paths import (LONGEST_LENS_FACTOR, lens_keeping_inside, past_capture_warning,  # noqa: E402
                              share_past_capture, spiral_path)
from neulf_core.render import PAST_CAPTURE_FRACTION, LightField  # noqa: E402


@pytest.fixture(scope="module")
def tiny_model(tiny_scene, tmp_path_factory):
    from neulf_core.train import TrainConfig, train

    folder = tmp_path_factory.mktemp("path_model") / "model"
    train(tiny_scene, folder, TrainConfig(steps=3, validate_seconds=1e9, checkpoint_seconds=1e9))
    return folder


def rig(light_field):
    meta = light_field.meta["rig"]
    return np.asarray(meta["centres"]), np.asarray(meta["K"]), int(meta["width"]), int(meta["height"])


def wider(K, factor: float) -> np.ndarray:
    """K with its focal length divided by `factor`: a wider lens on the same sensor."""
    K = np.array(K, np.float64)
    K[0, :2] /= factor
    K[1, 1] /= factor
    return K


def test_the_share_is_the_renderers_own_count(tiny_model):
    """On a camera no wider than the check's grid, the share past the capture is exactly the
    renderer's: its warning's percentage for the same frame."""
    light_field = LightField.load(tiny_model, "cpu")
    centres, K, width, height = rig(light_field)
    assert width <= 64  # (the check's grid is the image itself)
    poses = spiral_path(light_field.slab, centres, frames=6)
    wide = wider(K, 3.0)
    shares = share_past_capture(light_field.slab, wide, width, height, poses)
    assert shares.max() > PAST_CAPTURE_FRACTION  # (the wide lens sees past the capture)
    for (R, t), share in zip(poses, shares):
        warnings = light_field.render(wide, width, height, R, t, depth=False, pixel_samples=1).warnings
        said = [re.match(r"(\d+)% of the rays leave the region", note) for note in warnings]
        said = [int(match.group(1)) for match in said if match]
        if share > PAST_CAPTURE_FRACTION:
            assert said == [round(100 * share)], (warnings, share)
        else:
            assert said == [], (warnings, share)


def test_the_lens_that_keeps_the_path_inside_is_the_shortest(tiny_model):
    light_field = LightField.load(tiny_model, "cpu")
    slab = light_field.slab
    centres, K, width, height = rig(light_field)
    poses = spiral_path(slab, centres, frames=12)
    assert share_past_capture(slab, K, width, height, poses).max() <= PAST_CAPTURE_FRACTION  # (the rig's own lens)
    assert lens_keeping_inside(slab, K, width, height, poses, PAST_CAPTURE_FRACTION) == 1.0
    wide = wider(K, 4.0)
    factor = lens_keeping_inside(slab, wide, width, height, poses, PAST_CAPTURE_FRACTION)
    assert factor is not None and 1.0 < factor <= 4.0 * 1.01, factor
    assert share_past_capture(slab, wider(wide, 1 / factor), width, height, poses).max() <= PAST_CAPTURE_FRACTION
    shorter = factor / 1.03  # (found to 1 %: a lens 3 % shorter sees past again)
    assert share_past_capture(slab, wider(wide, 1 / shorter), width, height, poses).max() > PAST_CAPTURE_FRACTION
    # A path far off to the side of the capture: no lens keeps it inside.
    side = [(R, t - R @ (30.0 * slab.rotation[0])) for R, t in poses]
    assert lens_keeping_inside(slab, K, width, height, side, PAST_CAPTURE_FRACTION) is None
    note = past_capture_warning(slab, K, width, height, side, lens_mm=50.0)
    assert f"not even a lens {LONGEST_LENS_FACTOR:g} times as long" in note, note


def test_a_long_path_is_checked_at_frames_spread_along_it(tiny_model):
    """`video --frames 100000` had checked every frame before its first one (minutes); a path
    longer than PATH_CHECK_FRAMES is checked at that many frames spread along it, its count said
    as about so many, and agrees with the whole path's share."""
    import time

    from neulf_core.paths import PATH_CHECK_FRAMES

    light_field = LightField.load(tiny_model, "cpu")
    slab = light_field.slab
    centres, K, width, height = rig(light_field)
    long_path = spiral_path(slab, centres, frames=20 * PATH_CHECK_FRAMES)
    wide = wider(K, 3.0)
    started = time.perf_counter()
    note = past_capture_warning(slab, wide, width, height, long_path)
    assert time.perf_counter() - started < 20  # (every frame: 20 times as many checks)
    whole = int((share_past_capture(slab, wide, width, height, long_path) > PAST_CAPTURE_FRACTION).sum())
    said = int(re.match(r"about (\d+) of (\d+) frames", note).group(1))
    assert abs(said - whole) <= 0.02 * len(long_path), (said, whole)
    assert re.match(r"\d+ of 12 frames", past_capture_warning(slab, wide, width, height,
                                                              spiral_path(slab, centres, frames=12)))


def test_spiral_for_blender_names_the_lens(tiny_model, record_property):
    """Blender's Spiral Camera Path sends the camera that will fly it: a wide one is told which
    frames see past the capture and the lens (mm) that keeps them inside."""
    from neulf_core.worker import Service

    light_field = LightField.load(tiny_model, "cpu")
    _centres, K, width, height = rig(light_field)
    service = Service()
    own = {"K": K.tolist(), "width": width, "height": height, "lens_mm": 50.0}
    assert service.spiral(str(tiny_model), 12, camera=own)["warnings"] == []
    wide = dict(own, K=wider(K, 4.0).tolist(), lens_mm=12.5)
    warnings = service.spiral(str(tiny_model), 12, camera=wide)["warnings"]
    assert len(warnings) == 1 and "frames look past the region the photos captured" in warnings[0], warnings
    lens = int(re.search(r"a lens of (\d+) mm or longer \(this camera's: 12.5 mm\)", warnings[0]).group(1))
    assert 12.5 < lens <= 51, warnings  # (the rig's own focal length, 4 x 12.5 mm, keeps it inside)
    record_property("message", warnings[0])
    assert service.spiral(str(tiny_model), 12)["warnings"] == []  # (no camera given: nothing to check)


def test_video_says_frames_past_the_capture(tiny_model, tmp_path, monkeypatch, capfd, record_property):
    import neulf_core.cli as cli

    light_field = LightField.load(tiny_model, "cpu")
    centres, K, width, height = rig(light_field)
    out = tmp_path / "path.mp4"
    args = ["video", str(tiny_model), "--out", str(out), "--frames", "4", "--pixel-samples", "1"]
    assert cli.main(args) == 0
    assert "look past" not in capfd.readouterr().err  # (the rig's own lens)
    monkeypatch.setattr(cli, "_rig_from_meta", lambda _lf: (centres, wider(K, 4.0), width, height))
    assert cli.main(args) == 0
    err = capfd.readouterr().err
    assert err.count("frames look past the region the photos captured") == 1, err
    record_property("message", next(line for line in err.splitlines() if "look past" in line))


DAMAGED_RIGS = {
    "text for centres": {"centres": "abc", "K": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "width": 4, "height": 3},
    "a number for K": {"centres": [[0, 0, 0]], "K": 5, "width": 4, "height": 3},
    "text for a size": {"centres": [[0, 0, 0]], "K": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "width": "w", "height": 3},
    "no height": {"centres": [[0, 0, 0]], "K": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "width": 4, "height": None},
    "NaN centres": {"centres": [[float("nan"), 0, 0]], "K": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "width": 4, "height": 3},
    "not a dict": [1, 2, 3],
}


@pytest.mark.parametrize("rig", list(DAMAGED_RIGS))
def test_a_damaged_rig_is_said_in_one_line(rig):
    from neulf_core.errors import NeulfError
    from neulf_core.paths import saved_rig

    with pytest.raises(NeulfError, match="camera rig .* is damaged; retrain the model"):
        saved_rig({"rig": DAMAGED_RIGS[rig]})


def test_video_of_a_model_whose_rig_is_damaged_ends_in_one_line(tiny_model, tmp_path, capfd, record_property):
    """A model file whose rig was damaged (kept types it cannot have) had ended the video in int()'s traceback."""
    import shutil

    import neulf_core.cli as cli

    model = tmp_path / "model"
    shutil.copytree(tiny_model, model)
    for name in ("model.pt", "checkpoint.pt"):
        if (model / name).exists():
            payload = torch.load(model / name, map_location="cpu", weights_only=False)
            payload["rig"] = DAMAGED_RIGS["text for a size"]
            torch.save(payload, model / name)
    capfd.readouterr()
    assert cli.main(["video", str(model), "--out", str(tmp_path / "v.mp4"), "--frames", "2"]) == 2
    err = capfd.readouterr().err
    assert err.startswith("error: this model's camera rig") and err.count("\n") == 1 and "Traceback" not in err, err
    record_property("message", err.strip())

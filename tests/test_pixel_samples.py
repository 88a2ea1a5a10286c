"""Pixel samples (render.PIXEL_SAMPLES): a finished render's pixel is the mean of the field
over a grid of points in it.  Checked against renders of single points moved by hand, for the
pinhole path (Blender's cameras) and a registered view's own camera model (evaluation)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from neulf_core.errors import NeulfError
from neulf_core.rays import shifted_K, single_pixel_K
from neulf_core.render import (DEFAULT_PIXEL_SAMPLES, PIXEL_SAMPLES, SAMPLE_CONTRAST, LightField,
                               pixel_offsets)
from neulf_core.scene import load_scene
from neulf_core.train import TrainConfig, train


@pytest.fixture(scope="module")
def light_field(tiny_scene, tmp_path_factory):
    model_dir = tmp_path_factory.mktemp("pixel_samples")
    train(tiny_scene, model_dir, TrainConfig(steps=40, batch_size=512, seed=0, validate_seconds=1e9,
                                             checkpoint_seconds=1e9, device="cpu"))
    light_field = LightField.load(model_dir, "cpu", precision="full")
    light_field.model_dir = model_dir  # for the command-line test
    return light_field


def test_pixel_offsets_are_the_cell_centres_of_a_square_grid_over_the_central_footprint():
    assert np.array_equal(pixel_offsets(1), [[0.0, 0.0]])
    whole = pixel_offsets(4, footprint=1.0)
    assert sorted(map(tuple, whole)) == [(-0.25, -0.25), (-0.25, 0.25), (0.25, -0.25), (0.25, 0.25)]
    assert np.allclose(pixel_offsets(4), 0.5 * whole)  # the default footprint: the central half of the pixel
    nine = pixel_offsets(9, footprint=1.0)
    assert np.allclose(nine.mean(0), 0.0) and np.isclose(np.abs(nine).max(), 1 / 3)
    for wrong in (3, -4, 0):
        with pytest.raises(NeulfError, match="one of 1, 4, 9, 16"):
            pixel_offsets(wrong)
    with pytest.raises(NeulfError, match="from 0 to 1"):
        pixel_offsets(4, footprint=1.5)


def test_shifted_K_moves_the_pixel_centres_right_and_down(light_field, tiny_scene):
    view, K, width, height = _registered(tiny_scene)
    moved = shifted_K(K, (0.25, -0.5))
    assert (moved[0, 2], moved[1, 2]) == (K[0, 2] - 0.25, K[1, 2] + 0.5) and np.array_equal(moved[:2, :2], K[:2, :2])
    assert np.allclose(single_pixel_K(K, 10.75, 3.25), shifted_K(K, (10.25, 2.75)))
    # One whole pixel right / down: the image of the next column / row (the grid of points is
    # symmetric, so only this catches a sign or an x-y mix-up).
    still = light_field.render(K, width, height, view.R, view.t, depth=False).rgb
    right = light_field.render(shifted_K(K, (1.0, 0.0)), width, height, view.R, view.t, depth=False).rgb
    down = light_field.render(shifted_K(K, (0.0, 1.0)), width, height, view.R, view.t, depth=False).rgb
    assert np.allclose(right[:, :-1], still[:, 1:], atol=1e-5) and np.allclose(down[:-1], still[1:], atol=1e-5)


def _registered(tiny_scene):
    view = load_scene(tiny_scene).views[1]
    camera = view.scaled_camera(1.0)
    return view, camera.calibration_matrix(), int(camera.width), int(camera.height)


def test_render_takes_the_mean_over_the_pixel_and_keeps_the_centre_depth(light_field, tiny_scene):
    view, K, width, height = _registered(tiny_scene)
    centre = light_field.render(K, width, height, view.R, view.t, depth=True)
    four = light_field.render(K, width, height, view.R, view.t, depth=True, pixel_samples=4, sample_contrast=0)
    by_hand = np.mean([light_field.render(shifted_K(K, offset), width, height, view.R, view.t, depth=False).rgb
                       for offset in pixel_offsets(4)], axis=0)
    assert np.allclose(four.rgb, by_hand, atol=1e-6)
    assert four.refined == 1.0 and centre.refined == 0.0
    assert np.abs(four.rgb - centre.rgb).max() > 1e-4  # the points do differ
    assert np.array_equal(four.depth, centre.depth, equal_nan=True) and np.array_equal(four.valid, centre.valid)
    assert four.warnings == centre.warnings
    # Turned until part of the picture misses the slab: the mask and the warnings stay the centre ray's.
    turn = np.array([[np.cos(1.3), 0.0, np.sin(1.3)], [0.0, 1.0, 0.0], [-np.sin(1.3), 0.0, np.cos(1.3)]])
    R = turn @ view.R
    centre = light_field.render(K, width, height, R, view.t, depth=True)
    four = light_field.render(K, width, height, R, view.t, depth=True, pixel_samples=4, sample_contrast=0)
    assert 0 < centre.valid.sum() < centre.valid.size and centre.warnings
    assert np.array_equal(four.valid, centre.valid) and four.warnings == centre.warnings
    # The pixels whose rays miss the slab show the background colour, not what the field extrapolates
    # (the four-point render's edge pixels mix it with their points that do cross the slab).
    background = light_field.background.cpu().numpy()
    assert np.allclose(centre.rgb[~centre.valid], background)
    assert not np.allclose(centre.rgb[centre.valid], background)
    assert np.array_equal(four.depth, centre.depth, equal_nan=True)


def _contrast_by_hand(image: np.ndarray) -> np.ndarray:
    """Per pixel, the largest colour difference (over channels) from its four neighbours."""
    padded = np.pad(image, ((1, 1), (1, 1), (0, 0)), mode="edge")
    shifted = [padded[:-2, 1:-1], padded[2:, 1:-1], padded[1:-1, :-2], padded[1:-1, 2:]]
    return np.max([np.abs(image - other).max(axis=2) for other in shifted], axis=0)


def test_the_points_go_only_to_pixels_whose_centre_colour_has_contrast(light_field, tiny_scene):
    view, K, width, height = _registered(tiny_scene)
    centre = light_field.render(K, width, height, view.R, view.t, depth=True)
    every = light_field.render(K, width, height, view.R, view.t, depth=True, pixel_samples=4, sample_contrast=0)
    contrast = _contrast_by_hand(centre.rgb)
    threshold = float(np.quantile(contrast, 0.6))  # (some pixels above it, some not)
    edges = contrast > threshold
    assert 0.2 < edges.mean() < 0.6
    renders = {"render": lambda chunk: light_field.render(K, width, height, view.R, view.t, depth=True, pixel_samples=4,
                                                          sample_contrast=threshold, chunk=chunk),
               "render_view": lambda chunk: light_field.render_view(view, depth=True, pixel_samples=4,
                                                                    sample_contrast=threshold, chunk=chunk)}
    for name, render in renders.items():
        for chunk in (None, 3 * width + 5):  # one band, and bands of 3 rows whose edge rows need the next band's
            some = render(chunk)
            assert np.allclose(some.rgb[edges], every.rgb[edges], atol=1e-5), name
            assert np.allclose(some.rgb[~edges], centre.rgb[~edges], atol=1e-5), name
            assert np.isclose(some.refined, edges.mean()), name
            assert np.allclose(some.depth, centre.depth, atol=1e-5, equal_nan=True) and np.array_equal(some.valid, centre.valid)
    # At the largest contrast no pixel takes the points: the one-point render.
    flat = light_field.render(K, width, height, view.R, view.t, depth=False, pixel_samples=4, sample_contrast=1.0)
    assert flat.refined == 0.0 and np.allclose(flat.rgb, centre.rgb, atol=1e-6)
    for wrong in (-0.1, 1.5, float("nan"), "0.02", True):
        with pytest.raises(NeulfError, match="sample contrast is a colour difference from 0"):
            light_field.render(K, width, height, view.R, view.t, pixel_samples=4, sample_contrast=wrong)


def test_a_registered_view_renders_the_same_points_through_its_own_camera(light_field, tiny_scene):
    view, K, width, height = _registered(tiny_scene)  # a pinhole: both paths see the same rays
    through_view = light_field.render_view(view, depth=True, pixel_samples=9)
    through_K = light_field.render(K, width, height, view.R, view.t, depth=True, pixel_samples=9)
    assert np.allclose(through_view.rgb, through_K.rgb, atol=1e-5)
    assert np.allclose(through_view.depth, through_K.depth, atol=1e-4, equal_nan=True)
    assert np.allclose(light_field.render_view(view, depth=False).rgb,
                       light_field.render(K, width, height, view.R, view.t, depth=False).rgb, atol=1e-5)


def test_a_refocused_render_takes_its_lens_samples_alone(light_field, tiny_scene):
    view, K, width, height = _registered(tiny_scene)
    depth = float(np.nanmedian(light_field.render(K, width, height, view.R, view.t).depth))
    options = dict(depth=False, focus_distance=depth, aperture=0.5)
    assert light_field._lens_plan(K, depth, 0.5, 64) is not None  # a blur wide enough for lens samples
    with pytest.raises(NeulfError, match="one of 1, 4, 9, 16"):  # still checked where the lens takes over
        light_field.render(K, width, height, view.R, view.t, pixel_samples=3, **options)
    assert np.array_equal(light_field.render(K, width, height, view.R, view.t, pixel_samples=4, **options).rgb,
                          light_field.render(K, width, height, view.R, view.t, **options).rgb)


def test_the_commands_render_and_score_four_points_by_default(light_field, tiny_scene, tmp_path, capfd):
    from PIL import Image

    from neulf_core.cli import main
    from neulf_core.images import save_rgb

    model = str(light_field.model_dir)
    view = load_scene(tiny_scene).view("view_00.png")
    for samples, folder in ((4, "default"), (1, "one")):
        extra = [] if samples == 4 else ["--pixel-samples", "1"]
        assert main(["render", model, "--scene", str(tiny_scene), "--views", "view_00", "--out", str(tmp_path / folder),
                     *extra]) == 0
        expected = light_field.render_view(view, depth=False, pixel_samples=samples).rgb
        save_rgb(tmp_path / f"{folder}_expected.png", expected)  # the same 8-bit rounding
        assert np.array_equal(np.asarray(Image.open(tmp_path / folder / "view_00.png")),
                              np.asarray(Image.open(tmp_path / f"{folder}_expected.png")))
    # --sample-contrast 0: the points in every pixel.
    assert main(["render", model, "--scene", str(tiny_scene), "--views", "view_00", "--out", str(tmp_path / "every"),
                 "--sample-contrast", "0"]) == 0
    save_rgb(tmp_path / "every_expected.png", light_field.render_view(view, depth=False, pixel_samples=4,
                                                                      sample_contrast=0).rgb)
    assert np.array_equal(np.asarray(Image.open(tmp_path / "every" / "view_00.png")),
                          np.asarray(Image.open(tmp_path / "every_expected.png")))
    assert main(["eval", model, "--scene", str(tiny_scene), "--out", str(tmp_path / "eval")]) == 0
    report = json.loads((tmp_path / "eval" / "eval.json").read_text())
    assert report["pixel_samples"] == 4 and report["sample_contrast"] == SAMPLE_CONTRAST
    capfd.readouterr()
    from neulf_core.cli import build_parser

    for command in ("render", "eval", "video"):  # the CLI spells the choices out (no torch import there)
        actions = {a.dest: a for a in build_parser()._subparsers._group_actions[0].choices[command]._actions}
        action = actions["pixel_samples"]
        assert tuple(action.choices) == PIXEL_SAMPLES and action.default is None  # (None: default_pixel_samples)
        assert actions["sample_contrast"].default == SAMPLE_CONTRAST
    assert main(["eval", model, "--scene", str(tiny_scene), "--pixel-samples", "3"]) != 0
    message = capfd.readouterr().err.strip().splitlines()
    assert len(message) == 1 and "--pixel-samples" in message[0] and "choose from 1, 4, 9, 16" in message[0]
    for wrong in ("-0.5", "2", "nan", "edges"):
        assert main(["eval", model, "--scene", str(tiny_scene), "--sample-contrast", wrong]) == 2
        message = capfd.readouterr().err.strip().splitlines()
        assert len(message) == 1 and "--sample-contrast" in message[0], message


def test_a_render_finer_than_the_trained_photos_takes_one_point_by_default(light_field, tiny_scene, tmp_path):
    """Where no count is asked, a camera that renders FINE_RENDER_SCALE times the trained
    resolution or finer takes the centre ray alone (the points gained 0.014 dB or less there);
    nearer the trained size it takes DEFAULT_PIXEL_SAMPLES; a count asked is taken as asked."""
    from neulf_core.cli import main
    from neulf_core.render import FINE_RENDER_SCALE

    view = load_scene(tiny_scene).view("view_00.png")
    camera = view.scaled_camera(light_field.trained_scale)
    K, width, height = np.array(camera.calibration_matrix()), int(camera.width), int(camera.height)

    def points(finer: float, asked=None) -> int:
        scaled = K * np.array([[finer], [finer], [1.0]])
        return light_field.render(scaled, round(width * finer), round(height * finer), view.R, view.t, depth=False,
                                  pixel_samples=asked).pixel_samples

    assert points(1.0) == DEFAULT_PIXEL_SAMPLES and points(FINE_RENDER_SCALE * 0.95) == DEFAULT_PIXEL_SAMPLES
    assert points(FINE_RENDER_SCALE) == 1 and points(2.0) == 1
    assert points(2.0, asked=4) == 4 and points(1.0, asked=1) == 1
    one = light_field.render(K * np.array([[2.0], [2.0], [1.0]]), width * 2, height * 2, view.R, view.t, depth=False)
    assert one.pixel_samples == 1 and one.refined == 0.0  # (the render's own default stays 1: an API caller's)
    assert light_field.render_view(view, 2.0 * light_field.trained_scale, depth=False, pixel_samples=None).pixel_samples == 1
    assert light_field.render_view(view, depth=False, pixel_samples=None).pixel_samples == DEFAULT_PIXEL_SAMPLES
    # eval at twice the trained size records the points it took
    assert main(["eval", str(light_field.model_dir), "--scene", str(tiny_scene), "--views", "view_00",
                 "--out", str(tmp_path / "eval")]) == 0
    assert json.loads((tmp_path / "eval" / "eval.json").read_text())["pixel_samples"] == DEFAULT_PIXEL_SAMPLES


def test_a_model_without_its_rigs_record_takes_the_default_points(light_field):
    """A model whose metadata lacks the trained camera (an older or hand-made one) keeps the
    default count rather than failing."""
    K = np.array([[1e6, 0, 10], [0, 1e6, 10], [0, 0, 1]])
    saved = light_field.meta.pop("rig")
    try:
        assert light_field.default_pixel_samples(K) == DEFAULT_PIXEL_SAMPLES
    finally:
        light_field.meta["rig"] = saved
    assert light_field.default_pixel_samples(K) == 1


def test_the_benchmark_blurs_as_it_says_and_tables_gains_per_seed(benchmark_script):
    bench = benchmark_script("pixel_samples")
    flat = np.full((5, 6, 3), 0.4)
    assert np.allclose(bench.blurred(flat), flat)
    dot = np.zeros((5, 5, 3))
    dot[2, 2] = 1.0
    spread = bench.blurred(dot)[..., 0]
    assert np.isclose(spread[2, 2], 0.75 ** 2) and np.isclose(spread[1, 2], 0.75 * 0.125)
    assert np.isclose(spread.sum(), 1.0)

    def row(seed, rendering, value, seconds=1.0):
        return {"configuration": "scene", "seed": seed, "view": "v", "rendering": rendering,
                "samples": int(rendering) if rendering.isdigit() else 1, "psnr": value, "ssim": 0.9,
                "render_seconds": seconds, "width": 4, "height": 3}

    rows = [row(0, "1", 30.0), row(0, "4", 30.5, 4.0), row(1, "1", 31.0), row(1, "4", 30.9, 4.4),
            row(0, bench.BLURRED, 29.0, float("nan")), row(1, bench.BLURRED, 30.0, float("nan"))]
    text = bench.table(rows)
    assert "30.70 (sd 0.200), +0.20 dB" in text and "x4.2 time" in text and "-1.00 dB" in text
    assert "4 points beat 1 point in 1 of 2 models" in text


def test_the_benchmark_plans_the_other_real_scenes_and_names_a_missing_one(benchmark_script, tmp_path, monkeypatch):
    bench = benchmark_script("pixel_samples")
    monkeypatch.setitem(bench.OTHER_SCENES, "fern", (tmp_path, 0.5))
    args = bench.parse_args(["--seeds", "0-2", "--steps", "50"])
    jobs = bench.other_scene_jobs(["fern"], args)["fern"]
    assert [job.seed for job in jobs] == [0, 1, 2] and {(job.path, job.scale, job.steps) for job in jobs} == {
        (str(tmp_path), 0.5, 50)}
    monkeypatch.setitem(bench.OTHER_SCENES, "fern", (tmp_path / "missing", 0.5))
    with pytest.raises(SystemExit, match="fern is not at"):
        bench.other_scene_jobs(["fern"], args)


def test_the_contrast_benchmark_tables_each_way_against_one_point_and_every_pixel(benchmark_script, tmp_path):
    bench = benchmark_script("sample_contrast")
    ways = bench.renderings()
    assert ways["1"] == (1, 0.0) and ways[bench.EVERY_PIXEL] == (4, 0.0)
    assert [ways[f"4, contrast {c:g}"] for c in bench.CONTRASTS] == [(4, c) for c in bench.CONTRASTS]

    def row(seed, rendering, value, seconds, refined):
        return {"configuration": "scene", "seed": seed, "view": "v", "rendering": rendering,
                "contrast": ways[rendering][1], "psnr": value, "ssim": 0.9, "render_seconds": seconds,
                "refined": refined, "width": 4, "height": 3}

    rows = []
    for seed, shift in ((0, 0.0), (1, 1.0)):
        rows += [row(seed, "1", 30.0 + shift, 1.0, 0.0), row(seed, bench.EVERY_PIXEL, 30.2 + shift, 4.0, 1.0)]
        rows += [row(seed, f"4, contrast {c:g}", 30.2 + shift - 0.01 * i, 2.0 - 0.2 * i, 0.3 - 0.05 * i)
                 for i, c in enumerate(bench.CONTRASTS)]
    text = bench.table(rows)
    assert "| scene | 1 | 31.00 dB, 1.00 s | +0.200 dB, x4.00 time, 100 % of pixels | +0.200 dB, x2.00 time, 30 % of pixels" in text
    assert f"- 4, contrast {bench.CONTRASTS[1]:g}: against the points in every pixel -0.010 dB on average" in text
    assert "at x0.45 the time (median); every pixel's points gain +0.200 dB over one." in text
    bench.chart(rows, tmp_path / "chart.png")
    assert (tmp_path / "chart.png").stat().st_size > 0

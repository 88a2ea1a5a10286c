"""The speed benchmarks end to end on the tiny scene: benchmarks/train_step_time.py (both Adam
variants train, a CSV row per run, --append adds to it) and benchmarks/sweep_time.py (the
depth teacher's sweep timed, its targets' checksum the same on every repeat), and the others
that time code: setup_time.py (each checkout's own code), jpeg_half_decode.py, train_scale.py,
viewport_preview.py (Blender's viewport preview through both of the extension's routes), same_weights.py
(whether two checkouts train to the same bits)."""

from __future__ import annotations

import csv
import importlib.util
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def load(name: str):
    spec = importlib.util.spec_from_file_location(name, REPO / "benchmarks" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_train_step_time_both_variants_and_append(tiny_scene, tmp_path, capsys):
    bench = load("train_step_time")
    out = tmp_path / "times.csv"
    common = ["--scene", str(tiny_scene), "--scale", "1", "--steps", "3", "--repeats", "1", "--out", str(out)]
    bench.main(common)
    bench.main([*common, "--threads", "2", "--append"])
    rows = list(csv.DictReader(open(out)))
    assert [r["variant"] for r in rows] == ["fused", "loop", "fused", "loop"]
    assert all(r["steps"] == "3" and float(r["ms_per_step"]) > 0 for r in rows)
    assert [r["machine"].endswith(f"cpu ({n} threads)") for r, n in zip(rows, (1, 1, 2, 2))] == [True] * 4
    assert "fused / loop" in capsys.readouterr().out


def test_sweep_time_appends_labelled_runs_with_one_checksum(tiny_scene, tmp_path, capsys):
    bench = load("sweep_time")
    out = tmp_path / "sweep.csv"
    bench.main(["--scene", str(tiny_scene), "--scale", "1", "--repeats", "2", "--label", "a", "--out", str(out)])
    bench.main(["--scene", str(tiny_scene), "--scale", "1", "--repeats", "1", "--label", "b", "--out", str(out)])
    rows = list(csv.DictReader(open(out)))
    assert [r["label"] for r in rows] == ["a", "a", "b"] and all(float(r["seconds"]) > 0 for r in rows)
    assert len({r["checksum"] for r in rows}) == 1  # the same targets every time
    assert "median" in capsys.readouterr().out


def test_render_fps_times_every_variant_and_appends(tiny_scene, tmp_path, capsys):
    from neulf_core.train import TrainConfig, train

    model = tmp_path / "model"
    train(tiny_scene, model, TrainConfig(steps=5, batch_size=256, validate_seconds=1e9, checkpoint_seconds=1e9, device="cpu"))
    bench = load("render_fps")
    out = tmp_path / "fps.csv"
    common = ["--scene", str(tiny_scene), "--model", f"m={model}", "--width", "40", "--height", "30",
              "--device", "cpu", "--repeats", "2", "--out", str(out)]
    bench.main([*common, "--precision", "full", "--chunks", "64,4096"])
    bench.main([*common, "--precision", "half", "--pixel-samples", "1,4"])
    rows = list(csv.DictReader(open(out)))
    assert [r["variant"] for r in rows] == [
        "m, full (full), rgb, chunk 64", "m, full (full), rgb+depth, chunk 64",
        "m, full (full), rgb, chunk 4096", "m, full (full), rgb+depth, chunk 4096",
        "m, half (half), rgb", "m, half (half), rgb+depth",
        "m, half (half), rgb, 4 points a pixel", "m, half (half), rgb+depth, 4 points a pixel"]
    assert all(r["resolution"] == "40x30" and float(r["fps"]) > 0 for r in rows)
    assert "frames per second" in capsys.readouterr().out


def test_gpu_profile_writes_both_tables(tiny_scene, tmp_path, capsys):
    bench = load("gpu_profile")
    bench.main(["--scene", str(tiny_scene), "--scale", "1", "--steps", "12", "--device", "cpu", "--width", "40",
                "--height", "30", "--frames", "2", "--out", str(tmp_path)])
    train_text = (tmp_path / "profile_train.txt").read_text()
    assert train_text.startswith("6 steps,") and "by self CPU time" in train_text
    assert "aten::" in (tmp_path / "profile_render.txt").read_text()
    assert "ms per step" in capsys.readouterr().out


def test_speed_accuracy_reads_a_batch_from_the_method_name():
    bench = load("speed_accuracy")
    assert bench.split_method("fast@65536") == ("fast", 65536)
    assert bench.split_method("authors") == ("authors", None)


def test_side_by_side_trains_both_settings_of_a_pair_and_scores_them(tiny_scene, tmp_path, capsys):
    """benchmarks/side_by_side.py end to end on the tiny scene (3 steps a run, pinned cores):
    one CSV row per setting, each trained as its JSON says, and the pair's change printed."""
    import os

    import pytest

    bench = load("side_by_side")
    bench.SCENES[tiny_scene.name] = (1.0, None)
    out = tmp_path / "sub" / "pairs.csv"
    bench.main(["--scenes", tiny_scene.name, "--data", str(tiny_scene.parent), "--steps", "3", "--seeds", "0",
                "--baseline", 'coarse={"field_overrides": {"geometry_spatial_res": [4, 8]}, "point_depth": false}',
                "--candidate", 'two={"members": 2}', "--out", str(out)])
    rows = list(csv.DictReader(open(out)))
    assert [(r["setting"], r["seed"], r["steps"]) for r in rows] == [("coarse", "0", "3"), ("two", "0", "3")]
    assert [r["members"] for r in rows] == ["1", "2"]  # the members each model trained
    assert all(0 < float(r["psnr"]) < 100 for r in rows)
    if len(os.sched_getaffinity(0)) > 1:
        assert rows[0]["core"] != rows[1]["core"]  # each run pinned to a core of its own
    printed = capsys.readouterr().out
    assert f"{tiny_scene.name}: mean change" in printed and "| coarse | two |" in printed
    assert "| 3 / 3 | 1 / 2 |" in printed  # steps, then members, of the pair
    assert bench.parse_setting('off={"point_depth": false}') == ("off", {"point_depth": False})
    for wrong in ("no-equals-sign", "x=[1]", "x={bad json"):
        with pytest.raises(SystemExit):
            bench.parse_setting(wrong)
    with pytest.raises(SystemExit):
        bench.main(["--scenes", "nowhere", "--baseline", "a={}"])
    assert load("point_depth").main.__module__ == "side_by_side"  # the same script, its two settings fixed


def test_side_by_side_trains_a_setting_with_another_checkouts_code(tiny_scene, tmp_path):
    """A setting's "checkout" runs that setting through the other checkout's own copy of the
    script (here a stand-in that reports a fixed row), the other setting through this one's."""
    bench = load("side_by_side")
    bench.SCENES[tiny_scene.name] = (1.0, None)
    other = tmp_path / "other"
    (other / "benchmarks").mkdir(parents=True)
    (other / "benchmarks" / "side_by_side.py").write_text(
        "import json, sys\n"
        "scene, images, scale, budget, seed, options, device, folder = json.loads(sys.argv[sys.argv.index('--child') + 1])\n"
        "assert 'checkout' not in options and options == {'members': 1}\n"
        "print(json.dumps({'steps': budget['steps'] + 1000, 'train_seconds': 0.0, 'psnr': 12.5, 'ssim': 0.5,\n"
        "                  'point_rays': 0, 'members': 1, 'members_passes': '', 'texture_factor': ''}))\n")
    out = tmp_path / "versions.csv"
    bench.main(["--scenes", tiny_scene.name, "--data", str(tiny_scene.parent), "--steps", "3", "--seeds", "0",
                "--baseline", f'before={{"checkout": "{other}", "members": 1}}', "--candidate", 'after={"members": 1}',
                "--out", str(out)])
    rows = {r["setting"]: r for r in csv.DictReader(open(out))}
    assert (rows["before"]["steps"], rows["before"]["psnr"]) == ("1003", "12.5")  # the other checkout's run
    assert rows["after"]["steps"] == "3" and float(rows["after"]["psnr"]) != 12.5  # this checkout's


def test_side_by_side_trains_the_auto_preset_as_the_command_line_does(tiny_scene, tmp_path):
    """`{"preset": "auto"}` searches the texture size first (autosize.train_auto), and the row
    says the size it chose; the other presets' rows leave it empty."""
    bench = load("side_by_side")
    bench.SCENES[tiny_scene.name] = (1.0, None)
    out = tmp_path / "auto.csv"
    bench.main(["--scenes", tiny_scene.name, "--data", str(tiny_scene.parent), "--steps", "30", "--seeds", "0",
                "--baseline", 'fast={"members": 1}', "--candidate", 'auto={"preset": "auto", "members": 1}',
                "--out", str(out)])
    rows = {r["setting"]: r for r in csv.DictReader(open(out))}
    assert rows["fast"]["texture_factor"] == ""
    from neulf_core.autosize import FACTORS

    assert float(rows["auto"]["texture_factor"]) in FACTORS


def test_auto_search_trains_the_candidates_and_the_final_models(tiny_scene, tmp_path, capsys):
    """benchmarks/auto_search.py end to end on the tiny scene: each candidate texture as the
    search trains it, scored on the validation views (and, for the diagnosis, on the held-out
    ones), each final model on the held-out views, and the table of what the search would
    choose against the final model that scored best."""
    import json

    from neulf_core.autosize import validation_split
    from neulf_core.scene import load_scene
    from neulf_core.train import TrainConfig

    bench = load("auto_search")
    bench.SCENES[tiny_scene.name] = (1.0, None)
    out = tmp_path / "search.csv"
    bench.main(["--scenes", tiny_scene.name, "--data", str(tiny_scene.parent), "--steps", "40", "--curve", "6",
                "--factors", "1,0.5", "--out", str(out)])
    rows = list(csv.DictReader(open(out)))
    assert sorted((r["kind"], r["factor"], r["steps"]) for r in rows) == [
        ("candidate", "0.5", "6"), ("candidate", "1.0", "6"), ("final", "0.5", "24"), ("final", "1.0", "24")]  # 40 - 2 x 8
    _, validation, held = validation_split(load_scene(tiny_scene), TrainConfig())
    for row in rows:
        assert 0 < float(row["psnr"]) < 100
        if row["kind"] == "candidate":
            views = json.loads(row["view_psnr"])
            assert set(views) == {v.name for v in validation + held}
            assert float(row["psnr"]) == round(sum(views[v.name] for v in validation) / len(validation), 3)
        else:
            assert row["held_out_psnr"] == "" and row["view_psnr"] == ""
    from functools import partial

    halfway = partial(bench.halfway_validation_split, validation_split)  # the variant tried
    fit, views, _ = halfway(load_scene(tiny_scene), TrainConfig())
    assert [v.name for v in views] == ["view_04.png"] and len(fit) == 6 and "view_01.png" in {v.name for v in fit}
    finals = {float(r["factor"]): float(r["psnr"]) for r in rows if r["kind"] == "final"}
    printed = capsys.readouterr().out
    assert f"| model, 24 steps (held-out) | {finals[1.0]:.2f} |  | {finals[0.5]:.2f} | x{max(finals, key=finals.get):g} |" in printed


def test_setup_time_runs_each_checkout_in_turn(tiny_scene, tmp_path, capsys):
    """Each run is the training command in each checkout's own code (here a stand-in checkout
    whose package records what it was asked), the checkouts taking turns."""
    bench = load("setup_time")
    other = tmp_path / "other"
    (other / "neulf_core").mkdir(parents=True)
    (other / "neulf_core" / "__main__.py").write_text(
        "import sys, pathlib\n"
        f"with open({str(tmp_path / 'asked.txt')!r}, 'a') as f: f.write(' '.join(sys.argv[1:]) + '\\n')\n")
    out = tmp_path / "setup.csv"
    bench.main(["--scene", str(tiny_scene), "--scale", "1", "--run", "short=--steps 2", "--checkout", f"before={other}",
                "--checkout", f"after={REPO}", "--repeats", "2", "--out", str(out)])
    rows = list(csv.DictReader(open(out)))
    assert [(r["checkout"], r["repeat"]) for r in rows] == [("before", "0"), ("after", "0"), ("before", "1"), ("after", "1")]
    assert all(r["run"] == "short" and r["torch_threads"] == "1" and float(r["seconds"]) > 0 for r in rows)
    asked = (tmp_path / "asked.txt").read_text().splitlines()
    assert len(asked) == 2 and all(a.startswith(f"train {tiny_scene}") and a.endswith("--scale 1.0 --steps 2") for a in asked)
    assert "after median" in capsys.readouterr().out


def test_jpeg_half_decode_times_and_compares_whole_fractions(tmp_path, capsys):
    from PIL import Image
    import numpy as np

    bench = load("jpeg_half_decode")
    ys, xs = np.mgrid[0:192, 0:256]
    smooth = np.stack([xs, ys, (xs + ys) // 2], -1).astype(np.uint8)
    (tmp_path / "photos").mkdir()
    Image.fromarray(smooth).save(tmp_path / "photos" / "ramp.jpg", quality=92)
    Image.fromarray(smooth).save(tmp_path / "photos" / "ramp.png")  # not a JPEG: left out
    out = tmp_path / "decode.csv"
    bench.main(["--photos", str(tmp_path / "photos"), "--repeats", "1", "--label", "t", "--out", str(out)])
    rows = list(csv.DictReader(open(out)))
    assert [r["wanted"] for r in rows] == ["64x48", "32x24", "16x12"] and all(r["photo"] == "ramp.jpg" for r in rows)
    assert all(float(r["psnr_vs_full"]) > 40 and float(r["half_decode_s"]) > 0 for r in rows)
    assert "half size" in capsys.readouterr().out


def test_train_scale_scores_every_model_at_every_render_scale(tiny_scene, tmp_path, capsys):
    bench = load("train_scale")
    out = tmp_path / "scale.csv"
    bench.main(["--scene", str(tiny_scene), "--scales", "0.5,1", "--eval-scales", "0.5,1", "--minutes", "0.02",
                "--seeds", "0", "--no-pin", "--out", str(out)])
    rows = list(csv.DictReader(open(out)))
    assert [(r["train_scale"], r["train_size"], r["eval_size"]) for r in rows] == [
        ("0.5", "24x18", "24x18"), ("0.5", "24x18", "48x36"), ("1.0", "48x36", "24x18"), ("1.0", "48x36", "48x36")]
    assert all(int(r["steps"]) > 0 and float(r["psnr"]) > 5 for r in rows)
    assert "| x0.5 |" in capsys.readouterr().out


def test_viewport_preview_times_both_routes(tiny_scene, tmp_path, capsys):
    from neulf_core.train import TrainConfig, train

    model = tmp_path / "model"
    train(tiny_scene, model, TrainConfig(steps=20, validate_seconds=1e9, checkpoint_seconds=1e9))
    out = tmp_path / "viewport.csv"
    load("viewport_preview").main(["--model", str(model), "--regions", "192x144", "--preview-pixels", "3000",
                                   "--frames", "3", "--moving-seconds", "0.5", "--out", str(out)])
    rows = list(csv.DictReader(open(out)))
    assert [r["route"] for r in rows] == ["in-process", "worker"] and all(r["region"] == "192x144" for r in rows)
    for row in rows:
        assert 0 < float(row["coarse_ms_median"]) <= float(row["full_ms_median"]), row
        assert float(row["moving_images_per_s"]) > 0 and row["views"] == "3", row
    assert "| worker | 192x144 | 3,000 px |" in capsys.readouterr().out


def test_same_weights_tells_the_same_training_from_another(tiny_scene, tmp_path, capsys):
    bench = load("same_weights")
    runs = {}
    for name, seed in (("a", 0), ("b", 0), ("c", 1)):
        runs[name] = tmp_path / f"{name}.json"
        assert bench.main(["--scene", str(tiny_scene), "--steps", "12", "--seed", str(seed),
                           "--out", str(runs[name])]) == 0
    assert bench.main(["--compare", str(runs["a"]), str(runs["b"])]) == 0
    assert "scene: the same (" in capsys.readouterr().out
    assert bench.main(["--compare", str(runs["a"]), str(runs["c"])]) == 1
    assert "entries differ" in capsys.readouterr().out
    import json

    a, c = (json.loads(runs[name].read_text())["scene"] for name in ("a", "c"))
    assert any(".state_dict." in key and a[key] != c[key] for key in a)  # the weights themselves


def test_untuned_scene_compares_each_alternative_with_the_default_beside_it():
    """benchmarks/untuned_scene.py's table: each alternative against the default that trained
    beside it (not another pair's), the mean change and how many pairs it won."""
    untuned = load("untuned_scene")
    rows = []
    for scene, seed, label, default, other in (("1", 0, "one member", 30.0, 29.5), ("1", 1, "one member", 29.0, 28.9),
                                               ("1", 0, "no sweep teacher", 31.0, 31.2)):
        common = {"scene": scene, "seed": seed, "paired_with": label, "steps": 100, "members": 2,
                  "back_surface": True, "depth_layers": 0}
        rows += [{**common, "setting": "default", "psnr": default}, {**common, "setting": label, "psnr": other}]
    lines = untuned.table(rows)
    member = next(line for line in lines if line.startswith("| one member"))
    assert "| -0.50 | -0.10 |" in member and "-0.30 ± 0.20 dB" in member and "0 of 2" in member, member
    teacher = next(line for line in lines if line.startswith("| no sweep teacher"))
    assert "| +0.20 |  |" in teacher and "1 of 1" in teacher, teacher
    assert any("arrangement 1, seed 0: 30.50 dB (30.00-31.00 over 2 runs)" in line for line in lines), lines

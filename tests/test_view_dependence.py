"""benchmarks/view_dependence.py and benchmarks/volume_baseline.py: the mask of the shiny
objects, the masked PSNR, and the volume baseline (the paper's point of comparison) learning a
scene: on the tiny scene it must beat the held-out photo's mean colour by a wide margin."""

import numpy as np
import pytest
import torch


@pytest.fixture(scope="module")
def view_dependence(benchmark_script):
    return benchmark_script("view_dependence")


def test_mask_marks_the_pixels_that_differ_and_grows_by_the_dilation(view_dependence):
    lambertian = np.full((20, 30, 3), 0.5, dtype=np.float32)
    shiny = lambertian.copy()
    shiny[10, 15, 1] += 0.2                 # a reflection: one pixel, one channel
    shiny[2, 2] += 0.01                     # rendering noise: under the threshold
    mask = view_dependence.shiny_mask(shiny, lambertian, threshold=0.04, dilation=2)
    assert mask.sum() == 25 and mask[8:13, 13:18].all() and not mask[2, 2]
    assert view_dependence.shiny_mask(shiny, lambertian, dilation=0).sum() == 1
    with pytest.raises(ValueError, match="differ in size"):
        view_dependence.shiny_mask(shiny[:10], lambertian)


def test_masked_psnr_scores_only_the_masked_pixels(view_dependence):
    target = np.zeros((4, 4, 3), dtype=np.float32)
    image = target.copy()
    image[0, 0] = 0.1                        # an error of 0.1 inside the mask: 20 dB there
    image[3, 3] = 1.0                        # a large error outside it: not counted
    mask = np.zeros((4, 4), dtype=bool)
    mask[0, :2] = True
    assert view_dependence.masked_psnr(image, target, mask) == pytest.approx(10 * np.log10(2 / 0.01))
    assert np.isnan(view_dependence.masked_psnr(image, target, np.zeros((4, 4), dtype=bool)))
    scores = view_dependence.score({"a.png": image}, {"a.png": target}, {"a.png": mask})
    assert scores["mask_share"] == pytest.approx(2 / 16) and scores["psnr_mask"] > scores["psnr_outside"]


def test_volume_baseline_learns_the_tiny_scene(view_dependence, tiny_scene):
    from neulf_core.metrics import psnr
    from neulf_core.scene import load_scene, split_views
    from neulf_core.slab import scene_depths, slab_frame

    volume = view_dependence.volume_baseline
    torch.set_num_threads(1)
    scene = load_scene(tiny_scene)
    train_views, held = split_views(scene)
    rotation, origin = slab_frame(train_views)
    depths = scene_depths(scene, rotation, origin)
    config = volume.VolumeConfig(resolution=(24, 24, 8), features=4, samples=16, hidden=32, batch=1024, steps=300)
    model, record = volume.train_volume(train_views, 1.0, rotation, origin, 0.9 * depths.min(), 1.1 * depths.max(), config)
    assert record["steps"] == 300 and np.isfinite(record["final_loss"])
    assert record["parameters"] == 24 * 24 * 8 * 5 + sum(p.numel() for p in model.field.colour.parameters())
    target = held[0].load_image(1.0).astype(np.float32) / 255.0
    image = model.render_view(held[0], 1.0)
    assert image.shape == target.shape and np.isfinite(image).all()
    flat = np.broadcast_to(target.reshape(-1, 3).mean(0), target.shape)
    assert psnr(image, target) > psnr(flat, target) + 8  # ~24 dB against ~13


ONE_SURFACE = "one surface"  # a light-field run logged before the back surface (its key has no config)


def logged_row(view_dependence, method, variant, seed, steps=1000, minutes=0.0, psnr=30.0, mask=27.0, config=None):
    if config is None and method != "volume":
        config = view_dependence.LIGHT_FIELD_CONFIG
    key = view_dependence.run_key(method, variant, seed, steps, None if config == ONE_SURFACE else config, minutes)
    return {"key": key, "method": method, "variant": variant, "seed": seed, "steps": steps, "train_seconds": 40.0,
            "render_seconds": 0.03, "parameters": 210_000, "psnr": psnr, "psnr_mask": mask, "psnr_outside": 32.0,
            "psnr_per_view": "a=1/1;b=1/1"}


def test_report_names_each_budget_and_pairs_the_seeds_of_a_drop(view_dependence):
    rows = [logged_row(view_dependence, "volume", "lambertian", 0, steps=2400, psnr=33.0, mask=31.0),
            logged_row(view_dependence, "light field", "lambertian", 0, psnr=30.0),
            logged_row(view_dependence, "light field", "lambertian", 1, psnr=31.0),
            logged_row(view_dependence, "light field", "shiny", 0, psnr=29.0, mask=26.0),
            logged_row(view_dependence, "light field, equal time", "lambertian", 0, steps=1000, minutes=7.5)]
    assert view_dependence.labels(rows) == ["light field, 1000 steps", "light field, 7.5 min", "volume, 2400 steps"]
    before = logged_row(view_dependence, "light field", "lambertian", 0, psnr=29.0, config=ONE_SURFACE)
    colours = logged_row(view_dependence, "light field", "lambertian", 0, psnr=29.5, config={"back_surface": "by rule"})
    assert view_dependence.labels(rows + [colours, before])[:3] == [
        "light field, one surface, 1000 steps", "light field, colours blended, 1000 steps", "light field, 1000 steps"]
    # shiny has seed 0 only: its drop is against the Lambertian seed 0 (30.0), not the mean of 0 and 1
    assert view_dependence.drop(rows, "light field, 1000 steps", "shiny", "psnr") == "-1.00"
    assert view_dependence.drop(rows, "volume, 2400 steps", "shiny", "psnr") == "--"
    text = view_dependence.table(rows)
    assert "| light field, 1000 steps | 2 | 1000 |" in text and "30.50 ± 1.00" in text


def test_a_fresh_machine_starts_the_log_from_the_csv_with_the_same_runs_and_labels(view_dependence, tmp_path):
    """The run log lives in the temp folder; the committed CSV restarts it, keys and all, so the
    report keeps the runs (and their far-from-the-objects scores, whose renders are gone)."""
    import stability

    rows = [logged_row(view_dependence, "volume", "lambertian", 0, steps=2400, psnr=33.0, mask=31.0),
            logged_row(view_dependence, "light field", "shiny", 1, psnr=29.5),
            logged_row(view_dependence, "light field", "lambertian", 0, psnr=29.0, config=ONE_SURFACE)]
    for row in rows:
        row.update(psnr_far=37.5, date="2026-11-28", machine="test machine")
    table = tmp_path / "view_dependence.csv"
    stability.write_csv([{"label": view_dependence.label_of(row), **row} for row in rows], table, view_dependence.CSV_COLUMNS)
    log = tmp_path / "cache" / "runs.jsonl"
    assert stability.seed_log_from_csv(log, table) == 3
    assert stability.seed_log_from_csv(log, table) == 0  # a log that exists is kept
    again = view_dependence.load_runs(log)
    assert sorted(again) == sorted(row["key"] for row in rows)
    assert sorted(map(view_dependence.label_of, again.values())) == sorted(map(view_dependence.label_of, rows))
    assert all(row["psnr_far"] == 37.5 and row["seed"] in (0, 1) for row in again.values())


def test_a_logged_far_score_survives_a_newer_run_taking_its_render_names(view_dependence, tmp_path):
    """Renders are named by label, and a newer rule's runs take the plain label an older rule's
    runs had: a row logged with its far-from-the-objects score keeps it, an older row without
    one is scored from its label's renders, or nan where they are gone."""
    from neulf_core.images import save_rgb

    target = np.full((30, 30, 3), 0.5, dtype=np.float32)
    mask = np.zeros((30, 30), dtype=bool)
    mask[:5, :5] = True                     # the objects: far from them is the rest but a margin
    truths, masks = {"lambertian": {"v.png": target}}, {"v.png": mask}
    newer = logged_row(view_dependence, "light field", "lambertian", 0)
    render = np.clip(target + 0.1, 0, 1)    # an error of 0.1 everywhere: 20 dB
    save_rgb(view_dependence.render_path(tmp_path, view_dependence.label_of(newer), "lambertian", 0, "v.png"), render)
    logged = {**logged_row(view_dependence, "light field", "lambertian", 0), "psnr_far": 38.0}  # the same names
    gone = logged_row(view_dependence, "light field", "lambertian", 1, config={"back_surface": "by rule"})
    view_dependence.add_far_scores([newer, logged, gone], truths, masks, tmp_path)
    assert newer["psnr_far"] == pytest.approx(20.0, abs=0.2)
    assert logged["psnr_far"] == 38.0 and np.isnan(gone["psnr_far"])

"""Depth and refocus, measured against ground truth; the multi-view losses on and off.

    python benchmarks/depth.py --steps 3000 [--hci-steps 8000] [--parts hci,synthetic,canclip,refocus] [--jobs 2]

Parts (each trains the default `fast` field four ways -- plain, with the paper's losses, with
the plane-sweep depth teacher (`train --sweep-teacher`), and as `train` chooses by default for
the scene -- same steps, same seed; held-out views are every 8th view and never trained on):
- hci:       ../shared/data/hci_antinous, the centre view (held out): disparity error against
             the benchmark's ground truth -- BadPix(0.07) and MSE x100 as HCI reports them,
             both as rendered and after a least-squares fit d = a/Z + b (only relative depth
             is meaningful there, see the data README); held-out PSNR.
- synthetic: the project's own Blender scene (neulf_synth, exact poses, exact depth):
             absolute relative depth error on the held-out views, held-out PSNR; also the
             shiny variant (mirror, glass) to see what the losses do on view-dependent scenes.
- canclip:   a real Lambertian-ish capture at half resolution: held-out PSNR.
- refocus:   on the synthetic scene's held-out view, focus at a pixel on the near sphere and
             on the back wall (the model's depth there), and compare the variance of the
             Laplacian of each object between the two renders; images saved for people.
Writes docs/depth.csv (rows of scenes not in this run's parts are kept) and docs/depth/*.png;
prints the rows.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))
from reference_data import present  # noqa: E402

DATA = ROOT.parent / "shared" / "data"
DOCS = ROOT / "docs"
CACHE = Path(os.environ.get("NEULF_BENCH_CACHE", "/tmp/neulf_depth_bench"))
HCI_FOCAL_PX, HCI_BASELINE, HCI_SHIFT = 1462.86, 0.01, 8.0   # see ../shared/data/README.md


# ----------------------------------------------------------------------------- scenes
def synthetic_scene(variant: str, size: str = "320x240") -> Path:
    """A 4x4 Cycles capture with exact poses (sparse_gt) and depth, rendered once and cached."""
    rendered = CACHE / f"synth_{variant}_{size}"
    if not (rendered / "ground_truth" / "scene.json").is_file():
        subprocess.run([sys.executable, "-m", "neulf_synth", str(rendered), "--grid", "4x4", "--size", size,
                        "--samples", "32", "--variant", variant], check=True, cwd=ROOT)
    scene = CACHE / f"scene_{variant}_{size}"
    if not scene.exists():
        (scene / "sparse").mkdir(parents=True)
        (scene / "sparse" / "0").symlink_to(rendered / "sparse_gt" / "0")
        (scene / "images").symlink_to(rendered / "images")
    return scene


# ----------------------------------------------------------------------------- training
def train_model(scene: Path, name: str, consistency: bool, steps: int, scale: float, seed: int = 0,
                teacher: bool = False) -> dict:
    """Train (or reuse) one model; returns its folder, training seconds and held-out PSNR/SSIM."""
    import torch

    from neulf_core.evaluate import evaluate_model
    from neulf_core.train import TrainConfig, train

    torch.set_num_threads(1)  # runs go side by side; one thread each keeps them independent
    out = CACHE / "models" / f"{name}_{mode_of(consistency, teacher)}_{steps}_s{seed}"
    record = out / "bench.json"
    if record.is_file():
        return json.loads(record.read_text())
    if out.exists():
        import shutil
        shutil.rmtree(out)
    started = time.perf_counter()
    result = train(scene, out, TrainConfig(steps=steps, scale=scale, seed=seed, consistency=consistency, teacher=teacher,
                                           validate_seconds=1e9, checkpoint_seconds=1e9))
    seconds = time.perf_counter() - started
    report = evaluate_model(out, scene, save_images=False, pixel_samples=1)  # as its cached rows were scored
    meta = json.loads((out / "model.json").read_text())
    row = {"model": str(out), "scene": name, "mode": mode_of(consistency, teacher), "consistency": consistency,
           "teacher": teacher, "losses_used": bool(meta.get("multiview_losses")), "steps": result.step,
           "train_seconds": round(seconds, 1), "psnr": report["mean_psnr"], "ssim": report["mean_ssim"]}
    record.write_text(json.dumps(row))
    return row


# ----------------------------------------------------------------------------- measures
def hci_depth_errors(model_dir: str, data: Path = DATA) -> dict:
    """Disparity of the held-out centre view against the benchmark's ground truth."""
    from neulf_core.render import LightField
    from neulf_core.scene import load_scene

    light_field = LightField.load(model_dir, precision="full")
    scene = load_scene(data / "hci_antinous")
    view = scene.view("input_Cam040.png")
    depth = light_field.render_view(view, 1.0, depth=True).depth
    truth = np.load(data / "hci_antinous" / "gt_disparity_Cam040.npy")
    disparity = HCI_FOCAL_PX * HCI_BASELINE / depth - HCI_SHIFT
    inverse = 1.0 / depth
    ok = np.isfinite(inverse)
    a, b = np.linalg.lstsq(np.stack([inverse[ok], np.ones(ok.sum())], 1), truth[ok], rcond=None)[0]
    fitted = a * inverse + b
    return {**_disparity_scores(disparity, truth, ok, ""), **_disparity_scores(fitted, truth, ok, "fit_"),
            "disparity_map": disparity}


def _disparity_scores(disparity, truth, ok, prefix: str) -> dict:
    error = np.where(ok, disparity - truth, np.inf)  # a pixel without depth counts as bad
    finite = np.isfinite(error)
    return {f"{prefix}badpix007": float(100.0 * np.mean(np.abs(error) > 0.07)),
            f"{prefix}mse100": float(100.0 * np.mean(error[finite] ** 2))}


def synthetic_depth_error(model_dir: str, scene: Path) -> dict:
    """Absolute relative error of depth along the optical axis on the held-out views."""
    from neulf_core.render import LightField
    from neulf_core.scene import load_scene

    light_field = LightField.load(model_dir, precision="full")
    loaded = load_scene(scene)
    truth_dir = Path(os.path.realpath(scene / "images")).parent / "ground_truth"
    errors, maps = [], {}
    for name in light_field.meta["scene"]["held_out"]:
        view = loaded.view(name)
        depth = light_field.render_view(view, 1.0, depth=True).depth
        truth = np.load(truth_dir / f"depth_{view.stem}.npy")
        ok = np.isfinite(truth) & np.isfinite(depth)
        errors.append(np.abs(depth[ok] - truth[ok]) / truth[ok])
        maps[view.stem] = (depth, truth)
    error = np.concatenate(errors)
    return {"abs_rel": float(100.0 * error.mean()), "abs_rel_median": float(100.0 * np.median(error)),
            "within_5pct": float(100.0 * np.mean(error < 0.05)), "maps": maps}


def refocus_study(model_dir: str, scene: Path, out_dir: Path, aperture: float) -> list[dict]:
    """Focus at a pixel on the near sphere, then on the back wall: each object should be the
    sharper one in the render focused on it."""
    from neulf_core.images import save_rgb
    from neulf_core.metrics import eroded, laplacian_variance
    from neulf_core.render import LightField
    from neulf_core.scene import load_scene

    light_field = LightField.load(model_dir, precision="full")
    view = load_scene(scene).view("view_00_00.png")
    truth_dir = Path(os.path.realpath(scene / "images")).parent / "ground_truth"
    objects = np.load(truth_dir / "object_index_view_00_00.npy")
    index = {o["name"]: o["pass_index"] for o in json.loads((truth_dir / "scene.json").read_text())["objects"]}
    regions = {"near sphere": eroded(objects == index["NearSphere"]), "back wall": eroded(objects == index["BackWall"])}
    camera = view.scaled_camera(1.0)
    K = camera.calibration_matrix()
    renders, rows = {}, []
    for name, region in regions.items():
        ys, xs = np.nonzero(region)
        pick = len(ys) // 2
        focus = light_field.depth_at(K, view.R, view.t, xs[pick] + 0.5, ys[pick] + 0.5)
        rendering = light_field.render(K, camera.width, camera.height, view.R, view.t, depth=False,
                                       focus_distance=focus, aperture=aperture)
        renders[name] = rendering.rgb
        save_rgb(out_dir / f"refocus_{name.replace(' ', '_')}.png", rendering.rgb)
        rows.append({"focused_on": name, "pixel": [int(xs[pick]), int(ys[pick])], "focus_distance": focus})
    for row in rows:
        name = row["focused_on"]
        other = next(n for n in regions if n != name)
        row["sharpness_ratio"] = laplacian_variance(renders[name], regions[name]) / laplacian_variance(renders[other], regions[name])
    return rows


# ----------------------------------------------------------------------------- parts
# (paper's losses, plane-sweep teacher): off, the losses on, the teacher on (teacher.py), and
# the default (None, None: what `train` chooses for the scene; the row records the losses' choice).
MODES = ((False, False), (True, False), (False, True), (None, None))


def mode_of(consistency: bool | None, teacher: bool | None) -> str:
    if consistency is None and teacher is None:
        return "default"
    return "teacher" if teacher else ("on" if consistency else "off")


def jobs_for(parts: list[str], steps: int, hci_steps: int | None = None, data: Path = DATA) -> list[tuple]:
    scenes = []
    if "hci" in parts:
        scenes.append((data / "hci_antinous", "hci", 1.0))
    if "synthetic" in parts or "refocus" in parts:
        scenes.append((synthetic_scene("lambertian"), "synthetic", 1.0))
    if "synthetic" in parts:
        scenes.append((synthetic_scene("shiny"), "synthetic_shiny", 1.0))
    if "canclip" in parts:
        scenes.append((data / "canclip", "canclip", 0.5))
    return [(path, name, consistency, (hci_steps or steps) if name == "hci" else steps, scale, 0, teacher)
            for path, name, scale in scenes for consistency, teacher in MODES]


def measure(row: dict, out_dir: Path, aperture: float, data: Path = DATA) -> dict:
    from neulf_core.video import depth_to_colour
    from neulf_core.images import save_rgb

    tag = f"{row['scene']}_{row.get('mode') or mode_of(row['consistency'], row.get('teacher', False))}"
    if row["scene"] == "hci":
        scores = hci_depth_errors(row["model"], data)
        disparity = scores.pop("disparity_map")
        save_rgb(out_dir / f"depth_{tag}.png", depth_to_colour(1.0 / (disparity + HCI_SHIFT)))
        row.update(scores)
    elif row["scene"].startswith("synthetic"):
        scene = synthetic_scene("shiny" if "shiny" in row["scene"] else "lambertian")
        scores = synthetic_depth_error(row["model"], scene)
        depth, truth = next(iter(scores.pop("maps").values()))
        save_rgb(out_dir / f"depth_{tag}.png", depth_to_colour(depth))
        if row.get("mode", "off") == "off":
            save_rgb(out_dir / f"depth_{row['scene']}_truth.png", depth_to_colour(np.where(np.isfinite(truth), truth, np.nan)))
        row.update(scores)
        if row["scene"] == "synthetic":
            for r in refocus_study(row["model"], scene, out_dir / tag, aperture):
                row[f"refocus_ratio_{r['focused_on'].replace(' ', '_')}"] = r["sharpness_ratio"]
    return row


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=3000)
    # HCI's 71 training views of 512x512 are 18.6 M rays: 2000 steps of 8192 rays see each
    # ray less than once, and its depth edges settle only after a few passes (docs/DEPTH.md).
    parser.add_argument("--hci-steps", type=int, default=8000, help="steps for the HCI light field (default 8000)")
    parser.add_argument("--parts", default="hci,synthetic,canclip,refocus")
    parser.add_argument("--jobs", type=int, default=2, help="trainings side by side (one torch thread each)")
    parser.add_argument("--aperture", type=float, default=0.08, help="refocus lens radius (synthetic scene units)")
    parser.add_argument("--csv", default=str(DOCS / "depth.csv"))
    parser.add_argument("--data", type=Path, default=DATA, help="the folder holding hci_antinous and canclip")
    args = parser.parse_args(argv)
    # The parts on a capture need its folder; checked before the synthetic scene is rendered.  The
    # CSV keeps the rows of the parts left out, so the others still run.
    needs = {"hci": args.data / "hci_antinous", "canclip": args.data / "canclip"}
    parts = present({part: needs.get(part) for part in args.parts.split(",")}, "--data")
    jobs = jobs_for(parts, args.steps, args.hci_steps, args.data)
    with ProcessPoolExecutor(args.jobs) as pool:
        rows = list(pool.map(train_model, *zip(*jobs)))
    out_dir = DOCS / "depth"
    out_dir.mkdir(parents=True, exist_ok=True)
    rows = [measure({"teacher": False, **row}, out_dir, args.aperture, args.data) for row in rows]
    hardware = _hardware()
    table = kept_rows(Path(args.csv), {row["scene"] for row in rows}) + [{**row, "hardware": hardware} for row in rows]
    fields = sorted({k for row in table for k in row if k not in ("model", "hardware")},
                    key=lambda k: (k not in ("scene", "mode", "consistency", "teacher"), k))
    with open(args.csv, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=fields + ["hardware"])
        writer.writeheader()
        for row in table:
            writer.writerow({k: row.get(k, "") for k in fields + ["hardware"]})
    for row in rows:
        print({k: (round(v, 3) if isinstance(v, float) else v) for k, v in row.items() if k != "model"})
    return 0


def kept_rows(path: Path, replaced_scenes: set[str]) -> list[dict]:
    """The rows of an earlier CSV whose scenes this run did not measure (a run of some parts
    updates those and keeps the rest, each row with the hardware it ran on)."""
    if not path.is_file():
        return []
    with open(path, newline="") as handle:
        return [row for row in csv.DictReader(handle) if row.get("scene") not in replaced_scenes]


def _hardware() -> str:
    import platform

    import torch

    cpu = platform.processor() or platform.machine()
    try:
        cpu = next(line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    return f"{cpu}, {os.cpu_count()} cores, torch {torch.__version__}"


if __name__ == "__main__":
    sys.exit(main())

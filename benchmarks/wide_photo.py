"""One photo that sees far wider than the others: what it costs, and what the slab's placement does.

A capture's photos taken with one lens, except one (a phone that switched to its ultra-wide, a
second camera).  Made from a real capture with exact geometry: every CanClip photo is cropped
to its central part (its camera's size and principal point moved with the crop, its lens
unchanged), except one training photo, which keeps its full frame and so sees about twice as
wide on the light slab.  The held-out views (every 8th) are cropped like the rest, so each arm
is scored on the same pixels:

- `cropped`: every photo cropped (no wide photo: the reference);
- `wide`: the one photo full frame, trained on as it is;
- `wide-excluded`: the wide photo held out of training, as the warning suggests.

    python benchmarks/wide_photo.py [--scene ../shared/data/canclip] [--steps 1000] [--seeds 0,1]
        [--crop 0.45] [--wide img013.png] [--scale 1] [--csv docs/wide_photo.csv] [--label NAME]

Rows are added to the CSV (an arm, a seed, the code's label, the held-out PSNR and each view's).
`--label` names the code measured (a run from another checkout, `--root`, compares the same
arms before and after a change, on the same machine).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from reference_data import skip_unless_present  # noqa: E402
from speed_accuracy import append_rows, machine  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
ARMS = ("cropped", "wide", "wide-excluded")


def make_scene(source: Path, out: Path, crop: float, wide: str | None) -> Path:
    """`source`'s photos cropped to their central `crop` of each side (all but `wide`), with a
    COLMAP model whose cameras follow the crops."""
    import pycolmap
    from PIL import Image

    model = pycolmap.Reconstruction(str(source / "sparse" / "0"))
    (out / "images").mkdir(parents=True, exist_ok=True)
    recon = pycolmap.Reconstruction()
    cameras = {}
    for image_id in sorted(model.images):
        image = model.images[image_id]
        camera = model.cameras[image.camera_id]
        photo = Image.open(source / "images" / image.name)
        keep_full = image.name == wide
        width = camera.width if keep_full else int(round(camera.width * crop / 2)) * 2
        height = camera.height if keep_full else int(round(camera.height * crop / 2)) * 2
        x0, y0 = (camera.width - width) // 2, (camera.height - height) // 2
        photo.crop((x0, y0, x0 + width, y0 + height)).save(out / "images" / image.name)
        params = np.array(camera.params, float)
        principal = list(camera.principal_point_idxs())
        params[principal[0]] -= x0
        params[principal[1]] -= y0
        key = (width, height, tuple(params))
        if key not in cameras:
            cam = pycolmap.Camera(model=camera.model_name, width=width, height=height, params=params,
                                  camera_id=len(cameras) + 1)
            recon.add_camera_with_trivial_rig(cam)
            cameras[key] = cam.camera_id
        pose = image.cam_from_world() if callable(image.cam_from_world) else image.cam_from_world
        recon.add_image_with_trivial_frame(pycolmap.Image(name=image.name, camera_id=cameras[key],
                                                          image_id=image_id), pose)
    for point in model.points3D.values():  # (positions only: the slab's depth range)
        recon.add_point3D(point.xyz, pycolmap.Track(), point.color)
    (out / "sparse" / "0").mkdir(parents=True, exist_ok=True)
    recon.write_binary(str(out / "sparse" / "0"))
    return out


def run_arm(scene: Path, arm: str, seed: int, steps: int, wide: str, work: Path, scale: float) -> dict:
    import torch

    from neulf_core.evaluate import evaluate_model
    from neulf_core.scene import load_scene, split_views
    from neulf_core.train import TrainConfig, train

    torch.set_num_threads(1)
    held = [v.name for v in split_views(load_scene(scene), 8)[1]]
    exclude = held + [wide] if arm == "wide-excluded" else None
    model = work / f"{arm}_{seed}"
    warnings = []
    started = time.perf_counter()
    train(scene, model, TrainConfig(steps=steps, seed=seed, exclude=exclude, scale=scale, validate_seconds=1e9),
          progress=lambda e: warnings.append(e["message"]) if e.get("event") in ("warning", "stage") else None)
    seconds = time.perf_counter() - started
    report = evaluate_model(model, scene, views=held, save_images=False, out_dir=work / f"eval_{arm}_{seed}",
                            pixel_samples=1)
    return {"psnr": float(np.mean([v["psnr"] for v in report["views"]])),
            "per_view": " ".join(f"{v['psnr']:.2f}" for v in report["views"]), "seconds": round(seconds, 1),
            "wide_named": any("see more than twice as wide" in w for w in warnings)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scene", type=Path, default=REPO.parent / "shared" / "data" / "canclip")
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--seeds", default="0,1")
    parser.add_argument("--crop", type=float, default=0.45)
    parser.add_argument("--wide", default="img013.png")
    parser.add_argument("--scale", type=float, default=1.0, help="every arm's training scale (the default rule "
                        "follows the largest photo, which would train the wide arms' cropped photos at half size)")
    parser.add_argument("--arms", default=",".join(ARMS))
    parser.add_argument("--csv", type=Path, default=REPO / "docs" / "wide_photo.csv")
    parser.add_argument("--label", default="current")
    parser.add_argument("--work", type=Path, default=None)
    args = parser.parse_args()
    skip_unless_present(args.scene)
    work = args.work or Path(tempfile.mkdtemp(prefix="wide_photo_"))
    scenes = {}
    for arm in args.arms.split(","):
        kind = "cropped" if arm == "cropped" else "wide"
        if kind not in scenes:
            scenes[kind] = make_scene(args.scene, work / f"scene_{kind}", args.crop,
                                      None if kind == "cropped" else args.wide)
    columns = ["date", "machine", "label", "arm", "seed", "steps", "scale", "crop", "wide_photo", "psnr",
               "per_view_psnr", "train_seconds", "wide_named"]
    for seed in [int(s) for s in args.seeds.split(",")]:
        for arm in args.arms.split(","):
            scene = scenes["cropped" if arm == "cropped" else "wide"]
            row = run_arm(scene, arm, seed, args.steps, args.wide, work, args.scale)
            print(json.dumps({"label": args.label, "arm": arm, "seed": seed, **row}), flush=True)
            append_rows(args.csv, [{"date": time.strftime("%Y-%m-%d"), "machine": machine(), "label": args.label,
                                    "arm": arm, "seed": seed, "steps": args.steps, "scale": args.scale,
                                    "crop": args.crop, "wide_photo": args.wide, "psnr": f"{row['psnr']:.3f}",
                                    "per_view_psnr": row["per_view"], "train_seconds": row["seconds"],
                                    "wide_named": row["wide_named"]}], columns)
    return 0


if __name__ == "__main__":
    sys.exit(main())

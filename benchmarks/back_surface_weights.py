"""How a trained model uses its back surface (DisparityConfig.back_surface).

Trains the stability study's default on the project's synthetic scene (1000 steps, as the
study trains it) and reads, over every ray of the held-out views and of four training views,
the front surface's weight in the colour and the back surface's depth unit as a share of the
front's.  Prints quantiles and writes them to docs/back_surface_weights.csv:

    python benchmarks/back_surface_weights.py                     # lambertian and shiny, seed 0 (about 2 minutes)
    python benchmarks/back_surface_weights.py --variants fine --seed 1

The scenes are the study's renders in its cache (rendered there first when missing).
"""

from __future__ import annotations

import argparse
import csv
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import stability  # noqa: E402

from neulf_core.dataset import view_uvst  # noqa: E402
from neulf_core.render import LightField  # noqa: E402
from neulf_core.train import train  # noqa: E402

QUANTILES = (0.01, 0.1, 0.25, 0.5, 0.75, 0.9, 0.99)
TRAINING_VIEWS_READ = 4


def surfaces_over(light_field: LightField, views, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """(front weight, back unit / front unit) over every pixel-centre ray of `views`."""
    weights, shares = [], []
    for view in views:
        uvst, _ = view_uvst(view, light_field.slab, scale)
        with torch.no_grad():
            ((_, front_unit), (_, back_unit)), front_weight = light_field.field.surfaces(uvst)
        weights.append(front_weight[:, 0].numpy())
        shares.append((back_unit / front_unit.clamp(min=1e-9))[:, 0].numpy())
    return np.concatenate(weights), np.concatenate(shares)


def measure(variant: str, seed: int, steps: int, scale: float, cache: Path) -> list[dict]:
    scene_dir = stability.render_synthetic(cache, variant)
    job = stability.Job(scene=variant, path=str(scene_dir), truth=str(scene_dir), scale=scale,
                        preset="fast", steps=steps, seed=seed, colour_start=stability.preset_colour_start("fast"))
    scene, train_views, held = stability.prepare(job)
    rows = []
    with tempfile.TemporaryDirectory(prefix="neulf_back_surface_") as model_dir:
        train(scene, model_dir, stability.train_config(job, held))
        light_field = LightField.load(model_dir, "cpu", precision="full")
        config = getattr(light_field.field, "config", None)
        if not getattr(config, "back_surface", False):  # (a model of two members has no single field to read)
            raise SystemExit(f"{variant}: the model is not one field with a back surface")
        for rays, views in (("held-out", held), ("training", train_views[:TRAINING_VIEWS_READ])):
            weight, share = surfaces_over(light_field, views, job.scale)
            for quantity, values in (("front weight", weight), ("back unit / front unit", share)):
                row = {"variant": variant, "seed": seed, "steps": steps, "rays": rays, "quantity": quantity}
                row.update({f"q{round(100 * q)}": round(float(v), 3) for q, v in zip(QUANTILES, np.quantile(values, QUANTILES))})
                row["share above 0.999"] = round(float(np.mean(values > 0.999)), 4)
                rows.append(row)
                print(f"{variant} seed {seed}, {rays} rays, {quantity}: quantiles "
                      f"{' / '.join(str(row[f'q{round(100 * q)}']) for q in QUANTILES)} "
                      f"(1/10/25/50/75/90/99 %); above 0.999: {row['share above 0.999']}", flush=True)
    return rows


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--variants", type=lambda s: s.split(","), default=["lambertian", "shiny"])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--scale", type=float, default=0.5, help="training scale of the 320x240 renders (the study's)")
    parser.add_argument("--cache", type=Path, default=stability.DEFAULT_CACHE)
    parser.add_argument("--out", type=Path, default=stability.REPO / "docs" / "back_surface_weights.csv")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    rows = [row for variant in args.variants for row in measure(variant, args.seed, args.steps, args.scale, args.cache)]
    with open(args.out, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    print("wrote", args.out)


if __name__ == "__main__":
    main()

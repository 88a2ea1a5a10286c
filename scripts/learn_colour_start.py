"""Learn the fast preset's colour-decoder start (neulf_core/fields/starts/<name>.npz).

    python scripts/learn_colour_start.py [--scenes ../shared/data/statue] [--name statue_v1] \
        [--steps 1000] [--scale 0.25]

Trains the default model on each scene in turn (seed 0, one torch thread, the held-out views --
every 8th -- never trained on) and keeps only its colour decoder, the small network that turns
the texture's features into a colour.  The first scene starts from PyTorch's random decoder;
each later one from the decoder the one before left.  The decoder is written with its colour
slopes zeroed: the field starts view-independent, as it does from a random start.

Why: with the decoder drawn from the seed, the seed alone moved the held-out PSNR of dense
captures by 0.2-0.4 dB; a start no seed draws brought CanClip's 26 views to 0.05 dB and HCI's
70 to 0.02 (docs/STABILITY.md, "Twenty-eighth session").  Learn it from scenes that no study
or benchmark scores the start on -- Statue is in none of the stability study's.
"""

from __future__ import annotations

import argparse
import io
import json
import sys
import tempfile
from datetime import date
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from neulf_core.checkpoint import atomic_write_bytes, load_checkpoint  # noqa: E402
from neulf_core.fields.disparity import colour_start_path  # noqa: E402
from neulf_core.train import TrainConfig, train  # noqa: E402

STATUE = REPO.parent / "shared" / "data" / "statue"


def decoder_weights(model_dir: Path) -> dict[str, np.ndarray]:
    """The trained colour decoder's weights (Linear "0", ReLU, Linear "2"), its colour slopes
    (outputs 3-8 of the last layer) zeroed."""
    state = load_checkpoint(model_dir)["state_dict"]
    weights = {key[len("decoder."):]: value.float().numpy().copy() for key, value in state.items()
               if key.startswith("decoder.")}
    weights["2.weight"][3:] = 0.0
    weights["2.bias"][3:] = 0.0
    return weights


def learn(scenes: list[Path], name: str, steps: int, scale: float) -> Path:
    out = colour_start_path(name)
    history = []
    for i, scene in enumerate(scenes):
        start = name if i else ""  # each later scene from the decoder the one before left
        config = TrainConfig(preset="fast", steps=steps, scale=scale, seed=0, field_overrides={"colour_start": start},
                             validate_seconds=1e9, checkpoint_seconds=1e9)
        with tempfile.TemporaryDirectory(prefix="neulf_colour_start_") as model_dir:
            result = train(scene, model_dir, config)
            weights = decoder_weights(Path(model_dir))
        history.append({"scene": scene.name, "steps": result.step, "scale": scale, "seed": 0,
                        "val_psnr": result.val_psnr})
        print(f"{scene.name}: {result.step} steps, held-out PSNR {result.val_psnr or float('nan'):.2f} dB", flush=True)
        meta = {"learned_by": "scripts/learn_colour_start.py", "date": date.today().isoformat(),
                "torch": torch.__version__, "scenes": history}
        buffer = io.BytesIO()
        np.savez(buffer, **weights, meta=np.array(json.dumps(meta)))
        atomic_write_bytes(out, buffer.getvalue())  # a half-written start never replaces a whole one
    shapes = ", ".join(f"{k} {tuple(v.shape)}" for k, v in weights.items())
    print(f"wrote {out} ({shapes})")
    return out


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", default=str(STATUE), help="comma-separated scene folders, learned in turn")
    parser.add_argument("--name", default="statue_v1", help="the start's name (DisparityConfig.colour_start)")
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--scale", type=float, default=0.25)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)  # as the start in the package was learned (the result depends a little on it)
    learn([Path(s).expanduser() for s in args.scenes.split(",")], args.name, args.steps, args.scale)


if __name__ == "__main__":
    main()

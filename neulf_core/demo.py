"""The demo: a scene rendered by Blender -> pycolmap reconstruction -> NeuLF -> renders and a video.

Nothing is downloaded.  The scene is rendered by `neulf_synth` (Blender's Cycles through
the bpy module) in a separate process, so neulf_core itself never imports bpy.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import time
from pathlib import Path

from .errors import NeulfError
from .model_files import can_resume


def _say(text: str) -> None:
    print(f"== {text}", file=sys.stderr, flush=True)


def render_synthetic_scene(out: Path, grid: str = "4x4", size: str = "320x240") -> Path:
    """Run the Blender generator; returns the folder with images/ and ground_truth/."""
    command = [sys.executable, "-m", "neulf_synth", str(out), "--grid", grid, "--size", size]
    try:
        subprocess.run(command, check=True)
    except subprocess.CalledProcessError as exc:
        raise NeulfError(
            f"rendering the demo scene with Blender failed (exit {exc.returncode}); is the bpy module installed "
            "(pip install -e '.[blender]') with its system libraries (see README)?"
        ) from None
    return out


def run_demo(out: Path, minutes: float = 3.0, keep: bool = False) -> dict:
    from .cli import main as cli_main
    from .evaluate import evaluate_model
    from .reconstruct import reconstruct

    out = Path(out)
    started = time.perf_counter()
    rendered = out / "blender_scene"
    if not (keep and (rendered / "images").is_dir()):
        _say("1/5 rendering a small forward-facing scene with Blender Cycles (16 views, 320x240)")
        render_synthetic_scene(rendered)
    scene_dir = out / "scene"
    model_dir = out / "model"
    if not (keep and (scene_dir / "sparse" / "0").is_dir()):
        _say("2/5 reconstructing the cameras with pycolmap (features, matching, mapping)")
        if (scene_dir / "images").is_dir():  # the demo's own photos of its last render (reconstruct keeps a folder's photos)
            shutil.rmtree(scene_dir / "images")
        reconstruct(rendered / "images", scene_dir,
                    progress=lambda e: print(f"   [{e['stage']}] {e['message']}", file=sys.stderr, flush=True))
        if model_dir.exists():  # the demo's own model of the previous reconstruction: it no longer fits
            _say(f"   removing the previous demo model {model_dir} (trained on the previous reconstruction)")
            shutil.rmtree(model_dir)
    _say(f"3/5 training the light field for {minutes:g} minutes (every 8th view held out)")
    resume = can_resume(model_dir)
    code = cli_main(["train", str(scene_dir), "--out", str(model_dir), "--minutes", str(minutes)] + (["--resume"] if resume else []))
    if code != 0:
        raise NeulfError("training failed; see the message above.")
    _say("4/5 rendering and scoring the held-out views")
    report = evaluate_model(model_dir, scene_dir, out_dir=out / "held_out")
    if cli_main(["render", str(model_dir), "--scene", str(scene_dir), "--views", "held-out", "--out", str(out / "held_out"),
                 "--depth"]) != 0:
        raise NeulfError("rendering the held-out views failed; see the message above.")
    _say("5/5 rendering a spiral camera path to video")
    if cli_main(["video", str(model_dir), "--out", str(out / "spiral.mp4"), "--frames", "60"]) != 0:
        raise NeulfError("rendering the video failed; see the message above.")
    for row in report["views"]:
        print(f"held-out {row['view']}: PSNR {row['psnr']:.2f} dB, SSIM {row['ssim']:.3f}")
    print(f"mean held-out PSNR {report['mean_psnr']:.2f} dB (a flat mean-colour image scores {report['mean_colour_psnr']:.2f} dB)")
    print(f"renders: {out / 'held_out'}  video: {out / 'spiral.mp4'}  total {time.perf_counter() - started:.0f} s")
    return report

"""`frames` on a filmed capture: its time and peak memory, and whether `reconstruct` registers
the photos it picks.

The clip is made from a real capture: CanClip's 30 photos in name order (a sideways sweep of the
rig), each pair of neighbours cross-faded over `--between` frames and enlarged to 1920x1080, so a
10-second 1080p pan at 29 frames a second -- real texture, the camera moving between real
viewpoints -- with every `--blur-every`th frame smeared sideways as a hand's shake would.  Then,
each in a process of its own (one torch thread):

    python -m neulf_core frames CLIP --out PHOTOS [--count N]
    python -m neulf_core reconstruct PHOTOS --out SCENE        (with --reconstruct)

    python benchmarks/frames_time.py [--scene ../shared/data/canclip] [--count 60] [--reconstruct]
        [--csv docs/frames_time.csv]

Prints and appends to the CSV: the clip's frames and size, the seconds and peak resident memory
of each command (the child's ru_maxrss), the photos picked, how many of the blurred frames were
picked, and the photos `reconstruct` registered.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))

from reference_data import skip_unless_present  # noqa: E402

COLUMNS = ["date", "machine", "clip_frames", "clip_size", "count", "command", "seconds", "peak_mb", "photos",
           "blurred_picked", "registered"]


def make_clip(photos: list[Path], out: Path, between: int, size: tuple[int, int], blur_every: int) -> tuple[int, set]:
    """The pan (frames written to `out` as H.264) and the indices of the frames smeared."""
    from PIL import Image

    from neulf_core.video import write_video

    def load(path: Path) -> np.ndarray:
        return np.asarray(Image.open(path).convert("RGB").resize(size, Image.BILINEAR), np.float32)

    blurred = set()

    def frames():
        previous = load(photos[0])
        index = 0
        for path in photos[1:]:
            current = load(path)
            for k in range(between):
                weight = k / between
                frame = (1 - weight) * previous + weight * current
                if blur_every and index % blur_every == blur_every - 1:
                    frame = sum(np.roll(frame, shift, axis=1) for shift in range(-12, 13, 3)) / 9  # a sideways shake
                    blurred.add(index)
                yield np.clip(frame, 0, 255).astype(np.uint8)
                index += 1
            previous = current

    count = write_video(frames(), out, fps=29)
    return count, blurred


# Runs the CLI and writes its own peak resident memory (kB) to the file named first: Linux's
# VmHWM, this process image's own high-water mark (ru_maxrss there keeps the forked copy of this
# benchmark's memory from before the exec); elsewhere ru_maxrss (macOS: bytes).
_PEAK_WRAPPER = (
    "import re, resource, runpy, sys\n"
    "out = sys.argv.pop(1)\n"
    "sys.argv[0] = 'neulf_core'\n"
    "def peak():\n"
    "    try:\n"
    "        return float(re.search(r'VmHWM:\\s*(\\d+)', open('/proc/self/status').read()).group(1))\n"
    "    except (OSError, AttributeError):\n"
    "        rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss\n"
    "        return rss / 1024.0 if sys.platform == 'darwin' else float(rss)\n"
    "try:\n"
    "    runpy.run_module('neulf_core', run_name='__main__', alter_sys=True)\n"
    "finally:\n"
    "    open(out, 'w').write(str(peak()))\n")


def timed(argv: list[str], work: Path) -> tuple[float, float, str]:
    """(seconds, peak MB, its stderr + stdout) of `python -m neulf_core ARGV` in a process of its own."""
    peak_file = work / "peak.txt"
    started = time.perf_counter()
    result = subprocess.run([sys.executable, "-c", _PEAK_WRAPPER, str(peak_file), *argv], cwd=REPO,
                            capture_output=True, text=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
    seconds = time.perf_counter() - started
    if result.returncode != 0:
        raise SystemExit(f"{' '.join(argv)} failed:\n{result.stderr[-2000:]}")
    return seconds, float(peak_file.read_text()) / 1024.0, result.stderr + result.stdout


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scene", type=Path, default=REPO.parent / "shared" / "data" / "canclip")
    parser.add_argument("--count", type=int, default=60)
    parser.add_argument("--between", type=int, default=10, help="frames from one photo to the next")
    parser.add_argument("--size", default="1920x1080")
    parser.add_argument("--blur-every", type=int, default=4, help="every Nth frame smeared sideways (0: none)")
    parser.add_argument("--reconstruct", action="store_true")
    parser.add_argument("--csv", type=Path, default=REPO / "docs" / "frames_time.csv")
    parser.add_argument("--work", type=Path, default=None)
    args = parser.parse_args()
    skip_unless_present(args.scene)
    from speed_accuracy import append_rows, machine

    work = args.work or Path(tempfile.mkdtemp(prefix="frames_time_"))
    work.mkdir(parents=True, exist_ok=True)
    size = tuple(int(x) for x in args.size.split("x"))
    photos = sorted((args.scene / "images").iterdir())
    clip = work / "pan.mp4"
    frames, blurred = make_clip(photos, clip, args.between, size, args.blur_every)
    print(f"clip: {frames} frames of {args.size} ({clip.stat().st_size / 1e6:.1f} MB), {len(blurred)} smeared",
          flush=True)
    rows = []
    seconds, peak, _ = timed(["frames", str(clip), "--out", str(work / "photos"), "--count", str(args.count)], work)
    picked = sorted((work / "photos").iterdir())
    blurred_picked = _smeared_among(picked, clip, blurred)
    base = {"date": time.strftime("%Y-%m-%d"), "machine": machine(), "clip_frames": frames, "clip_size": args.size,
            "count": args.count}
    rows.append({**base, "command": "frames", "seconds": round(seconds, 1), "peak_mb": round(peak),
                 "photos": len(picked), "blurred_picked": blurred_picked, "registered": ""})
    print(json.dumps(rows[-1]), flush=True)
    if args.reconstruct:
        seconds, peak, output = timed(["reconstruct", str(work / "photos"), "--out", str(work / "scene")], work)
        import pycolmap

        registered = len(pycolmap.Reconstruction(str(work / "scene" / "sparse" / "0")).images)
        rows.append({**base, "command": "reconstruct", "seconds": round(seconds, 1), "peak_mb": round(peak),
                     "photos": len(picked), "blurred_picked": "", "registered": registered})
        print(json.dumps(rows[-1]), flush=True)
    append_rows(args.csv, rows, COLUMNS)
    return 0


def _smeared_among(picked: list[Path], clip: Path, blurred: set) -> int:
    """How many picked photos are smeared frames: each photo matched to the clip's frame it is
    closest to (mean absolute difference at 480x270, where the smear is 6 pixels wide)."""
    import av
    from PIL import Image

    def small(image: Image.Image) -> np.ndarray:
        return np.asarray(image.convert("L").resize((480, 270), Image.BILINEAR), np.float32)

    with av.open(str(clip)) as container:
        frames = [small(frame.to_image()) for frame in container.decode(video=0)]
    count = 0
    for path in picked:
        photo = small(Image.open(path))
        nearest = int(np.argmin([np.abs(photo - frame).mean() for frame in frames]))
        count += nearest in blurred
    return count


if __name__ == "__main__":
    sys.exit(main())

"""Would decoding a large JPEG at half size (libjpeg's scaled decoding, Pillow's `draft`)
speed up a run's start without changing its photos?  Times a read at the size training wants
(full decode then box filter, as `images.load_rgb` does) against a half-size decode then the
same box filter, and measures how far the two results differ.  (Sixty-ninth session: not
adopted, docs/BENCHMARKS.md, "Decoding JPEG photos at half size".)

    python benchmarks/jpeg_half_decode.py [--photos DIR] [--repeats 5] [--label NAME] \
        [--out docs/jpeg_half_decode.csv]

Without `--photos` it makes three JPEGs (quality 92, Pillow's default 4:2:0 chroma) from the
first photo of `--scene` (CanClip by default): "smooth", the photo upscaled 4 times
(3840x2160; little fine detail, so it decodes fast); "detailed", the same at 4032x3024 with
Gaussian noise of 12 grey levels added (high entropy, like a phone photo's fine texture and
sensor noise; 5 MB); "colourful", 4032x3024 of saturated random colours in 16-pixel blocks
with the same noise (strong colour edges everywhere).  Each photo is read at a quarter, an
eighth and a sixteenth of its size (whole fractions of the half-size decode, so both box
filters average the same footprint; a run's training rays at `--scale 0.125` read an eighth,
the depth teacher's sweep a sixteenth).  Per size: the median seconds of `--repeats` reads
each way, and the PSNR and largest difference (grey levels) of the half-size read against
the full one.  Appends the rows to the CSV.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from datetime import date
from pathlib import Path

import numpy as np
from PIL import Image, ImageOps

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

from neulf_core.images import _to_rgb_uint8, list_images, load_rgb  # noqa: E402
from speed_accuracy import append_rows, machine  # noqa: E402

COLUMNS = ["date", "machine", "label", "photo", "photo_size", "wanted", "full_decode_s", "half_decode_s", "speedup",
           "psnr_vs_full", "max_difference"]
FRACTIONS = (4, 8, 16)


def full_decode(path: Path, size: tuple[int, int]) -> np.ndarray:
    """What a run reads: the photo decoded in full, then box-filtered to `size`."""
    return load_rgb(path, size)


def half_decode(path: Path, size: tuple[int, int]) -> np.ndarray:
    """The photo decoded at half size by libjpeg, then box-filtered to `size`."""
    with Image.open(path) as image:
        image.draft(None, (image.width // 2, image.height // 2))
        image.load()
        rgb = _to_rgb_uint8(ImageOps.exif_transpose(image))
    return np.asarray(Image.fromarray(rgb).resize(size, resample=Image.BOX))


def make_photos(scene: Path, folder: Path) -> list[Path]:
    source = Image.open(list_images(scene / "images")[0]).convert("RGB")
    smooth = source.resize((source.width * 4, source.height * 4), Image.BICUBIC)
    smooth.save(folder / "smooth.jpg", quality=92)
    detailed = np.asarray(smooth.resize((4032, 3024), Image.BICUBIC), dtype=np.float64)
    detailed += np.random.default_rng(0).normal(0.0, 12.0, detailed.shape)
    Image.fromarray(np.clip(np.round(detailed), 0, 255).astype(np.uint8)).save(folder / "detailed.jpg", quality=92)
    rng = np.random.default_rng(1)
    blocks = np.kron(rng.integers(0, 256, (3024 // 16, 4032 // 16, 3)), np.ones((16, 16, 1)))
    colourful = np.clip(np.round(blocks + rng.normal(0.0, 12.0, blocks.shape)), 0, 255).astype(np.uint8)
    Image.fromarray(colourful).save(folder / "colourful.jpg", quality=92)
    return [folder / "smooth.jpg", folder / "detailed.jpg", folder / "colourful.jpg"]


def median_seconds(read, repeats: int) -> tuple[float, np.ndarray]:
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        result = read()
        times.append(time.perf_counter() - started)
    return statistics.median(times), result


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return float("inf") if mse == 0 else 10 * np.log10(255.0 ** 2 / mse)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--photos", type=Path, help="a folder of JPEG photos (default: make two)")
    parser.add_argument("--scene", type=Path, default=REPO.parent / "shared" / "data" / "canclip")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--label", default="")
    parser.add_argument("--out", type=Path, default=REPO / "docs" / "jpeg_half_decode.csv")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as temp:
        if args.photos is not None:
            photos = [p for p in list_images(args.photos) if p.suffix.lower() in (".jpg", ".jpeg")]
        elif (args.scene / "images").is_dir():
            photos = make_photos(args.scene, Path(temp))
        else:
            sys.exit(f"error: no photos: pass --photos DIR or --scene with an images/ folder ({args.scene})")
        if not photos:
            sys.exit(f"error: no JPEG photos in {args.photos}")
        rows = []
        for path in photos:
            with Image.open(path) as image:
                width, height = ImageOps.exif_transpose(image).size
            for fraction in FRACTIONS:
                size = (max(1, round(width / fraction)), max(1, round(height / fraction)))
                old_s, old = median_seconds(lambda: full_decode(path, size), args.repeats)
                new_s, new = median_seconds(lambda: half_decode(path, size), args.repeats)
                rows.append({"date": date.today().isoformat(), "machine": machine(),
                             "label": args.label, "photo": path.name, "photo_size": f"{width}x{height}",
                             "wanted": f"{size[0]}x{size[1]}", "full_decode_s": round(old_s, 4),
                             "half_decode_s": round(new_s, 4), "speedup": round(old_s / new_s, 2),
                             "psnr_vs_full": round(psnr(new, old), 1),
                             "max_difference": int(np.abs(new.astype(int) - old.astype(int)).max())})
                row = rows[-1]
                print(f"{path.name} {row['photo_size']} -> {row['wanted']}: full {old_s * 1000:.0f} ms, "
                      f"half size {new_s * 1000:.0f} ms ({row['speedup']}x), {row['psnr_vs_full']} dB, "
                      f"max {row['max_difference']}", flush=True)
    append_rows(args.out, rows, COLUMNS)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()

"""Command line: `python -m neulf_synth OUT_DIR [--variant ...] [--grid 4x4] ...`."""

from __future__ import annotations

import argparse
import json
import sys

from .layout import VARIANTS


def _pair(text: str) -> tuple[int, int]:
    try:
        first, second = (int(part) for part in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected AxB with integers, got {text!r}") from None
    return first, second


def _arrangement(text: str) -> int:
    try:
        number = int(text)
    except ValueError:
        number = -1
    if number < 0:
        raise argparse.ArgumentTypeError(f"expected a whole number from 0 on, got {text!r}")
    return number


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="python -m neulf_synth",
        description="Render the NeuLF synthetic forward-facing scene with ground truth.")
    parser.add_argument("out_dir", help="output folder (created if missing)")
    parser.add_argument("--variant", choices=VARIANTS, default="lambertian")
    parser.add_argument("--grid", type=_pair, default=(4, 4), metavar="ROWSxCOLS")
    parser.add_argument("--size", type=_pair, default=(320, 240), metavar="WIDTHxHEIGHT")
    parser.add_argument("--samples", type=int, default=32)
    parser.add_argument("--exposure-jitter", type=float, default=0.0, metavar="STOPS",
                        help="each view's exposure is drawn uniformly in [-STOPS, STOPS]")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--arrangement", type=_arrangement, default=0, metavar="N",
                        help="0: the documented layout; another number: the objects placed, sized and turned "
                             "by a draw of their own (a scene no default was tuned on)")
    parser.add_argument("--no-gt-model", action="store_true",
                        help="skip writing the COLMAP ground-truth model (sparse_gt/0)")
    return parser.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    # Imported here so that --help works quickly and without bpy.
    from .generate import generate_scene

    summary = generate_scene(
        args.out_dir, variant=args.variant, grid=args.grid, size=args.size,
        samples=args.samples, exposure_jitter_stops=args.exposure_jitter, seed=args.seed,
        arrangement=args.arrangement,
        write_gt_model=not args.no_gt_model, progress=lambda line: print(line, flush=True))
    print(json.dumps(summary["timings"]))
    print(f"wrote {len(summary['images'])} views to {summary['out_dir']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The SfM points' depth at the product's budget: the default with and without it, side by side.

    python benchmarks/point_depth.py                         # CanClip and Statue, 1.5 minutes, seeds 0 / 1
    python benchmarks/point_depth.py --scenes statue --minutes 3 --seeds 0
    python benchmarks/point_depth.py --scenes statue --steps 3400 --seeds 0-7 --device cuda --jobs 8 \\
        --out docs/point_depth_statue_h200.csv                  # a GPU: many pairs at once, a fixed step count

benchmarks/side_by_side.py with its two settings fixed: the default as it is (`--point-depth`:
the rays through the training photos' keypoints pulled toward their points' depth,
neulf_core/point_depth.py) against `--no-point-depth`, each pair trained at once on pinned
cores and scored as `eval` scores them (4 points a pixel).  Only scenes whose COLMAP model keeps
tracks change (CanClip and Statue here; fern's and HCI's models have none).  Writes
docs/point_depth.csv (or `--out`; one row per run, `setting` off / on; the CSVs written before
the script shared side_by_side.py name that column `point_depth`) and prints the pairs and the
mean change with its standard error over the seeds.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from side_by_side import DOCS, main  # noqa: E402

if __name__ == "__main__":
    main(description=__doc__, baseline='off={"point_depth": false}', candidate='on={"point_depth": true}',
         scenes="canclip,statue", out=DOCS / "point_depth.csv")

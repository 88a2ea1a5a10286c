"""The defaults on scenes they were not chosen on.

    python benchmarks/untuned_scene.py [--arrangements 1,2] [--seeds 0,1] [--minutes 1.5]

The default's rules (members, back surface, depth layers, the SfM points' pull, the plane
sweep's teacher) and the preset itself were chosen by held-out PSNR on the reference scenes
and the project's synthetic scene, the same views the benchmarks then report: selection on
the test set.  This trains them on scenes none of them saw: the synthetic scene's objects
placed, sized and turned by a draw of their own (`python -m neulf_synth --arrangement N`;
arrangement 0 is the tuned layout), every 8th view held out.  Each alternative trains side by
side with the default (benchmarks/side_by_side.py: the same minutes, one torch thread each,
pinned to a core each), so a rule that only suited its own scenes shows as an alternative
that beats it here.  Writes docs/untuned_scene.csv (a row per run) and docs/untuned_scene.md
(the table), and prints the table.
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import subprocess
import sys
from datetime import date
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DOCS = REPO / "docs"
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

from side_by_side import machine_name, pair, write_rows  # noqa: E402
from seed_scatter import parse_seeds  # noqa: E402
from stability import SYNTH  # noqa: E402  (the stability study's rig, size and samples)

# Each a choice of the default turned the other way, or the authors' network: (label, TrainConfig
# fields, or a function of the scene's rule inputs giving them).  The rules' own choice on each
# scene is what is turned: the back surface by the scene's depth range, the depth layers by it
# and the training views' count (rules.py).  The members are decided while training (by the
# passes a minutes budget makes); "one member" is the same as the default where it trained one.
ALTERNATIVES = [
    ("one member", {"members": 1}),
    ("back surface turned", lambda back_surface, layers: {"back_surface": not back_surface}),
    ("depth layers turned", lambda back_surface, layers: {"field_overrides": {"geometry_layers": 0 if layers else 8}}),
    ("no SfM point pull", {"point_depth": False}),
    ("no sweep teacher", {"teacher": False}),
    ("authors' network", {"preset": "authors"}),
]


def render_arrangement(cache: Path, arrangement: int) -> Path:
    """The synthetic scene with its objects arranged by `arrangement`, rendered once into the
    cache, as a scene folder (its exact model, sparse_gt/0, copied to sparse/0)."""
    out = cache / f"arrangement_{arrangement}"
    if not (out / "sparse" / "0").is_dir():
        command = [sys.executable, "-m", "neulf_synth", str(out), "--arrangement", str(arrangement),
                   *(part for key, value in SYNTH.items() for part in (f"--{key}", value))]
        print("rendering:", " ".join(command[1:]), flush=True)
        subprocess.run(command, check=True, cwd=REPO, stdout=subprocess.DEVNULL)
        shutil.copytree(out / "sparse_gt" / "0", out / "sparse" / "0")
    return out


def rule_inputs(scene: Path) -> tuple[bool, int]:
    """(back surface, depth layers) as the default's rules decide them for this scene's training views."""
    from neulf_core import rules
    from neulf_core.scene import load_scene, split_views
    from neulf_core.slab import fit_slab

    loaded = load_scene(scene)
    train_views, _ = split_views(loaded)
    slab = fit_slab(loaded, train_views)
    return rules.default_back_surface(slab), rules.default_depth_layers(slab, len(train_views))


def table(rows: list[dict]) -> list[str]:
    """Per alternative: each scene and seed's change against the default trained beside it
    (the two ran at once on the same machine), and the mean change with its standard error."""
    pairs = sorted({(r["scene"], r["seed"]) for r in rows})
    lines = ["| alternative | " + " | ".join(f"arr. {a}, seed {d}" for a, d in pairs) + " | mean change | up |",
             "|---|" + "---|" * len(pairs) + "---|---|"]
    for label, _ in ALTERNATIVES:
        cells, changes = [], []
        for scene, seed in pairs:
            ran = {r["setting"]: r for r in rows if (r["scene"], r["seed"], r["paired_with"]) == (scene, seed, label)}
            if label in ran and "default" in ran:
                changes.append(ran[label]["psnr"] - ran["default"]["psnr"])
                cells.append(f"{changes[-1]:+.2f}")
            else:
                cells.append("")
        if changes:
            error = statistics.stdev(changes) / len(changes) ** 0.5 if len(changes) > 1 else float("nan")
            lines.append(f"| {label} | " + " | ".join(cells) + f" | {statistics.mean(changes):+.2f} ± {error:.2f} dB "
                         f"| {sum(c > 0 for c in changes)} of {len(changes)} |")
    lines += ["", "The default's runs (one beside each alternative), median per scene and seed:"]
    for scene, seed in pairs:
        runs = [r for r in rows if (r["scene"], r["seed"], r["setting"]) == (scene, seed, "default")]
        first = runs[0]
        lines.append(f"- arrangement {scene}, seed {seed}: {statistics.median(r['psnr'] for r in runs):.2f} dB "
                     f"({min(r['psnr'] for r in runs):.2f}-{max(r['psnr'] for r in runs):.2f} over {len(runs)} runs), "
                     f"{statistics.median(r['steps'] for r in runs):.0f} steps, {first['members']} member(s), back surface "
                     f"{'on' if first['back_surface'] else 'off'}, {first['depth_layers']} depth layers")
    return lines


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--arrangements", default="1,2", help="comma-separated arrangement numbers (0: the tuned layout)")
    parser.add_argument("--seeds", default="0,1")
    parser.add_argument("--minutes", type=float, default=1.5)
    parser.add_argument("--only", help="comma-separated labels of ALTERNATIVES (default: all)")
    parser.add_argument("--cache", default="/tmp/neulf_untuned")
    parser.add_argument("--out", default=str(DOCS / "untuned_scene.csv"))
    args = parser.parse_args(argv)
    chosen = [a for a in ALTERNATIVES if not args.only or a[0] in args.only.split(",")]
    machine = machine_name(None)
    rows: list[dict] = []
    for arrangement in (int(a) for a in args.arrangements.split(",")):
        scene = render_arrangement(Path(args.cache), arrangement)
        back_surface, layers = rule_inputs(scene)
        for seed in parse_seeds(args.seeds):
            for label, options in chosen:
                options = options(back_surface, layers) if callable(options) else options
                settings = [("default", {}), (label, options)]
                ran = pair(str(arrangement), {"minutes": args.minutes}, seed, settings, None, Path(args.cache),
                           where=(scene, 1.0, None))
                rows += [{**r, "paired_with": label, "date": date.today().isoformat(), "machine": machine} for r in ran]
                write_rows(Path(args.out), rows)
                print(f"arrangement {arrangement} seed {seed}: "
                      + ", ".join(f"{r['setting']} {r['psnr']:.2f} dB ({r['steps']} steps)" for r in ran), flush=True)
    lines = table(rows)
    header = [f"# The defaults on scenes they were not chosen on ({date.today().isoformat()}, {machine})", "",
              f"Generated by `python benchmarks/untuned_scene.py --arrangements {args.arrangements} --seeds {args.seeds} "
              f"--minutes {args.minutes:g}` (docs/untuned_scene.csv). Change in held-out PSNR (every 8th of 16 views, "
              "4 points a pixel) of each alternative against the default trained beside it for the same minutes.", ""]
    Path(args.out).with_suffix(".md").write_text("\n".join(header + lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()

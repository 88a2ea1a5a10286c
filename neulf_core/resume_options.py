"""The options a resumed training keeps as the model has them.

Resuming continues the model as it was trained (train.config_for_resume: its preset, held-out
views, seed, batch, scale, slab and the rules' choices), so an option asked for otherwise is
said, not dropped without a word.  The command line asks with the options written on it;
train() from Python with the TrainConfig fields set away from their defaults.
"""

from __future__ import annotations

import json
from dataclasses import fields
from pathlib import Path

from .errors import NeulfError
from .model_files import read_metadata

# TrainConfig's fields a model keeps from its first training, and the command line's option
# for each ("geometry_layers" stands for field_overrides["geometry_layers"], --depth-layers).
KEPT = {"preset": "--preset", "holdout_every": "--holdout-every", "exclude": "--exclude", "scale": "--scale",
        "st_depth": "--st-depth", "uv_depth": "uv_depth", "near": "--near", "far": "--far",
        "teacher": "--sweep-teacher", "point_depth": "--point-depth", "consistency": "--consistency",
        "appearance": "--appearance", "refine_poses": "--refine-poses", "coarse_to_fine": "--coarse-to-fine",
        "back_surface": "--back-surface", "two_starts": "--two-starts", "pixel_jitter": "--pixel-jitter",
        "seed": "--seed", "batch_size": "--batch-size", "members_split": "--members-split",
        "geometry_layers": "--depth-layers"}
LAYERS = "geometry_layers"
RUN_CHOICES = ("seed", "batch_size", "members_split")  # (the run's, _run_choices)


def fields_set(config) -> set[str]:
    """The kept fields a TrainConfig sets away from its defaults: what a caller from Python asked for."""
    defaults = type(config)()
    asked = {f.name for f in fields(config) if f.name in KEPT and getattr(config, f.name) != getattr(defaults, f.name)}
    if LAYERS in (config.field_overrides or {}):
        asked.add(LAYERS)
    return asked


def kept_on_resume(model_dir, config, asked) -> list[tuple[str, object]]:
    """(field, the model's value) for each field in `asked` whose value in `config` differs from
    the model's own; [] for a folder with no readable model.json (training reads, and checks,
    the checkpoint)."""
    model_dir = Path(model_dir).expanduser()
    saved = read_metadata(model_dir).get("train_config")
    if not isinstance(saved, dict):
        return []
    own = _run_choices(model_dir, saved)
    kept = []
    for name in KEPT:
        if name not in asked:
            continue
        if name == LAYERS:
            wanted, theirs = (config.field_overrides or {}).get(LAYERS), (saved.get("field_overrides") or {}).get(LAYERS)
        elif name in RUN_CHOICES:
            if name not in own:
                continue  # (not recorded: nothing to compare with)
            wanted, theirs = getattr(config, name), own[name]
        elif name in saved:
            wanted, theirs = getattr(config, name), saved[name]
        else:
            continue
        if _listed(wanted) != _listed(theirs):
            kept.append((name, theirs))
    return kept


def kept_message(kept: list[tuple[str, object]], names: dict[str, str] | None = None) -> str:
    """'scale (the model's: 0.5), ...', each field by its name in `names` (default: its own)."""
    names = names or {}

    def value(name, theirs):
        return "the rule" if theirs is None and name == LAYERS else repr(theirs)

    return ", ".join(f"{names.get(name, name)} (the model's: {value(name, theirs)})" for name, theirs in kept)


def _listed(value):
    return list(value) if isinstance(value, tuple) else value


def _run_choices(model_dir: Path, saved: dict) -> dict:
    """The seed, batch and members' split the model's run has, where they are not model.json's
    own: a model's seed is its run's (members.json, or starts.json where a second start was kept,
    whose folder trained with the second seed), its split members.json's, and members that split
    the batch each keep their share of it (the whole is what was asked)."""
    from .presets import get_preset

    def read(name: str) -> dict:
        try:
            record = json.loads((model_dir / name).read_text())
        except (OSError, ValueError):
            return {}
        return record if isinstance(record, dict) else {}

    members, starts = read("members.json"), read("starts.json")
    own = {}
    seed = members.get("seed", starts.get("seed", saved.get("seed")))
    if seed is not None:
        own["seed"] = seed
    if members.get("split"):
        own["members_split"] = members["split"]
    batch = saved.get("batch_size")
    if batch is None and saved.get("preset"):
        try:
            batch = get_preset(saved["preset"]).batch_size
        except NeulfError:  # (a preset of another version: training says so)
            batch = None
    if members and saved.get("batch_size") and members.get("split") == "batch":
        batch = int(saved["batch_size"]) * int(members.get("count", 1))
    if batch is not None:
        own["batch_size"] = batch
    return own

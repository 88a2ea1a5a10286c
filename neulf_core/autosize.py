"""The `auto` preset: the smallest fast field a scene needs, chosen on validation views.

Validation views are carved from the training views (every 8th of them; the held-out test
views are never looked at).  A few texture sizes of the fast field train for the same short
step budget on the rest, each is scored on the validation views, and the smallest whose PSNR
is within `tolerance_db` of the largest tried wins; that size then trains on all training
views for the remaining budget.  Everything goes through `train.train()`: a candidate is a
TrainConfig with more views excluded and a texture-size override.
"""

from __future__ import annotations

import contextlib
import json
import shutil
import tempfile
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from .checkpoint import METADATA_NAME, MODEL_NAME, checkpoint_path, load_checkpoint, save_checkpoint
from .clock import running_time
from .errors import NeulfError
from .fields.disparity import texture_size_for
from .files import atomic_write_bytes, refuse_a_path_too_long
from .interrupt import stops_at_once
from .lock import training_lock
from .memo import kept_while_training
from .metrics import psnr
from .render import LightField
from .scene import Scene, load_scene, scaled_size, split_views
from .slab import fit_slab
from .train import (TrainConfig, TrainResult, check_config, longest_path_written, refuse_to_overwrite,
                    say_nothing_to_resume, train)
from .progress import emit as _emit
from .rules import (LOSSES_DECISION_STEP, announce_default_losses, default_back_surface, default_coarse_to_fine,
                    default_consistency, default_depth_detail_reads, default_geometry_tv, default_max_passes,
                    with_default_scale)

PRESET = "auto"
FACTORS = (1.0, 0.7, 0.5)    # finest texture size / the default (~1 texel per pixel); area 1, 1/2, 1/4
TOLERANCE_DB = 0.3
VALIDATION_EVERY = 8          # every 8th training view validates the candidates
SEARCH_SHARE = 0.4            # of the budget spent on the candidates together
# The search as it goes (each candidate scored, then the choice and the final model's options),
# in the model folder until the model's checkpoint holds the record: a run stopped or killed
# during the search resumes after its last scored candidate, one stopped before the final
# model's first checkpoint trains the chosen size at once, and a resumed model trains to its
# share of the new budget (the whole of it, search included, before).
SEARCH_FILE = "autosize.json"
# The candidates' and the rate probe's training folders, inside the model folder: a run killed
# outright (SIGKILL) had left them in the system's temporary folder, where nothing removed them;
# here the next run into the folder does (train_auto).
SCRATCH_DIR = ".autosize-scratch"
SCRATCH_PREFIX = "neulf-auto-"


@dataclass
class Candidate:
    factor: float
    overrides: dict
    steps: int = 0
    val_psnr: float = float("nan")
    model_bytes: int = 0      # model.pt, what ships


def texture_overrides(train_views, scale: float, factor: float = 1.0, *, channels: int | None = None,
                      levels: int | None = None) -> dict:
    """Field overrides for a fast field whose finest texture is `factor` times the default
    (about one texel per training pixel)."""
    rows, cols = texture_size_for(scaled_size(max(v.size for v in train_views), scale))
    overrides = {"texture_size": [max(2, int(round(rows * factor))), max(2, int(round(cols * factor)))]}
    if channels is not None:
        overrides["texture_channels"] = channels
    if levels is not None:
        overrides["texture_levels"] = levels
    return overrides


def choose(candidates: list[Candidate], tolerance_db: float = TOLERANCE_DB) -> Candidate:
    """The smallest candidate whose validation PSNR is within tolerance of the largest one's."""
    by_size = sorted(candidates, key=lambda c: (c.model_bytes, c.factor))  # equal bytes: the smaller texture first
    reference = by_size[-1].val_psnr
    return next(c for c in by_size if c.val_psnr >= reference - tolerance_db)


def validation_split(scene: Scene, config: TrainConfig):
    """(views the candidates train on, validation views, held-out test views)."""
    train_views, held = split_views(scene, config.holdout_every, config.exclude)
    validation = train_views[::VALIDATION_EVERY]
    names = {v.name for v in validation}
    fit = [v for v in train_views if v.name not in names]
    if len(fit) < 2:
        raise NeulfError(f"the auto preset needs at least 3 training views (it validates on every {VALIDATION_EVERY}th); "
                         f"this scene has {len(train_views)}: use --preset fast.")
    return fit, validation, held


def mean_view_psnr(model_dir: Path, views, scale: float, device: str | None = None) -> float:
    """Mean PSNR of full renders of `views` by the shipped model file (model.pt)."""
    return float(np.mean(view_psnrs(model_dir, views, scale, device)))


def view_psnrs(model_dir: Path, views, scale: float, device: str | None = None) -> list[float]:
    """Each view's PSNR, its full render by the shipped model file (model.pt) against its photo."""
    light_field = LightField.load(model_dir, device, precision="full")
    return [psnr(light_field.render_view(v, scale, depth=False).rgb, v.load_image(scale).astype(np.float32) / 255.0)
            for v in views]


def _rescaled(progress, offset: float, share: float, label: str | None):
    """Forward a run's progress events into the whole auto run's [0, 1].  A candidate's own
    start/checkpoint/finished events are not the model's and are dropped, and so is its
    held-out PSNR (train() pools the test views with the validation views it excluded), and the
    warning that its budget left it barely trained (a candidate's is short by design)."""
    def report(event: dict) -> None:
        if progress is None or (label and (event.get("event") in ("start", "checkpoint", "finished", "cancelled")
                                           or event.get("barely_trained"))):
            return
        if "fraction" in event:
            event = {**event, "fraction": offset + share * event["fraction"]}
        if label:
            event = {**event, "candidate": label, **({"val_psnr": None} if "val_psnr" in event else {})}
        progress(event)
    return report


def train_auto(scene: Scene | str | Path, model_dir: str | Path, config: TrainConfig, *, images_dir=None,
               resume: bool = False, progress=None, should_stop=None, factors=FACTORS,
               tolerance_db: float = TOLERANCE_DB, asked: dict[str, str] | None = None) -> TrainResult:
    """`train()` for the auto preset: size search on validation views, then the final run
    (`asked`: as train()'s)."""
    model_dir = Path(model_dir).expanduser()
    check_config(config)
    # The folder's lock is held through the search too (its 40 % of the budget): a second training
    # of the folder started meanwhile trained to its end, and this run, its search spent, was then
    # refused as overwriting a model.  The final train() takes the lock again (training_lock).
    with training_lock(model_dir):
        # (a candidate's folder: tempfile's 8 random characters after the prefix)
        refuse_a_path_too_long(model_dir, Path(SCRATCH_DIR) / f"{SCRATCH_PREFIX}{'x' * 8}" / longest_path_written(config))
        shutil.rmtree(model_dir / SCRATCH_DIR, ignore_errors=True)  # a killed run's (the lock says none is running)
        if resume and checkpoint_path(model_dir).is_file():  # the size was chosen before: continue it
            record = load_checkpoint(model_dir).get("autosize") or (saved_search(model_dir) or {}).get("record")
            result = train(scene, model_dir, final_budget(config, record), images_dir=images_dir, resume=True,
                           progress=progress, should_stop=should_stop, asked=asked)
            return _record(model_dir, record, result)
        refuse_to_overwrite(model_dir, resume)  # (said before the search spends its share of the budget)
        saved = saved_search(model_dir) if resume else None
        if resume and saved is None:  # (and nothing to resume: the search starts)
            say_nothing_to_resume(model_dir, progress)
        elif saved is not None:
            _emit(progress, event="stage", message=f"auto: {len(saved['candidates'])} texture size(s) scored before "
                                                     "are kept" + ("; the size chosen trains" if "record" in saved else ""))
        if saved is None:  # (a new run's search is its own)
            (model_dir / SEARCH_FILE).unlink(missing_ok=True)
        # A minutes budget is the whole run's: the photos' loading and the rules' probe too, and the search's
        # time before a stop.
        started = running_time() - (saved or {}).get("search_seconds", 0.0)
        if not isinstance(scene, Scene):
            with stops_at_once():  # (nothing is training yet: a stop need not wait for a step)
                scene = load_scene(scene, images_dir)
        # One training call (memo.py): the candidates read the photos and build their rays once, and
        # a warning about the scale is said once.
        with kept_while_training():
            return _search_and_train(scene, model_dir, replace(config, preset=PRESET), progress, should_stop, factors,
                                     tolerance_db, started, saved)


def saved_search(model_dir: Path) -> dict | None:
    """The search's SEARCH_FILE where a run left one that can be read, else None (searched again)."""
    try:
        saved = json.loads((Path(model_dir) / SEARCH_FILE).read_text())
        [Candidate(**c) for c in saved["candidates"]], float(saved["search_seconds"])
        if "record" in saved:
            TrainConfig(**saved["final_config"])
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return saved


def _save_search(model_dir: Path, search: dict) -> None:
    atomic_write_bytes(model_dir / SEARCH_FILE, json.dumps(search, indent=2).encode())


def final_budget(config: TrainConfig, record: dict | None) -> TrainConfig:
    """`config`'s budget less the search's (its candidates' steps, or its seconds): the final
    model's share, as the run that searched gave it."""
    if not record:  # (a model the search's record was lost from: its whole budget, as before)
        return config
    if config.steps:
        return replace(config, steps=max(1, config.steps - sum(int(c["steps"]) for c in record["candidates"])))
    return replace(config, minutes=max(config.minutes * 0.05, config.minutes - float(record["search_seconds"]) / 60))


def _search_and_train(scene: Scene, model_dir: Path, config: TrainConfig, progress, should_stop, factors,
                      tolerance_db: float, started: float, saved: dict | None = None) -> TrainResult:
    if saved is not None and "record" in saved:  # the size was chosen before the stop: it trains
        record = saved["record"]
        final = final_budget(replace(TrainConfig(**saved["final_config"]), steps=config.steps, minutes=config.minutes,
                                     checkpoint_seconds=config.checkpoint_seconds,
                                     validate_seconds=config.validate_seconds, device=config.device), record)
    else:
        with search_scratch(model_dir) as scratch:
            with stops_at_once():  # (the rules' decisions: nothing a stop could lose)
                config = with_default_scale(scene, config, progress=progress)
                config = final_model_defaults(scene, config, progress, scratch)
            done = [Candidate(**c) for c in saved["candidates"]] if saved is not None else []
            searched = _search(scene, config, factors, progress, should_stop, started, model_dir, done, scratch)
        if searched is None:  # cancelled: the candidates scored are kept (SEARCH_FILE), --resume goes on from them
            return TrainResult(model_dir, "cancelled", 0, running_time() - started, None, [])
        candidates, validation = searched
        chosen = choose(candidates, tolerance_db)
        record = {"candidates": [asdict(c) for c in candidates], "chosen": asdict(chosen), "tolerance_db": tolerance_db,
                  "validation_views": [v.name for v in validation], "search_seconds": round(running_time() - started, 1)}
        final = final_budget(replace(config, field_overrides=chosen.overrides), record)
        _save_search(model_dir, {"candidates": record["candidates"], "search_seconds": record["search_seconds"],
                                 "record": record, "final_config": asdict(final)})
        _emit(progress, event="autosize", stage="chosen", **record)
        _emit(progress, event="stage", message=f"auto: chose texture x{chosen.factor:g} {chosen.overrides['texture_size']}")
    result = train(scene, model_dir, final, progress=_rescaled(progress, SEARCH_SHARE, 1 - SEARCH_SHARE, None),
                   should_stop=should_stop)
    return _record(model_dir, record, result)


@contextlib.contextmanager
def search_scratch(model_dir: Path):
    """SCRATCH_DIR of `model_dir` while the search runs, removed after it (and after a failure)."""
    folder = Path(model_dir) / SCRATCH_DIR
    folder.mkdir(parents=True, exist_ok=True)
    try:
        yield folder
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def final_model_defaults(scene: Scene, config: TrainConfig, progress, scratch: Path | None = None) -> TrainConfig:
    """`config` with the view-count rules left to the default (rules.default_consistency,
    rules.default_coarse_to_fine, rules.default_depth_detail_reads, rules.default_geometry_tv,
    rules.default_max_passes, rules.default_back_surface) decided once, for the final
    model's training views: the search runs (fewer views: the validation views are carved
    out) train as the model will.  `scratch`: where a rate probe trains (None: the system's
    temporary folder)."""
    train_views, _ = split_views(scene, config.holdout_every, config.exclude)
    if config.coarse_to_fine is None:
        config = replace(config, coarse_to_fine=default_coarse_to_fine(len(train_views)))
    if config.max_passes is None:
        config = replace(config, max_passes=default_max_passes(len(train_views)))
    rules = {"depth_detail_reads": default_depth_detail_reads, "tv_weight": default_geometry_tv}
    chosen = {name: rule(len(train_views)) for name, rule in rules.items() if name not in config.field_overrides}
    config = replace(config, field_overrides={**config.field_overrides, **chosen})
    slab = fit_slab(scene, train_views, scale=config.scale, st_depth=config.st_depth, uv_depth=config.uv_depth,
                    near=config.near, far=config.far)
    if config.back_surface is None:  # the search's slab, of fewer views, could fall on the other side of the rule
        config = replace(config, back_surface=default_back_surface(slab))
    if config.consistency is None:
        decided = default_consistency(slab, train_views, config)
        if decided is None:  # a minutes budget: how many steps it buys is measured, as train() does
            decided = default_consistency(slab, train_views, config, _steps_per_minute(scene, config, scratch))
        config = replace(config, consistency=decided)  # (LOSSES_UNTIL_POSES_RIGHT: each run's pose check ends them)
        if config.consistency:
            announce_default_losses(progress, len(train_views))
    return config


def _steps_per_minute(scene: Scene, config: TrainConfig, scratch: Path | None = None) -> float:
    """The step rate with the multi-view losses on that train() counts a minutes budget at
    (rules.measured_steps_per_minute), from a run of its first steps in a scratch folder (its
    steps end it; a minute at least, so that a short budget on a busy machine still gets
    there, and 0 if it did not)."""
    probe = replace(config, steps=LOSSES_DECISION_STEP + 1, minutes=max(config.minutes, 1.0), consistency=None,
                    teacher=False, refine_poses=False, checkpoint_seconds=1e9, validate_seconds=1e9, two_starts=False)
    with tempfile.TemporaryDirectory(prefix=f"{SCRATCH_PREFIX}rate-", dir=scratch) as folder:
        train(scene, folder, probe)
        return float(json.loads((Path(folder) / METADATA_NAME).read_text()).get("losses_steps_per_minute", 0.0))


def _search(scene: Scene, config: TrainConfig, factors, progress, should_stop, started: float, model_dir: Path,
            done: list[Candidate] = (), scratch: Path | None = None):
    """Train and score every candidate size: (candidates, validation views), None if cancelled.
    `started`: when the auto run began (running_time()); `done`: candidates a stopped run
    scored (SEARCH_FILE), kept as they are; each one scored here is added to the file."""
    fit, validation, held = validation_split(scene, config)
    _emit(progress, event="stage", message=f"auto: {len(factors)} texture sizes, validated on "
                                             f"{', '.join(v.name for v in validation)}")
    candidates = [Candidate(f, {**config.field_overrides, **texture_overrides(fit, config.scale, f)})
                  for f in sorted(factors, reverse=True)]
    steps, share = _candidate_steps(config, len(candidates)), SEARCH_SHARE / len(candidates)
    scored = {c.factor: c for c in done}
    for i, candidate in enumerate(candidates):
        if candidate.factor in scored:
            candidates[i] = scored[candidate.factor]
            steps = steps or candidates[i].steps
            continue
        budget = {"steps": steps, "minutes": None} if steps else {"steps": None,
                                                                   "minutes": _first_candidate_minutes(config, len(candidates), started)}
        run = candidate_config(config, candidate, budget, held + validation)
        report = _rescaled(progress, i * share, share, f"x{candidate.factor:g}")
        if not score_candidate(scene, run, candidate, validation, report, should_stop, scratch=scratch):
            return None
        steps = steps or candidate.steps  # a minutes budget: the largest candidate sets the steps for the rest
        _save_search(model_dir, {"candidates": [asdict(c) for c in candidates[:i + 1]],
                                 "search_seconds": round(running_time() - started, 1)})
        _emit(progress, event="autosize", stage="candidate", **asdict(candidate))
        _emit(progress, event="stage", message=f"auto: texture x{candidate.factor:g} {candidate.overrides['texture_size']}: "
                                                 f"{candidate.val_psnr:.2f} dB, {candidate.model_bytes / 1e6:.2f} MB")
    return candidates, validation


def candidate_config(config: TrainConfig, candidate: Candidate, budget: dict, excluded_views) -> TrainConfig:
    """How one candidate trains: its texture, `budget` ({"steps": n, "minutes": None} or the
    reverse), without the `excluded_views` (held-out and validation)."""
    # Sizes compared from one start, and without the sweep teacher: its early pull toward the sweep's
    # depth evens the short candidates out, so the smallest wins -- with it CanClip's search picked
    # x0.5 where it picks x0.7-x1, and the model lost 1.5 dB at 1.5 minutes (docs/BENCHMARKS.md,
    # "The auto preset").  The final run trains with it as the preset says.
    return replace(config, **budget, exclude=[v.name for v in excluded_views], field_overrides=candidate.overrides,
                   checkpoint_seconds=1e9, validate_seconds=1e9, two_starts=False, teacher=False)


def score_candidate(scene: Scene, run: TrainConfig, candidate: Candidate, validation, progress, should_stop, *,
                    scratch: Path | None = None) -> bool:
    """Train one candidate in a folder of its own in `scratch` (None: the system's temporary
    folder) and fill in its steps, PSNR and file size."""
    with tempfile.TemporaryDirectory(prefix=SCRATCH_PREFIX, dir=scratch) as folder:
        result = train(scene, folder, run, progress=progress, should_stop=should_stop)
        if result.status == "cancelled":
            return False
        candidate.steps = result.step
        candidate.val_psnr = mean_view_psnr(Path(folder), validation, run.scale, run.device)
        candidate.model_bytes = (Path(folder) / MODEL_NAME).stat().st_size
    return True


def _first_candidate_minutes(config: TrainConfig, count: int, started: float) -> float:
    """A minutes budget: the first candidate's minutes (the rest train its steps), its even part
    of the search's share less the time already spent loading the photos and deciding the rules
    (fern at 1.5 minutes: 5 of the search's 36 seconds), so the model keeps its share; a quarter
    of the even part at least."""
    even = config.minutes * SEARCH_SHARE / count
    left = config.minutes * SEARCH_SHARE - (running_time() - started) / 60
    return max(even / 4, left / count)


def _candidate_steps(config: TrainConfig, count: int) -> int | None:
    """Steps per candidate for a steps budget; None for a minutes budget (set by the first)."""
    return max(1, int(config.steps * SEARCH_SHARE / count)) if config.steps else None


def _record(model_dir: Path, record: dict | None, result: TrainResult) -> TrainResult:
    """The search's candidates and choice into the saved model's metadata (all three files)."""
    if record is not None and checkpoint_path(model_dir).is_file():
        payload = load_checkpoint(model_dir)
        payload["autosize"] = record
        save_checkpoint(model_dir, payload)
        (Path(model_dir) / SEARCH_FILE).unlink(missing_ok=True)  # (the checkpoint holds it now)
    return result

"""The auto preset (autosize.py) stopped or killed at any point resumes to the model a run never
stopped trains: the size search goes on after its last scored candidate, a size chosen before
the final model's first checkpoint trains at once, and a resumed model trains to its share of
the budget (the search's steps taken off), with the search's record kept in model.json.

A kill is an exception raised from the progress callback: nothing after it runs but the
`finally` blocks, as after SIGKILL (the training lock aside, which a dead process leaves)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from conftest import assert_same_weights
from neulf_core.autosize import SEARCH_FILE, train_auto
from neulf_core.checkpoint import METADATA_NAME, load_checkpoint
from neulf_core.train import TrainConfig

STEPS = 150  # three candidates of 20 steps (40 % of the budget), then the chosen size's 90


class Killed(Exception):
    pass


def _config(**extra) -> TrainConfig:
    options = dict(preset="auto", steps=STEPS, batch_size=512, seed=0, validate_seconds=1e9, checkpoint_seconds=1e9,
                   device="cpu")
    return TrainConfig(**{**options, **extra})


def _kill_at(predicate):
    """A progress callback that raises Killed at the first event `predicate` accepts."""
    def progress(event: dict) -> None:
        if predicate(event):
            raise Killed(event)
    return progress


@pytest.fixture(scope="module")
def never_stopped(tiny_scene, tmp_path_factory):
    model = tmp_path_factory.mktemp("auto_never_stopped")
    train_auto(tiny_scene, model, _config())
    return model


def _record(model) -> dict:
    record = dict(json.loads((model / METADATA_NAME).read_text())["autosize"])
    record.pop("search_seconds")
    return record


def _candidate_runs(tiny_scene, model, monkeypatch) -> list:
    """Resume `model`, counting the candidates the search trains."""
    import neulf_core.autosize as autosize

    trained, real = [], autosize.score_candidate
    monkeypatch.setattr(autosize, "score_candidate", lambda *a, **k: trained.append(a[2].factor) or real(*a, **k))
    train_auto(tiny_scene, model, _config(), resume=True)
    return trained


@pytest.mark.parametrize("killed_after", [1, 2])
def test_a_search_killed_after_scored_candidates_goes_on_from_them(tiny_scene, tmp_path, never_stopped, monkeypatch,
                                                                   killed_after, record_property):
    model = tmp_path / "model"
    seen = []
    with pytest.raises(Killed):
        train_auto(tiny_scene, model, _config(), progress=_kill_at(
            lambda e: e.get("event") == "autosize" and e.get("stage") == "candidate"
            and seen.append(e) is None and len(seen) == killed_after))
    saved = json.loads((model / SEARCH_FILE).read_text())
    assert len(saved["candidates"]) == killed_after and "record" not in saved
    assert _candidate_runs(tiny_scene, model, monkeypatch) == [1.0, 0.7, 0.5][killed_after:]
    assert _record(model) == _record(never_stopped)
    assert_same_weights(model, never_stopped)
    assert not (model / SEARCH_FILE).exists()  # (the checkpoint holds the record now)
    record_property("message", "the size search goes on after its last scored candidate")


def test_a_size_chosen_before_the_final_models_first_checkpoint_trains_at_once(tiny_scene, tmp_path, never_stopped,
                                                                              monkeypatch):
    model = tmp_path / "model"
    with pytest.raises(Killed):
        train_auto(tiny_scene, model, _config(), progress=_kill_at(
            lambda e: e.get("event") == "autosize" and e.get("stage") == "chosen"))
    assert "record" in json.loads((model / SEARCH_FILE).read_text())
    assert _candidate_runs(tiny_scene, model, monkeypatch) == []  # no candidate trains again
    assert _record(model) == _record(never_stopped)
    assert_same_weights(model, never_stopped)


def test_a_final_model_killed_after_a_checkpoint_resumes_to_its_share_of_the_budget(tiny_scene, tmp_path,
                                                                                   never_stopped, record_property):
    """It trained the whole --steps before (150 where a run never stopped trains 90), and the
    search's record was lost from model.json."""
    model = tmp_path / "model"
    with pytest.raises(Killed):
        train_auto(tiny_scene, model, _config(checkpoint_seconds=0.01), progress=_kill_at(
            lambda e: e.get("event") == "checkpoint" and e.get("step", 0) >= 40))
    assert load_checkpoint(model)["progress"]["step"] >= 40 and "autosize" not in load_checkpoint(model)
    train_auto(tiny_scene, model, _config(), resume=True)
    assert load_checkpoint(model)["progress"]["step"] == load_checkpoint(never_stopped)["progress"]["step"] == 90
    assert _record(model) == _record(never_stopped)
    # A finished model resumed with the same budget trains no further.
    train_auto(tiny_scene, model, _config(), resume=True)
    assert load_checkpoint(model)["progress"]["step"] == 90
    record_property("message", "the final model resumes to its share of the budget, the search's record kept")


def test_a_new_training_does_not_take_a_stopped_runs_search(tiny_scene, tmp_path, monkeypatch):
    model = tmp_path / "model"
    model.mkdir()
    (model / SEARCH_FILE).write_text(json.dumps({"candidates": [], "search_seconds": 1.0}))
    import neulf_core.autosize as autosize

    trained, real = [], autosize.score_candidate
    monkeypatch.setattr(autosize, "score_candidate", lambda *a, **k: trained.append(a[2].factor) or real(*a, **k))
    train_auto(tiny_scene, model, _config())
    assert trained == [1.0, 0.7, 0.5] and not (model / SEARCH_FILE).exists()
    # A damaged file is searched again, not trusted.
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / SEARCH_FILE).write_text("{not json")
    assert autosize.saved_search(tmp_path / "other") is None


def test_the_search_trains_inside_the_model_folder_and_clears_a_killed_runs_folders(tiny_scene, tmp_path, monkeypatch):
    """The candidates (and the rate probe) train in the model folder's SCRATCH_DIR, which the
    search removes; one a run killed outright left (SIGKILL runs no `finally`) is removed by the
    next run.  They had trained in the system's temporary folder, where a kill left them for good."""
    import tempfile

    import neulf_core.autosize as autosize

    system_temp = tmp_path / "system_temp"
    system_temp.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(system_temp))
    model = tmp_path / "model"
    left_by_a_kill = model / autosize.SCRATCH_DIR / (autosize.SCRATCH_PREFIX + "killed")
    left_by_a_kill.mkdir(parents=True)
    (left_by_a_kill / "checkpoint.pt").write_bytes(b"a candidate's checkpoint")
    folders, real_train = [], autosize.train
    monkeypatch.setattr(autosize, "train", lambda scene, folder, *a, **k: folders.append(Path(folder)) or
                        real_train(scene, folder, *a, **k))

    assert train_auto(tiny_scene, model, _config(steps=60)).status == "finished"

    candidates = [f for f in folders if f != model]
    assert len(candidates) == 3 and all(f.parent == model / autosize.SCRATCH_DIR for f in candidates), folders
    assert not (model / autosize.SCRATCH_DIR).exists() and list(system_temp.iterdir()) == []

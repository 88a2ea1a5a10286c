"""Per-photo pose refinement (neulf_core/poses.py): the geometry of the corrected rays, that the
photometric gradient finds a known pose error, and its place in training and resuming."""

import json
import math

import numpy as np
import pytest
import torch

from neulf_core.poses import RIG_WIDE_START, PoseRefinement, own_part_projector, rotation_matrices
from neulf_core.slab import Slab

# World frame = slab frame; uv plane at z = 0, st plane at z = 3.
SLAB = Slab(np.eye(3), np.zeros(3), 0.0, 3.0, 2.0, 6.0, np.array([-1.0, -1.0, -2.0, -2.0]), np.array([1.0, 1.0, 2.0, 2.0]))
CENTRES = np.array([[-0.2, 0.0, -0.5], [0.2, 0.0, -0.5]])


def camera_rays(centre, n=64, seed=0):
    rng = np.random.default_rng(seed)
    directions = np.column_stack([rng.uniform(-0.3, 0.3, (n, 2)), np.ones(n)])
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    return torch.tensor(centre, dtype=torch.float64), torch.tensor(directions)


def test_rotation_matrices_match_rodrigues():
    axis_angle = torch.tensor([[0.0, 0.0, 0.0], [0.01, -0.02, 0.005], [0.3, 0.1, -0.2]], dtype=torch.float64)
    rotations = rotation_matrices(axis_angle)
    for vector, rotation in zip(axis_angle.numpy(), rotations.numpy()):
        angle = np.linalg.norm(vector)
        if angle == 0:
            assert np.allclose(rotation, np.eye(3))
            continue
        k = np.array([[0, -vector[2], vector[1]], [vector[2], 0, -vector[0]], [-vector[1], vector[0], 0]]) / angle
        exact = np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k
        assert np.allclose(rotation, exact, atol=1e-6)  # the series is exact to ~angle^6 / 5040
        assert np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-6)


def test_zero_corrections_leave_the_rays_alone():
    poses = PoseRefinement(SLAB, CENTRES)
    origin, directions = camera_rays(CENTRES[0])
    uvst, _ = SLAB.rays_to_uvst(origin, directions)
    moved = poses(uvst.float(), torch.zeros(len(uvst), dtype=torch.long))
    assert torch.allclose(moved, uvst.float(), atol=1e-6)


def test_a_correction_moves_the_rays_as_the_moved_camera_sees_them():
    """Turning camera 0 by R about its centre and shifting it by d gives the (u, v, s, t) of the
    rays that camera would cast from c + d with directions R d_i."""
    poses = PoseRefinement(SLAB, CENTRES)
    # (No turn about y nor shift along x: for two cameras on the x axis those are the rig
    # fanning out and its baseline growing, which the corrections hold at zero.)
    turn = torch.tensor([0.004, 0.0, 0.01])
    shift = torch.tensor([0.0, -0.02, 0.03])  # shares of the spacing (0.4 here)
    with torch.no_grad():  # opposite corrections: their mean is zero, so centring keeps them
        poses.rotation[:] = torch.stack([turn, -turn])
        poses.shift[:] = torch.stack([shift, -shift])
    assert poses.spacing == pytest.approx(0.4)
    origin, directions = camera_rays(CENTRES[0])
    uvst, _ = SLAB.rays_to_uvst(origin, directions)
    moved = poses(uvst.float(), torch.zeros(len(uvst), dtype=torch.long)).double()

    rotation = rotation_matrices(turn.double()[None])[0]
    expected, _ = SLAB.rays_to_uvst(origin + shift.double() * 0.4, directions @ rotation.T)
    assert torch.allclose(moved, expected, atol=1e-5)
    assert (moved - uvst).abs().max() > 1e-2  # and it did move them


def test_the_own_part_projector_removes_what_varies_linearly_over_the_rig():
    grid = np.array([[x, y] for x in range(3) for y in range(3)], dtype=np.float64)
    projector = own_part_projector(grid)
    rig_wide = np.column_stack([np.ones(9), grid]) @ np.array([[0.3, -0.1], [0.02, 0.05], [-0.04, 0.01]])
    own = np.random.default_rng(0).normal(size=(9, 2))
    own = own - np.column_stack([np.ones(9), grid]) @ np.linalg.lstsq(np.column_stack([np.ones(9), grid]), own, rcond=None)[0]
    assert np.allclose(projector @ rig_wide, 0, atol=1e-12)
    assert np.allclose(projector @ (rig_wide + own), own, atol=1e-12)
    assert np.allclose(projector @ projector, projector, atol=1e-12)
    # Cameras on a line: only the constant and the slope along the line are rig-wide.
    line = np.column_stack([np.arange(5.0), np.zeros(5)])
    kept = own_part_projector(line) @ np.array([1.0, -2.0, 1.0, 0.0, 0.0])  # no constant, no slope
    assert np.allclose(kept, [1.0, -2.0, 1.0, 0.0, 0.0]) and np.linalg.matrix_rank(own_part_projector(line)) == 3


def test_the_rig_wide_part_of_the_corrections_joins_after_a_fifth_of_the_budget():
    """Early on only each camera's own part of its correction acts; a rig-wide fan (rotations
    linear in the camera's position) drifts freely on a noisy field, so it waits (poses.py)."""
    centres = np.array([[x * 0.2, y * 0.2, -0.5] for x in range(3) for y in range(3)])
    poses = PoseRefinement(SLAB, centres)
    fan = torch.tensor([[0.0, 0.01 * c[0], 0.0] for c in centres], dtype=torch.float32)  # turning about y, more the further right
    own = torch.zeros(9, 3)
    own[4, 0], own[[1, 3, 5, 7], 0] = 0.004, -0.001  # the middle camera tilts against its neighbours
    with torch.no_grad():
        poses.rotation[:] = fan + own
    poses.set_training_progress(0.0)
    early, _ = poses.corrections()
    assert torch.allclose(early, own, atol=1e-6)
    poses.set_training_progress(RIG_WIDE_START)
    late, _ = poses.corrections()
    centred = (fan + own - (fan + own).mean(0)).double().numpy()
    fanning, _ = _fanning_and_baseline(centres)  # (the part a change of depth is: held, below)
    assert np.allclose(late.detach().double().numpy(), centred - (centred * fanning).sum() * fanning, atol=1e-6)
    assert not poses.own_part_only  # and what is saved and rendered is the full correction
    assert "own_part" not in poses.state_dict()  # follows from the centres; older models load


def _mean_st_move(poses, centres):
    """(V, 2): how far each camera's rays' st crossings move under the corrections, on average."""
    moves = []
    for index, centre in enumerate(centres):
        origin, directions = camera_rays(centre, seed=index)
        uvst, _ = SLAB.rays_to_uvst(origin, directions)
        moved = poses(uvst.float(), torch.full((len(uvst),), index, dtype=torch.long))
        moves.append((moved - uvst.float())[:, 2:].mean(0))
    return torch.stack(moves).detach().double().numpy()


def _fanning_and_baseline(centres):
    """(V, 3) unit vectors over all views' rotations and shifts: the rig fanning out (each camera
    turned toward +u at +u, +v at +v) and its baseline growing (each moved outward)."""
    position = centres[:, :2] - centres[:, :2].mean(0)
    fanning = np.column_stack([-position[:, 1], position[:, 0], np.zeros(len(centres))])
    baseline = np.column_stack([position[:, 0], position[:, 1], np.zeros(len(centres))])
    return fanning / np.linalg.norm(fanning), baseline / np.linalg.norm(baseline)


def test_the_fanning_is_a_change_of_depth_and_the_twist_is_not():
    """Why the corrections hold the fanning: it turns each camera so that its view shifts by one
    factor times the camera's position, in u and in v alike -- what a uniform change of the
    scene's inverse depth does to a light field, so the photos cannot pin it.  A twist of the
    rig, which the photos do show, shifts the views otherwise.  (Uncentred corrections, which
    hold nothing, show what each direction does.)"""
    centres = np.array([[x * 0.2, y * 0.2, -0.5] for x in (-1, 0, 1) for y in (-1, 0, 1)])
    position = centres[:, :2] - centres[:, :2].mean(0)
    fanning, _ = _fanning_and_baseline(centres)
    raw = PoseRefinement(SLAB, centres, centred=False, spacing=0.2)
    with torch.no_grad():
        raw.rotation[:] = torch.tensor(0.02 * fanning)
    moves = _mean_st_move(raw, centres)
    factor = (moves * position).sum() / (position ** 2).sum()  # one factor for both axes
    assert abs(factor) > 1e-3
    assert np.abs(moves - factor * position).max() < 0.02 * np.abs(moves).max()
    twist = np.column_stack([np.zeros(9), 0.01 * position[:, 1], 0.01 * position[:, 0]])
    with torch.no_grad():
        raw.rotation[:] = torch.tensor(twist)
    moves = _mean_st_move(raw, centres)  # the view shifts along u in proportion to v
    assert np.abs(moves - ((moves * position).sum() / (position ** 2).sum()) * position).max() > 0.5 * np.abs(moves).max()


def test_the_corrections_hold_no_fanning_and_no_baseline_growth():
    """The two depth-like directions are projected out of the corrections, as the mean is
    (DEPTH_LIKE_GAUGE): whatever the learned values hold of them, the corrections that move the
    rays hold none; each camera's own part and the rig's twists and shears pass unchanged.  A
    lone camera (fitting one held-out view) keeps its whole correction."""
    centres = np.array([[x * 0.2, y * 0.2, -0.5] for x in (-1, 0, 1) for y in (-1, 0, 1)])
    position = centres[:, :2] - centres[:, :2].mean(0)
    fanning, baseline = _fanning_and_baseline(centres)
    rng = np.random.default_rng(0)
    own = own_part_projector(position) @ rng.normal(size=(9, 3)) * 0.01
    zero = np.zeros(9)
    twist = np.column_stack([zero, 0.01 * position[:, 1], 0.01 * position[:, 0]])
    shear = np.column_stack([position[:, 1], position[:, 0], zero]) * 0.1
    poses = PoseRefinement(SLAB, centres)
    poses.set_training_progress(1.0)
    with torch.no_grad():
        poses.rotation[:] = torch.tensor(own + twist + 0.02 * fanning + 0.003, dtype=torch.float32)
        poses.shift[:] = torch.tensor(own + shear + 0.5 * baseline - 0.2, dtype=torch.float32)
    rotation, shift = (c.detach().double().numpy() for c in poses.corrections())
    assert np.allclose(rotation, own + twist, atol=1e-6)
    assert np.allclose(shift, (own + shear) * poses.spacing, atol=1e-6)
    assert abs((rotation * fanning).sum()) < 1e-6 and abs((shift * baseline).sum()) < 1e-6
    # The rays do not move under the fanning and the baseline growth alone.
    with torch.no_grad():
        poses.rotation[:] = torch.tensor(0.02 * fanning, dtype=torch.float32)
        poses.shift[:] = torch.tensor(0.5 * baseline, dtype=torch.float32)
    assert np.abs(_mean_st_move(poses, centres)).max() < 1e-6
    lone = PoseRefinement(SLAB, centres[:1], centred=False, spacing=0.2)
    with torch.no_grad():
        lone.rotation[:] = 0.01
    assert torch.allclose(lone.corrections()[0], torch.full((1, 3), 0.01))


def test_the_photometric_gradient_finds_a_known_pose_error():
    """A smooth light field seen by a camera whose pose is off by 0.3 degrees: fitting only the
    corrections to the true colours turns the camera back (the sign and size of the error).
    The turn is about x: with two cameras on the x axis, opposite turns about y are the rig
    fanning out, which the corrections hold at zero (test_the_corrections_hold_...)."""
    def light_field(uvst):  # any smooth function of the ray
        return torch.stack([torch.sin(3 * uvst[:, 2] + uvst[:, 0]), torch.cos(2 * uvst[:, 3] - uvst[:, 1]),
                            torch.sin(uvst[:, 2] * uvst[:, 3] + 0.5)], 1)

    true_turn = torch.tensor([math.radians(0.3), 0.0, 0.0], dtype=torch.float64)
    origin, directions = camera_rays(CENTRES[0], n=4096, seed=1)
    seen, _ = SLAB.rays_to_uvst(origin, directions)                                      # the pose we were given
    truth, _ = SLAB.rays_to_uvst(origin, directions @ rotation_matrices(true_turn[None])[0].T)  # where the rays went
    colours = light_field(truth.float())

    poses = PoseRefinement(SLAB, CENTRES)
    optimizer = torch.optim.Adam(poses.parameters(), lr=1e-3)
    view = torch.zeros(len(seen), dtype=torch.long)
    for _ in range(400):
        optimizer.zero_grad()
        loss = ((light_field(poses(seen.float(), view)) - colours) ** 2).mean()
        loss.backward()
        optimizer.step()
    rotation, _ = poses.corrections()
    found = rotation[0].detach().double()
    assert found[0].item() == pytest.approx(true_turn[0].item(), rel=0.15)
    assert loss.item() < 1e-5


def test_training_with_refinement_saves_and_resumes_the_corrections(tiny_scene, tmp_path):
    from neulf_core.checkpoint import load_checkpoint
    from neulf_core.render import LightField
    from neulf_core.scene import load_scene
    from neulf_core.train import TrainConfig, train

    events = []
    config = TrainConfig(steps=12, batch_size=512, refine_poses=True, teacher=False)
    train(tiny_scene, tmp_path / "m", config, progress=events.append)
    first = load_checkpoint(tmp_path / "m")
    assert first["poses"]["rotation"].shape == (len(first["scene"]["train"]), 3)
    assert first["poses"]["rotation"].abs().max() > 0  # they moved
    metadata = json.loads((tmp_path / "m" / "model.json").read_text())
    summary = metadata["pose_corrections"]
    assert 0 < summary["median_degrees"] <= summary["max_degrees"] < 1.0
    # model.json names the corrections' tensors by shape (their values are in model.pt), not a shortened print
    n = len(first["scene"]["train"])
    assert metadata["poses"]["rotation"] == f"tensor of shape [{n}, 3] (in model.pt)"
    assert [e for e in events if e["event"] == "poses"]

    result = train(tiny_scene, tmp_path / "m", TrainConfig(steps=20), resume=True)
    resumed = load_checkpoint(tmp_path / "m")
    assert result.step == 20 and resumed["train_config"]["refine_poses"]
    assert not torch.equal(resumed["poses"]["rotation"], first["poses"]["rotation"])  # continued, not restarted
    rendering = LightField.load(tmp_path / "m", "cpu").render_view(load_scene(tiny_scene).views[0])
    assert np.isfinite(rendering.rgb).all()


def test_a_run_that_refines_poses_repeats_bit_for_bit_on_two_threads(tiny_scene, tmp_path):
    """The per-view corrections' (and colour transforms', and the multi-view losses' camera
    centres') gradients are summed in a fixed order (neulf_core/rows.py): at a full batch on 2
    CPU threads the indexing's own backward summed them in no fixed order, and two runs of one
    seed differed."""
    from conftest import assert_same_weights
    from neulf_core.rows import rows_of
    from neulf_core.train import TrainConfig, train

    table = torch.randn(7, 3, 3, requires_grad=True)
    index = torch.randint(7, (8192, 2))
    assert torch.equal(rows_of(table, index), table[index])
    rows_of(table, index).square().sum().backward()
    expected = torch.zeros_like(table).index_put_((index.reshape(-1),), 2 * table[index].reshape(-1, 3, 3).detach(),
                                                  accumulate=True)
    assert torch.allclose(table.grad, expected)
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        config = TrainConfig(steps=120, seed=4, refine_poses=True, appearance=True, consistency=True, teacher=False,
                             members=1, max_passes=0, validate_seconds=1e9, checkpoint_seconds=1e9,
                             field_overrides={"texture_size": [16, 16]})
        for name in ("a", "b"):
            train(tiny_scene, tmp_path / name, config)
    finally:
        torch.set_num_threads(threads)
    assert_same_weights(tmp_path / "a", tmp_path / "b")


def test_the_cli_flag_reaches_training(tiny_scene, tmp_path, capsys):
    from neulf_core.checkpoint import load_checkpoint
    from neulf_core.cli import main

    out = tmp_path / "m"
    assert main(["train", str(tiny_scene), "--out", str(out), "--steps", "6", "--batch-size", "256",
                 "--no-sweep-teacher", "--refine-poses"]) == 0
    assert load_checkpoint(out)["train_config"]["refine_poses"]
    assert "camera poses corrected by" in capsys.readouterr().err


def test_corrected_centres_are_the_shifted_cameras():
    poses = PoseRefinement(SLAB, CENTRES)
    with torch.no_grad():
        # (none along x, which for two cameras on the x axis is the baseline growing: held at zero)
        poses.shift[:] = torch.tensor([[0.0, -0.02, 0.03], [0.0, 0.02, -0.03]])
        poses.rotation[:] = torch.tensor([[0.01, 0.0, 0.0], [-0.01, 0.0, 0.0]])  # turning leaves a centre in place
    expected = torch.tensor(CENTRES, dtype=torch.float32) + poses.shift.detach() * poses.spacing
    assert torch.allclose(poses.corrected_centres(), expected, atol=1e-7)


def test_the_multiview_losses_cast_neighbour_rays_from_the_refined_cameras(tiny_scene, tmp_path, monkeypatch):
    """With pose refinement the neighbours' rays leave from the corrected centres: the field is
    learned in the corrected frame, and rays from the cameras' first positions would compare a
    surface point with the wrong rays (and leave the shifts out of the losses' gradient)."""
    import neulf_core.train as train_module
    from neulf_core.train import TrainConfig, train

    seen = []
    real = train_module.multiview_losses

    def recording(field, geometry, neighbours, *args, **kwargs):
        seen.append((neighbours.centres.detach().clone(), neighbours.centres.requires_grad))
        return real(field, geometry, neighbours, *args, **kwargs)

    monkeypatch.setattr(train_module, "multiview_losses", recording)
    train(tiny_scene, tmp_path / "m", TrainConfig(steps=12, batch_size=512, refine_poses=True, consistency=True, teacher=False))
    first, last = seen[0][0], seen[-1][0]
    assert seen[0][1]  # the centres carry the shifts' gradient
    assert not torch.equal(first, last)  # they moved with the cameras
    assert (last - first).abs().max() < 0.1 * (first.max(0).values - first.min(0).values).max()  # a correction, not a jump


# ----------------------------------------------------------------------------- the pose check (the default)


def _check_events(events):
    return [e for e in events if e["event"] == "pose_check"]


@pytest.mark.parametrize("threshold, refining", [(90.0, False), (0.0, True)])
def test_the_pose_check_keeps_or_drops_the_refinement_and_saves_its_verdict(tiny_scene, tmp_path, monkeypatch,
                                                                            threshold, refining):
    """The default (refine_poses None) refines from the start and decides at POSE_CHECK_STEP:
    dropped, the corrections and their optimizer state are gone and a resumed run trains on
    without them; kept, they go on moving.  The verdict is in model.json and the checkpoint."""
    import neulf_core.poses as poses_module
    from neulf_core.checkpoint import load_checkpoint
    from neulf_core.train import TrainConfig, train

    monkeypatch.setattr(poses_module, "POSE_CHECK_STEP", 5)
    monkeypatch.setattr(poses_module, "POSE_CHECK_DEGREES", threshold)
    monkeypatch.setattr(poses_module, "POSE_CHECK_UNSURE_DEGREES", threshold)  # no second look here
    events = []
    train(tiny_scene, tmp_path / "m", TrainConfig(steps=12, batch_size=512, teacher=False), progress=events.append)
    (check,) = _check_events(events)
    assert check["step"] == 5 and check["refining"] is refining and check["message"]
    saved = load_checkpoint(tmp_path / "m")
    meta = json.loads((tmp_path / "m" / "model.json").read_text())
    assert saved["train_config"]["refine_poses"] is refining and meta["pose_check"]["refining"] is refining
    assert (saved["poses"] is not None) is refining
    assert len(saved["optimizer"]["param_groups"]) == len([g for g in saved["optimizer"]["param_groups"]
                                                           if g.get("name") != "poses"]) + refining
    assert bool([e for e in events if e["event"] == "poses"]) is refining  # corrections reported only when kept

    more = []
    result = train(tiny_scene, tmp_path / "m", TrainConfig(steps=20), resume=True, progress=more.append)
    assert result.step == 20 and not _check_events(more)  # decided once
    resumed = load_checkpoint(tmp_path / "m")
    assert resumed["train_config"]["refine_poses"] is refining and (resumed["poses"] is not None) is refining
    assert json.loads((tmp_path / "m" / "model.json").read_text())["pose_check"] == meta["pose_check"]  # kept
    if refining:
        assert not torch.equal(resumed["poses"]["rotation"], saved["poses"]["rotation"])


@pytest.mark.parametrize("preset", ["authors", "paper"])
def test_the_published_networks_train_with_fixed_poses_unless_asked(tiny_scene, tmp_path, monkeypatch, preset):
    """The pose check belongs to the default's recipe: at its step a published MLP is still a
    blur whose corrections fit the blur (presets.Preset.pose_check), so those presets train
    with the poses as given, and refine them only when asked."""
    import neulf_core.poses as poses_module
    from neulf_core.checkpoint import load_checkpoint
    from neulf_core.train import TrainConfig, train

    monkeypatch.setattr(poses_module, "POSE_CHECK_STEP", 3)
    monkeypatch.setattr(poses_module, "POSE_CHECK_DEGREES", 0.0)  # the default's check would keep any correction
    monkeypatch.setattr(poses_module, "POSE_CHECK_UNSURE_DEGREES", 0.0)
    events = []
    train(tiny_scene, tmp_path / "m", TrainConfig(preset=preset, steps=8, batch_size=256), progress=events.append)
    saved = load_checkpoint(tmp_path / "m")
    assert not _check_events(events) and saved["poses"] is None and saved["train_config"]["refine_poses"] is False
    train(tiny_scene, tmp_path / "asked", TrainConfig(preset=preset, steps=8, batch_size=256, refine_poses=True))
    assert load_checkpoint(tmp_path / "asked")["poses"] is not None


def test_a_run_stopped_before_the_pose_check_checks_when_resumed(tiny_scene, tmp_path, monkeypatch):
    import neulf_core.poses as poses_module
    from neulf_core.checkpoint import load_checkpoint
    from neulf_core.train import TrainConfig, train

    monkeypatch.setattr(poses_module, "POSE_CHECK_STEP", 8)
    monkeypatch.setattr(poses_module, "POSE_CHECK_DEGREES", 0.0)  # any correction: off
    steps = iter(range(1000))
    first = []
    result = train(tiny_scene, tmp_path / "m", TrainConfig(steps=20, batch_size=512, teacher=False), progress=first.append,
                   should_stop=lambda: next(steps) >= 6)  # cancelled at step 6, past halfway (4)
    saved = load_checkpoint(tmp_path / "m")
    assert result.status == "cancelled" and not _check_events(first)
    assert saved["train_config"]["refine_poses"] is None and saved["poses"] is not None  # undecided, corrections kept
    assert saved["pose_check"]["halfway_step"] == 4
    assert not [e for e in first if e["event"] == "poses"] and "pose_corrections" not in saved  # nor reported yet
    more = []
    train(tiny_scene, tmp_path / "m", TrainConfig(steps=20), resume=True, progress=more.append)
    (check,) = _check_events(more)
    assert check["step"] == 8 and check["refining"]
    assert check["halfway_degrees"] == saved["pose_check"]["halfway_degrees"]  # restored, not measured again
    assert load_checkpoint(tmp_path / "m")["poses"] is not None  # the corrections carried on


def test_a_budget_too_short_for_the_pose_check_trains_without_refinement(tiny_scene, tmp_path):
    from neulf_core.checkpoint import load_checkpoint
    from neulf_core.poses import POSE_CHECK_STEP
    from neulf_core.train import TrainConfig, train

    events = []
    train(tiny_scene, tmp_path / "m", TrainConfig(steps=2 * POSE_CHECK_STEP - 1, batch_size=256, teacher=False),
          progress=events.append)
    saved = load_checkpoint(tmp_path / "m")
    assert saved["poses"] is None and saved["train_config"]["refine_poses"] is False and not _check_events(events)


def test_the_pose_check_finds_poses_that_are_off(tiny_scene, tmp_path):
    """Behaviour, not plumbing: on the tiny scene with a degree of centred pose noise the check
    (at its real step and threshold) keeps refining, and the corrections it found at the check
    are several times those on the exact poses."""
    import sys
    from dataclasses import replace
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import stability
    from neulf_core.scene import load_scene, split_views
    from neulf_core.train import TrainConfig, train

    scene = load_scene(tiny_scene)
    training, held = split_views(scene, 8, None)
    found = {}
    for degrees in (0.0, 1.0):
        views = stability.perturb_poses(training, degrees, stability.rig_spacing(training)) if degrees else training
        events = []
        train(replace(scene, views=sorted(held + views, key=lambda v: v.name)), tmp_path / f"m{degrees}",
              TrainConfig(steps=200, batch_size=2048, teacher=False), progress=events.append)
        (found[degrees],) = _check_events(events)
    assert found[1.0]["refining"]
    assert found[1.0]["median_degrees"] > 5 * found[0.0]["median_degrees"]


def test_a_minutes_budget_that_ends_before_the_pose_check_is_checked_at_its_end(tiny_scene, tmp_path, monkeypatch):
    import neulf_core.poses as poses_module
    from neulf_core.train import TrainConfig, train

    monkeypatch.setattr(poses_module, "POSE_CHECK_STEP", 10 ** 6)
    events = []
    result = train(tiny_scene, tmp_path / "m", TrainConfig(minutes=0.01, max_passes=0, batch_size=256, teacher=False),
                   progress=events.append)
    (check,) = _check_events(events)
    assert check["step"] == result.step
    meta = json.loads((tmp_path / "m" / "model.json").read_text())
    assert meta["train_config"]["refine_poses"] is check["refining"] and meta["pose_check"]["step"] == result.step


def test_the_pose_check_measures_each_cameras_own_part():
    """A rotation that varies linearly across the rig (what drifts once the rig-wide part has
    joined) does not count; the cameras' own turns do."""
    centres = np.array([[x, y, -0.5] for x in (-0.2, 0.0, 0.2) for y in (-0.2, 0.0, 0.2)])
    poses = PoseRefinement(SLAB, centres)
    with torch.no_grad():
        poses.rotation[:, 1] = torch.tensor(centres[:, 0] * 0.01, dtype=torch.float32)  # rig-wide: linear in x
    assert poses.own_part_degrees() < 1e-4
    with torch.no_grad():
        poses.rotation[:, 2] += torch.tensor([1e-3, -1e-3] * 4 + [0.0], dtype=torch.float32)  # each its own
    assert poses.own_part_degrees() == pytest.approx(math.degrees(1e-3), rel=0.2)
    # Turns of unequal sizes: the statistic is their median, not the largest (one camera's big
    # turn, a photo SfM placed badly, must not call every pose off).
    turns = np.random.default_rng(5).normal(0.0, 1e-3, len(centres)) * np.linspace(0.2, 3.0, len(centres))
    basis = np.column_stack([np.ones(len(centres)), centres[:, 0], centres[:, 1]])  # the rig-wide part
    own = turns - basis @ np.linalg.lstsq(basis, turns, rcond=None)[0]
    with torch.no_grad():
        poses.rotation.zero_()
        poses.rotation[:, 2] = torch.tensor(turns, dtype=torch.float32)
    assert np.abs(own).max() > 1.5 * np.median(np.abs(own))  # (so the two readings part)
    assert poses.own_part_degrees() == pytest.approx(math.degrees(np.median(np.abs(own))), rel=1e-3)


def test_the_pose_check_goes_by_the_size_of_the_corrections_and_looks_again_when_unsure():
    """At least POSE_CHECK_DEGREES after POSE_CHECK_STEP steps, growing or shrinking since,
    the poses are off; under POSE_CHECK_UNSURE_DEGREES they are right; between, the check looks
    again at POSE_SECOND_LOOK_STEP against POSE_SECOND_LOOK_DEGREES, where few photos with
    0.1 degrees of noise and right poses part (docs/STABILITY.md, thirty-fifth session)."""
    from neulf_core.poses import (POSE_CHECK_DEGREES, POSE_CHECK_UNSURE_DEGREES, POSE_SECOND_LOOK_DEGREES,
                                  POSE_SECOND_LOOK_STEP, POSE_CHECK_STEP, poses_look_off)

    assert poses_look_off(POSE_CHECK_DEGREES) is True and poses_look_off(0.1) is True
    assert poses_look_off(0.5 * POSE_CHECK_UNSURE_DEGREES) is False  # drift
    assert poses_look_off((POSE_CHECK_UNSURE_DEGREES + POSE_CHECK_DEGREES) / 2) is None  # unsure
    assert poses_look_off(POSE_SECOND_LOOK_DEGREES, second_look=True) is True
    assert poses_look_off(0.9 * POSE_SECOND_LOOK_DEGREES, second_look=True) is False
    assert POSE_CHECK_UNSURE_DEGREES < POSE_SECOND_LOOK_DEGREES < POSE_CHECK_DEGREES
    assert POSE_SECOND_LOOK_STEP > POSE_CHECK_STEP


@pytest.mark.parametrize("second_threshold, refining", [(90.0, False), (0.0, True)])
def test_an_unsure_pose_check_refines_on_and_decides_at_its_second_look(tiny_scene, tmp_path, monkeypatch,
                                                                        second_threshold, refining):
    """Unsure at the first look: the corrections go on moving (nothing reported yet, the run
    still undecided in its checkpoint), and the second look decides.  A run stopped between
    the two looks resumes undecided and looks again at the second look's step."""
    import neulf_core.poses as poses_module
    from neulf_core.checkpoint import load_checkpoint
    from neulf_core.train import TrainConfig, train

    monkeypatch.setattr(poses_module, "POSE_CHECK_STEP", 5)
    monkeypatch.setattr(poses_module, "POSE_SECOND_LOOK_STEP", 9)
    monkeypatch.setattr(poses_module, "POSE_CHECK_DEGREES", 1e9)
    monkeypatch.setattr(poses_module, "POSE_CHECK_UNSURE_DEGREES", 0.0)  # every first look unsure
    monkeypatch.setattr(poses_module, "POSE_SECOND_LOOK_DEGREES", second_threshold)
    steps = iter(range(1000))
    first = []
    train(tiny_scene, tmp_path / "m", TrainConfig(steps=14, batch_size=512, teacher=False), progress=first.append,
          should_stop=lambda: next(steps) >= 7)  # stopped at step 7, between the looks
    (unsure,) = [e for e in first if e["event"] == "stage" and "looking again" in e["message"]]
    assert not _check_events(first) and not [e for e in first if e["event"] == "poses"]
    saved = load_checkpoint(tmp_path / "m")
    assert saved["train_config"]["refine_poses"] is None and saved["poses"] is not None  # undecided, corrections kept
    assert saved["pose_check"]["unsure_step"] == 5 and "refining" not in saved["pose_check"]
    more = []
    train(tiny_scene, tmp_path / "m", TrainConfig(steps=14), resume=True, progress=more.append)
    (check,) = _check_events(more)
    assert check["step"] == 9 and check["refining"] is refining
    assert f"after {saved['pose_check']['unsure_step']}" in check["message"]  # the first look, restored
    final = load_checkpoint(tmp_path / "m")
    assert final["train_config"]["refine_poses"] is refining and (final["poses"] is not None) is refining
    assert final["pose_check"]["step"] == 9 and final["pose_check"]["unsure_step"] == 5


def test_a_held_out_cameras_pose_is_fitted_to_its_photo(tiny_scene, tmp_path, capsys):
    """`eval --fit-poses`: a held-out camera turned by a degree (the tiny scene's pixels are
    about a degree wide) is turned back to within a twentieth of a degree, and scores as its
    exact pose does; the CLI reports the fitted score beside the plain one."""
    import sys
    from dataclasses import replace
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import stability
    from neulf_core.cli import main
    from neulf_core.metrics import psnr
    from neulf_core.poses import fit_view_pose
    from neulf_core.render import LightField
    from neulf_core.scene import camera_spacing, load_scene
    from neulf_core.train import TrainConfig, train

    train(tiny_scene, tmp_path / "m", TrainConfig(steps=300, batch_size=2048, teacher=False))
    light_field = LightField.load(tmp_path / "m", "cpu", precision="full")
    view = load_scene(tiny_scene).view(light_field.meta["scene"]["held_out"][0])
    scale = light_field.trained_scale
    photo = view.load_image(scale).astype(np.float32) / 255.0
    turn = stability.rotation_about(np.array([0.3, 1.0, 0.2]), 1.0)
    R = view.R @ turn.T
    off = replace(view, R=R, t=-R @ view.center)

    fitted, degrees, _ = fit_view_pose(light_field, off, scale, camera_spacing(np.asarray(light_field.meta["rig"]["centres"])))
    left = np.degrees(np.arccos(np.clip((np.trace(fitted.R @ view.R.T) - 1) / 2, -1, 1)))
    assert degrees == pytest.approx(1.0, abs=0.1) and left < 0.05, (degrees, left)
    score = lambda v: psnr(light_field.render_view(v, scale, depth=False).rgb, photo)
    assert score(off) < score(view) - 10 and score(fitted) > score(view) - 0.3

    assert main(["eval", str(tmp_path / "m"), "--scene", str(tiny_scene), "--fit-poses"]) == 0
    report = json.loads((tmp_path / "m" / "eval" / "eval.json").read_text())
    assert report["mean_psnr_pose_fitted"] > report["mean_psnr"] - 0.3  # right poses: fitting changes little
    assert "pose fitted to its photo" in capsys.readouterr().out


# ----------------------------------------------------------------------------- far-off poses restart the field


def test_the_far_off_bar_is_higher_for_many_photos_the_points_held():
    """pose_check.poses_far_off: with more than COARSE_TO_FINE_MAX_VIEWS photos whose first steps
    the SfM points' depth held, the field starts again only from MANY_PHOTOS_FAR_OFF_POSE_DEGREES
    (there the corrections do not stall at moderate error: docs/STABILITY.md); with fewer
    photos, or nothing holding the first steps (`--refine-poses`), from FAR_OFF_POSE_DEGREES."""
    from neulf_core.pose_check import FAR_OFF_POSE_DEGREES, MANY_PHOTOS_FAR_OFF_POSE_DEGREES, poses_far_off
    from neulf_core.rules import COARSE_TO_FINE_MAX_VIEWS

    few, many = COARSE_TO_FINE_MAX_VIEWS, COARSE_TO_FINE_MAX_VIEWS + 1
    assert FAR_OFF_POSE_DEGREES < MANY_PHOTOS_FAR_OFF_POSE_DEGREES
    between = (FAR_OFF_POSE_DEGREES + MANY_PHOTOS_FAR_OFF_POSE_DEGREES) / 2
    assert not poses_far_off(between, many, points_held=True)
    assert poses_far_off(between, few, points_held=True) and poses_far_off(between, many, points_held=False)
    assert poses_far_off(FAR_OFF_POSE_DEGREES, few, True) and not poses_far_off(FAR_OFF_POSE_DEGREES * 0.99, few, True)
    assert poses_far_off(MANY_PHOTOS_FAR_OFF_POSE_DEGREES, many, True) and poses_far_off(2.0, 70, True)


@pytest.mark.parametrize("views, points_held, geometry_only", [(26, True, True), (26, False, False), (13, True, False)])
def test_the_far_off_restart_keeps_the_texture_for_many_photos_the_points_held(views, points_held, geometry_only):
    """With more than COARSE_TO_FINE_MAX_VIEWS photos whose first steps the SfM points held,
    the far-off restart starts only the geometry again (fresh, its Adam moments gone); the
    texture and the colour decoder keep their weights and moments.  Otherwise all starts again.
    The geometry is the depth layers too; their smoothness rises with the planes'."""
    import neulf_core.pose_check as pose_check_module
    from neulf_core.fields import build_field, make_config

    torch.manual_seed(0)
    field = build_field("disparity", make_config("disparity", {"geometry_layers": 2}))
    tv, layer_tv = field.config.tv_weight, field.config.geometry_layer_tv
    optimizer = torch.optim.Adam(field.parameters(), lr=1e-2)
    field(torch.rand(64, 4) * 2 - 1)[0].sum().backward()
    optimizer.step()
    before = {k: v.clone() for k, v in field.state_dict().items()}

    class FarOff:  # the pose corrections as the check reads them: 1 degree, far off
        def own_part_degrees(self):
            return 1.0

    meta = {"point_depth": {"rays": 10}} if points_held else {}
    pose_check_module.restart_for_far_off_poses(field, optimizer, FarOff(), meta, None, 100, 0, fraction=0.1,
                                            n_train_views=views)
    assert meta["field_restart"]["geometry_only"] is geometry_only
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(1)
        fresh = build_field("disparity", make_config("disparity", field.field_config)).state_dict()
    after = field.state_dict()
    for name, parameter in field.named_parameters():
        started = not geometry_only or name.startswith(field.GEOMETRY_PARAMETERS)
        assert torch.equal(after[name], fresh[name] if started else before[name]), name
        assert (optimizer.state.get(parameter) in (None, {})) is started, name
    assert torch.equal(after["textures.0"], before["textures.0"]) is geometry_only
    assert not torch.equal(after["layers"], before["layers"])  # (geometry: started again either way)
    factor = pose_check_module.FAR_OFF_GEOMETRY_TV
    assert field.field_config["tv_weight"] == pytest.approx(factor * tv)
    assert field.field_config["geometry_layer_tv"] == pytest.approx(factor * layer_tv)
    assert meta["field_restart"]["depth_layers"] is True
    assert meta["field_restart"]["depth_layer_tv"] == pytest.approx(factor * layer_tv)


@pytest.mark.parametrize("threshold, deep, restarts, few", [(0.0, False, True, False), (0.0, False, True, True),
                                                           (90.0, False, False, False), (0.0, True, False, False)])
def test_far_off_poses_restart_the_field_with_smoother_geometry(tiny_scene, tmp_path, monkeypatch, threshold, deep,
                                                                restarts, few):
    """At the pose check's step, corrections of at least FAR_OFF_POSE_DEGREES on a shallow
    scene start the field again (a fresh start, its optimizer state gone) with geometry planes
    FAR_OFF_GEOMETRY_TV times smoother; the corrections go on.  Saved with the model, so a
    resumed run keeps the smoother geometry and does not restart again.  Deep scenes and
    smaller corrections train on as they were.  With few photos (`few`: the tiny scene's 7
    counted as few) the restarted texture also sharpens coarse to fine from the check on."""
    import neulf_core.pose_check as pose_check_module
    import neulf_core.poses as poses_module
    from neulf_core.checkpoint import load_checkpoint
    from neulf_core.fields import build_field, make_config
    from neulf_core.slab import Slab
    from neulf_core.train import TrainConfig, train
    from neulf_core.pose_check import FAR_OFF_GEOMETRY_TV

    monkeypatch.setattr(poses_module, "POSE_CHECK_STEP", 5)
    monkeypatch.setattr(pose_check_module, "FAR_OFF_POSE_DEGREES", threshold)
    monkeypatch.setattr(pose_check_module, "MANY_PHOTOS_FAR_OFF_POSE_DEGREES", threshold)
    monkeypatch.setattr(Slab, "is_deep", property(lambda self: deep))
    monkeypatch.setattr(pose_check_module, "FEW_PHOTOS_TEXTURE_MAX_VIEWS", 7 if few else 6)
    real, seen = pose_check_module.restart_for_far_off_poses, {}

    def watched(field_module, optimizer, poses, meta, progress, step, seed, **kwargs):
        before = {k: v.clone() for k, v in field_module.state_dict().items()}
        seen["tv_before"] = field_module.config.tv_weight
        poses_before = poses.rotation.detach().clone()
        real(field_module, optimizer, poses, meta, progress, step, seed, **kwargs)
        after = {k: v.clone() for k, v in field_module.state_dict().items()}
        seen.update(seed=seed, before=before, after=after, step=step, poses_before=poses_before,
                    poses_after=poses.rotation.detach().clone(),
                    state=[optimizer.state.get(p) for p in field_module.parameters()],
                    config=dict(field_module.field_config))

    monkeypatch.setattr(pose_check_module, "restart_for_far_off_poses", watched)
    events = []
    train(tiny_scene, tmp_path / "m", TrainConfig(steps=12, batch_size=512, refine_poses=True, teacher=False),
          progress=events.append)
    restart_events = [e for e in events if e["event"] == "field_restart"]
    meta = json.loads((tmp_path / "m" / "model.json").read_text())
    assert bool(restart_events) is restarts and ("field_restart" in meta) is restarts
    assert bool(seen) is (not deep)  # (deep scenes are not even measured)
    assert ("far_off_check" in meta) is (not deep)  # what the check measured, restart or not
    if not deep:
        check = meta["far_off_check"]
        assert check["step"] == 5 and check["train_views"] == 7
        assert check["points_held"] is False  # (refinement forced on: no points from the first step)
    if not restarts:
        assert meta["field_config"]["tv_weight"] == seen.get("tv_before", meta["field_config"]["tv_weight"])
        return
    (event,) = restart_events
    assert event["step"] == seen["step"] == 5 and event["message"].startswith("the camera poses are far off")
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seen["seed"] + 1)
        fresh = build_field("disparity", make_config("disparity", seen["config"])).state_dict()
    texture = "textures.0"
    assert not torch.equal(seen["before"][texture], seen["after"][texture])  # started again ...
    assert all(torch.equal(seen["after"][k], fresh[k]) for k in fresh)  # ... from a fresh start
    assert all(state in (None, {}) for state in seen["state"])  # without the old field's Adam moments
    assert torch.equal(seen["poses_before"], seen["poses_after"])  # the corrections are kept
    assert meta["field_config"]["tv_weight"] == pytest.approx(FAR_OFF_GEOMETRY_TV * seen["tv_before"])
    assert meta["field_restart"]["step"] == 5
    texture_ramp = meta["field_config"]["texture_coarse_to_fine"]
    if few:  # the coarsest level alone at the check, the finer ones fading in; saved with the model
        assert "coarse to fine" in event["message"] and meta["field_restart"]["texture_coarse_to_fine"] == pytest.approx(texture_ramp)
        assert texture_ramp == pytest.approx(0.9 * (1 - 5 / 12))  # the check late in a short budget: done before its end
        assert meta["field_config"]["texture_ramp_start"] == pytest.approx(5 / 12)
        assert seen["after"]["texture_level_weights"].tolist() == [0.0, 0.0, 0.0, 1.0]
    else:
        assert texture_ramp == 0 and "texture_coarse_to_fine" not in meta["field_restart"]
    more = []
    train(tiny_scene, tmp_path / "m", TrainConfig(steps=20), resume=True, progress=more.append)
    assert not [e for e in more if e["event"] == "field_restart"]  # once
    resumed = json.loads((tmp_path / "m" / "model.json").read_text())
    assert resumed["field_config"]["tv_weight"] == pytest.approx(FAR_OFF_GEOMETRY_TV * seen["tv_before"])
    assert resumed["field_restart"] == meta["field_restart"]
    assert load_checkpoint(tmp_path / "m")["progress"]["step"] == 20
    if few:  # sharp by the end of the budget, and the saved model renders so
        from neulf_core.render import LightField
        assert load_checkpoint(tmp_path / "m")["state_dict"]["texture_level_weights"].tolist() == [1.0] * 4
        assert LightField.load(tmp_path / "m", "cpu").field.texture_level_weights.tolist() == [1.0] * 4

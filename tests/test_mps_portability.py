"""What Apple's MPS device asks of the core, checked on the CPU (no Mac runs these tests).

MPS has no float64: training, the held-out pose fitting of `eval --fit-poses`, rendering and
depth run here on tests/mps_like.py's stand-in device, which refuses float64 on the device as
MPS does; float64 work belongs on the host (`.cpu().double()`, numpy).  The stand-in's own
tests come first: a stand-in that lets float64 through would make the rest pass for nothing.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from mps_like import MPS_FLOAT64, STAND_IN, MpsLike

# ----------------------------------------------------------------------------- the stand-in


def test_the_stand_in_refuses_float64_on_the_device_as_mps_does():
    with MpsLike() as mode:
        on_device = torch.ones(3, device=STAND_IN)
        layer = torch.nn.Linear(2, 2).to(STAND_IN)
        refusals = [lambda: on_device.double(),
                    lambda: (on_device * 2).to(torch.float64),
                    lambda: torch.zeros(3, dtype=torch.float64, device=STAND_IN),
                    lambda: torch.as_tensor(np.zeros(3), device=STAND_IN),  # numpy's float64 kept
                    lambda: torch.from_numpy(np.zeros(3)).to(STAND_IN),
                    lambda: layer.weight.double(),
                    lambda: layer(torch.ones(1, 2)).double()]
        for refused in refusals:
            with pytest.raises(TypeError, match="MPS framework doesn't support float64"):
                refused()
        with pytest.raises(TypeError, match="Use Tensor.cpu"):
            on_device.numpy()
    assert len(mode.refused) == len(refusals) + 1


def test_the_stand_in_lets_float64_work_on_the_host_through():
    with MpsLike():
        on_device = torch.ones(3, device=STAND_IN)
        assert on_device.cpu().double().dtype == torch.float64  # (.cpu() on the CPU is the tensor itself)
        assert on_device.to("cpu").double().numpy().sum() == 3
        assert torch.as_tensor(np.zeros(3), device=STAND_IN, dtype=torch.float32).dtype == torch.float32
        assert torch.zeros(3, dtype=torch.float64).sum().item() == 0  # the host's own float64
    assert MPS_FLOAT64.startswith("Cannot convert a MPS Tensor to float64")


# ----------------------------------------------------------------------------- the core on it


@pytest.fixture(scope="module")
def trained_on_stand_in(tiny_scene, tmp_path_factory):
    """A tiny model trained on the stand-in device with every loss that touches poses and depth:
    refined poses, the teacher's depth, the multi-view losses and the SfM points' depth."""
    from neulf_core.train import TrainConfig, train

    model = tmp_path_factory.mktemp("mps_like") / "m"
    config = TrainConfig(steps=12, batch_size=256, device=str(STAND_IN), refine_poses=True, teacher=True,
                         consistency=True, point_depth=True)
    with MpsLike() as mode:
        train(tiny_scene, model, config)
    assert not mode.refused and mode.device_results > 1000  # (it did train on the stand-in)
    return model


def test_training_on_the_stand_in_keeps_float64_off_the_device(trained_on_stand_in):
    metadata = json.loads((trained_on_stand_in / "model.json").read_text())
    assert metadata["train_config"]["refine_poses"] and metadata["pose_corrections"]


def test_fitting_a_held_out_pose_keeps_float64_off_the_device(trained_on_stand_in, tiny_scene):
    """The `eval --fit-poses` path: poses.fit_view_pose turns its device-side correction into a
    world pose in float64, on the host."""
    from neulf_core.poses import fit_view_pose
    from neulf_core.render import LightField
    from neulf_core.scene import camera_spacing, load_scene

    with MpsLike() as mode:
        light_field = LightField.load(trained_on_stand_in, str(STAND_IN), precision="full")
        view = load_scene(tiny_scene).view(light_field.meta["scene"]["held_out"][0])
        spacing = camera_spacing(np.asarray(light_field.meta["rig"]["centres"]))
        fitted, degrees, moved = fit_view_pose(light_field, view, light_field.trained_scale, spacing, steps=5, batch=256)
    assert not mode.refused and mode.device_results and np.isfinite(fitted.R).all() and np.isfinite([degrees, moved]).all()


def test_the_eval_command_fits_poses_on_the_stand_in(trained_on_stand_in, tiny_scene):
    from neulf_core.cli import main

    with MpsLike() as mode:
        assert main(["eval", str(trained_on_stand_in), "--scene", str(tiny_scene), "--fit-poses",
                     "--device", str(STAND_IN)]) == 0
    assert not mode.refused and mode.device_results


@pytest.mark.parametrize("precision", ["full", "half"])
def test_rendering_colour_and_depth_keeps_float64_off_the_device(trained_on_stand_in, tiny_scene, precision):
    from neulf_core.render import LightField
    from neulf_core.scene import load_scene

    view = load_scene(tiny_scene).views[0]
    with MpsLike() as mode:
        light_field = LightField.load(trained_on_stand_in, str(STAND_IN), precision=precision)
        renderings = [light_field.render_view(view, depth=True),
                      light_field.render_view(view, depth=True, pixel_samples=4),
                      light_field.render_view(view, depth=True, focus_distance=3.0, aperture=0.02, max_samples=8),
                      light_field.render(view.camera.calibration_matrix(), 24, 18, view.R, view.t, depth=True)]
    assert not mode.refused and mode.device_results
    for rendering in renderings:
        assert np.isfinite(rendering.rgb).all() and rendering.depth is not None


# ----------------------------------------------------------------------------- MPS builds that fall short


def _calls_per_device(monkeypatch) -> int:
    """How many grid_sample calls the probe makes on each of its two devices (counted, so the
    fakes below go wrong on the probed device alone, whatever the probe's number of calls)."""
    import torch.nn.functional as F

    from neulf_core.device import border_sampling_differs

    calls, real = [], F.grid_sample
    monkeypatch.setattr(F, "grid_sample", lambda *a, **k: calls.append(1) or real(*a, **k))
    assert not border_sampling_differs(torch.device("cpu"))  # (a device that samples as the CPU does passes)
    monkeypatch.setattr(F, "grid_sample", real)
    assert len(calls) % 2 == 0
    return len(calls) // 2


def _on_the_probed_device(monkeypatch, wrong):
    """grid_sample as torch has it for the reference's calls, then `wrong(real, *args, **kwargs)`."""
    import torch.nn.functional as F

    reference_calls, calls, real = _calls_per_device(monkeypatch), [], F.grid_sample

    def sample(*args, **kwargs):
        calls.append(1)
        return real(*args, **kwargs) if len(calls) <= reference_calls else wrong(real, *args, **kwargs)

    monkeypatch.setattr(F, "grid_sample", sample)


def _lacking(real, *args, **kwargs):
    raise RuntimeError("MPS: Unsupported Border padding mode")


def _off_by_a_little(real, *args, **kwargs):
    return real(*args, **kwargs) + 1e-3


def _wrong_grid_gradient(real, texture, grid, **kwargs):
    scaled_gradient = grid.detach() + 1.5 * (grid - grid.detach())  # the same values, 1.5 x the gradient
    return real(texture, scaled_gradient, **kwargs)


@pytest.mark.parametrize("wrong", [_lacking, _off_by_a_little, _wrong_grid_gradient])
def test_the_probe_finds_a_border_sampling_that_fails_or_differs(monkeypatch, wrong):
    from neulf_core.device import border_sampling_differs

    _on_the_probed_device(monkeypatch, wrong)
    assert border_sampling_differs(torch.device("cpu"))


def _mps_present(monkeypatch, falls_short: bool):
    """A machine with MPS (and no CUDA) whose MPS does, or does not, fall short of the probe."""
    from neulf_core import device

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(torch.backends.mps, "is_available", lambda: True)
    monkeypatch.setattr(device, "_border_sampling_differs_on", lambda name: falls_short)


def test_asking_for_an_mps_that_falls_short_is_refused_in_one_line(monkeypatch, trained_on_stand_in, tiny_scene,
                                                                    capsys, record_property):
    from neulf_core.cli import EXIT_USAGE, main
    from neulf_core.device import pick_device
    from neulf_core.errors import NeulfError

    _mps_present(monkeypatch, falls_short=False)
    assert pick_device("mps") == torch.device("mps")
    _mps_present(monkeypatch, falls_short=True)
    with pytest.raises(NeulfError, match="grid_sample with border padding.*: use --device cpu, or upgrade torch.$"):
        pick_device("mps")
    assert pick_device("cpu").type == "cpu"  # (other devices are not probed)

    capsys.readouterr()
    assert main(["eval", str(trained_on_stand_in), "--scene", str(tiny_scene), "--device", "mps"]) == EXIT_USAGE
    err = capsys.readouterr().err
    assert err.startswith("error: this torch's MPS cannot run grid_sample") and err.count("\n") == 1
    assert "use --device cpu, or upgrade torch." in err and "Traceback" not in err
    record_property("message", err.strip())


def test_the_default_device_passes_over_an_mps_that_falls_short_with_a_note(monkeypatch, capsys):
    from neulf_core.device import pick_device

    _mps_present(monkeypatch, falls_short=False)
    assert pick_device(None) == torch.device("mps") and capsys.readouterr().err == ""
    _mps_present(monkeypatch, falls_short=True)
    assert pick_device(None) == torch.device("cpu")
    note = capsys.readouterr().err
    assert note.startswith("note: this torch's MPS cannot run grid_sample") and note.count("\n") == 1
    assert "using the CPU (upgrade torch to use MPS)" in note


def test_only_mps_is_probed(monkeypatch):
    from neulf_core import device

    monkeypatch.setattr(device, "_border_sampling_differs_on", lambda name: pytest.fail(f"probed {name}"))
    assert not device.mps_shortfall(torch.device("cpu")) and not device.mps_shortfall(STAND_IN)

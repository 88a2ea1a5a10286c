"""Half-precision rendering (render.PRECISIONS): the field's matrix products run in float16,
ray geometry and the disparity field's geometry branch stay float32, and the picture is the
float32 one to within rounding.  On CPU this exercises the same autocast path a GPU takes
(float16 is the same IEEE format there; only the speed is a GPU's)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from PIL import Image

from neulf_core.cli import main
from neulf_core.errors import NeulfError
from neulf_core.render import LightField, half_precision
from neulf_core.scene import load_scene
from neulf_core.train import TrainConfig, train


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(10 * np.log10(1.0 / max(np.mean((a - b) ** 2), 1e-20)))


@pytest.fixture(scope="module", params=["fast", "authors"])
def trained_model(request, tiny_scene, tmp_path_factory):
    model_dir = tmp_path_factory.mktemp(f"precision_{request.param}")
    steps = 60 if request.param == "fast" else 15
    train(tiny_scene, model_dir, TrainConfig(preset=request.param, steps=steps, batch_size=512, seed=0,
                                             validate_seconds=1e9, checkpoint_seconds=1e9, device="cpu"))
    return request.param, model_dir


def _linear_output_dtypes(light_field: LightField) -> set:
    """The dtypes the field's linear layers produced in the last render (hooks)."""
    seen: set = set()
    for module in light_field.field.modules():
        if isinstance(module, torch.nn.Linear):
            module.register_forward_hook(lambda _m, _i, out: seen.add(out.dtype))
    return seen


def test_half_precision_renders_the_float32_picture(trained_model, tiny_scene):
    preset, model_dir = trained_model
    view = load_scene(tiny_scene).views[0]
    full = LightField.load(model_dir, "cpu", precision="full")
    half = LightField.load(model_dir, "cpu", precision="half")
    full_dtypes, half_dtypes = _linear_output_dtypes(full), _linear_output_dtypes(half)
    a = full.render_view(view, depth=True)
    b = half.render_view(view, depth=True)
    assert full_dtypes == {torch.float32}
    assert torch.float16 in half_dtypes  # the products really ran in float16
    if preset == "fast":  # the geometry branch's decoder stays float32 on purpose
        assert torch.float32 in half_dtypes
    assert b.rgb.dtype == np.float32 and np.isfinite(b.rgb).all()
    assert _psnr(a.rgb, b.rgb) > 50.0
    finite = np.isfinite(a.depth)
    assert np.array_equal(finite, np.isfinite(b.depth))
    assert np.allclose(a.depth[finite], b.depth[finite], rtol=2e-3)


def test_auto_precision_is_half_on_cuda_only():
    assert half_precision("auto", torch.device("cuda")) is True
    assert half_precision("auto", torch.device("cpu")) is False
    assert half_precision("auto", torch.device("mps")) is False
    assert half_precision("half", torch.device("cpu")) is True
    assert half_precision("full", torch.device("cuda")) is False
    with pytest.raises(NeulfError, match="unknown precision"):
        half_precision("double", torch.device("cpu"))


def test_render_cli_precision_flag(trained_model, tiny_scene, tmp_path, monkeypatch):
    preset, model_dir = trained_model
    if preset != "fast":
        pytest.skip("one preset is enough for the flag")
    name = load_scene(tiny_scene).views[0].name
    asked = []
    real_load = LightField.load.__func__
    monkeypatch.setattr(LightField, "load", classmethod(lambda cls, *a, **k: asked.append(a[2] if len(a) > 2 else k.get("precision"))
                                                        or real_load(cls, *a, **k)))
    for precision in ("full", "half"):
        code = main(["render", str(model_dir), "--scene", str(tiny_scene), "--views", name,
                     "--out", str(tmp_path / precision), "--precision", precision, "--device", "cpu"])
        assert code == 0
    assert asked == ["full", "half"]  # the flag reaches the renderer
    images = [np.asarray(Image.open(next((tmp_path / p).glob("*.png"))), np.float32) / 255 for p in ("full", "half")]
    assert _psnr(*images) > 45.0

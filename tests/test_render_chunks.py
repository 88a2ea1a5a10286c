"""Rendering in chunks (render.in_chunks): a GPU renders a frame in large chunks, and a chunk the
device has no memory for is tried again in halves.  CPU-only here: the device's refusal is
played by a field that raises torch's out-of-memory error for chunks above a size, which is
what CUDA raises; the frame must come out the same as one rendered in small chunks.  The CPU's
and MPS's allocators say it with RuntimeErrors of their own, which are halved on too."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from neulf_core.render import LightField, in_chunks
from neulf_core.scene import load_scene
from neulf_core.train import TrainConfig, train

# What torch raises when a device runs out of memory (older torch: only the CUDA class).
OUT_OF_MEMORY = getattr(torch, "OutOfMemoryError", torch.cuda.OutOfMemoryError)
# torch's CPU allocator (the words of c10's alloc_cpu.cpp), and an unrelated RuntimeError.
CPU_REFUSAL = ("[enforce fail at alloc_cpu.cpp:127] err == 0. DefaultCPUAllocator: can't allocate memory: you tried "
               "to allocate 268416000 bytes. Error code 12 (Cannot allocate memory)")


def test_in_chunks_covers_everything_once_and_halves_on_out_of_memory():
    seen, sizes = [], []

    def run(start, stop):
        sizes.append(stop - start)
        if stop - start > 3:
            raise OUT_OF_MEMORY("no room")
        seen.extend(range(start, stop))

    in_chunks(20, 16, run)
    assert seen == list(range(20))
    assert sizes[:3] == [16, 8, 4] and max(sizes[3:]) == 2  # the smaller size is kept from then on


def test_in_chunks_halves_on_the_cpu_allocators_refusal_only():
    sizes = []

    def run(start, stop):
        sizes.append(stop - start)
        if stop - start > 4:
            raise RuntimeError(CPU_REFUSAL)

    in_chunks(16, 16, run)
    assert sizes == [16, 8, 4, 4, 4, 4]

    def broken(start, stop):
        raise RuntimeError("mat1 and mat2 shapes cannot be multiplied")

    with pytest.raises(RuntimeError, match="shapes"):  # (a bug is not retried in halves)
        in_chunks(16, 16, broken)


@pytest.mark.parametrize("gpu", ["cuda", "mps"])
def test_in_chunks_hands_the_gpus_cached_blocks_back_before_the_smaller_try(monkeypatch, gpu):
    released = []
    monkeypatch.setattr(torch.cuda, "is_available", lambda: gpu == "cuda")
    monkeypatch.setattr(torch.backends.mps, "is_available", lambda: gpu == "mps")
    monkeypatch.setattr(torch.cuda, "empty_cache", lambda: released.append("cuda"))
    monkeypatch.setattr(torch.mps, "empty_cache", lambda: released.append("mps"))

    def run(start, stop):
        if stop - start > 4:
            raise OUT_OF_MEMORY("no room")

    in_chunks(8, 8, run)
    assert released == [gpu]


def test_in_chunks_stops_when_asked_and_gives_up_at_one():
    calls = []
    in_chunks(10, 3, lambda a, b: calls.append((a, b)) or (len(calls) < 2))
    assert calls == [(0, 3), (3, 6)]

    def never(start, stop):
        raise OUT_OF_MEMORY("none at all")

    with pytest.raises(OUT_OF_MEMORY):
        in_chunks(4, 4, never)


@pytest.fixture(scope="module")
def light_field(tiny_scene, tmp_path_factory):
    model_dir = tmp_path_factory.mktemp("chunks")
    train(tiny_scene, model_dir, TrainConfig(steps=30, batch_size=512, seed=0, validate_seconds=1e9,
                                             checkpoint_seconds=1e9, device="cpu"))
    return LightField.load(model_dir, "cpu")


def _refusing_big_chunks(light_field, limit: int):
    """The light field's query, raising the out-of-memory error for more than `limit` rays."""
    query = light_field.query

    def refusing(origins, directions, want_depth=True, want_colour=True):
        if len(directions) > limit:
            raise OUT_OF_MEMORY(f"{len(directions)} rays do not fit")
        return query(origins, directions, want_depth, want_colour)
    return refusing


def test_frame_rendered_after_out_of_memory_matches_small_chunks(light_field, tiny_scene, monkeypatch):
    view = load_scene(tiny_scene).views[0]
    camera = view.scaled_camera(1.0)
    K, width, height = camera.calibration_matrix(), int(camera.width), int(camera.height)
    small = light_field.render(K, width, height, view.R, view.t, depth=True, chunk=width * 2, pixel_samples=4)
    small_view = light_field.render_view(view, depth=True, chunk=97, pixel_samples=4)
    monkeypatch.setattr(light_field, "query", _refusing_big_chunks(light_field, width * 3))
    big = light_field.render(K, width, height, view.R, view.t, depth=True, chunk=width * height, pixel_samples=4)
    big_view = light_field.render_view(view, depth=True, chunk=width * height, pixel_samples=4)
    for a, b in ((small, big), (small_view, big_view)):
        assert np.array_equal(a.valid, b.valid)
        assert np.allclose(a.rgb, b.rgb, atol=1e-6)
        assert np.allclose(a.depth, b.depth, atol=1e-6, equal_nan=True)
    assert small.warnings == big.warnings


# What torch's MPS allocator raises (aten/src/ATen/mps/MPSAllocator.mm): out of its memory, and one
# buffer larger than Metal allows, both RuntimeErrors; a smaller chunk fits after either.
MPS_REFUSALS = ("MPS backend out of memory (MPS allocated: 17.94 GB, other allocations: 1.06 GB, max allowed: 18.13 GB). "
                "Tried to allocate 256.00 MB on private pool. Use PYTORCH_MPS_HIGH_WATERMARK_RATIO=0.0 to disable upper "
                "limit for memory allocations (may cause system failure).",
                "Invalid buffer size: 74.51 GB")


@pytest.mark.parametrize("refusal", MPS_REFUSALS, ids=["MPS backend out of memory", "Invalid buffer size"])
def test_a_field_the_mps_allocator_refuses_renders_in_halves(light_field, tiny_scene, monkeypatch, refusal):
    from neulf_core.errors import is_out_of_memory

    view = load_scene(tiny_scene).views[0]
    camera = view.scaled_camera(1.0)
    K, width, height = camera.calibration_matrix(), int(camera.width), int(camera.height)
    small = light_field.render(K, width, height, view.R, view.t, depth=True, chunk=width * 2)
    forward, sizes = light_field.field.forward, []

    def refusing(uvst, *args, **kwargs):
        sizes.append(len(uvst))
        if len(uvst) > width * 3:
            raise RuntimeError(refusal)
        return forward(uvst, *args, **kwargs)

    monkeypatch.setattr(light_field.field, "forward", refusing)
    big = light_field.render(K, width, height, view.R, view.t, depth=True, chunk=width * height)
    assert max(sizes) > width * 3 and sizes[-1] <= width * 3  # (refused, then halved until it fitted)
    assert np.array_equal(small.valid, big.valid)
    assert np.allclose(small.rgb, big.rgb, atol=1e-6)
    assert np.allclose(small.depth, big.depth, atol=1e-6, equal_nan=True)
    assert is_out_of_memory(RuntimeError(refusal)) and not is_out_of_memory(ValueError(refusal))


def test_a_chunk_retried_after_its_points_ran_out_of_memory_counts_its_rays_once(light_field, tiny_scene,
                                                                                  monkeypatch):
    """A view moved sideways, so some of its rays leave the captured region: a chunk whose
    multi-point pass (after the rays were counted) runs out of memory is retried, and
    render_view's warning still counts each ray once (it had said "200% of the rays leave")."""
    import dataclasses

    view = load_scene(tiny_scene).views[0]
    moved = dataclasses.replace(view, t=view.t + view.R @ np.array([0.25, 0.0, 0.0]))
    plain = light_field.render_view(moved, depth=False, pixel_samples=4)
    leaving = [w for w in plain.warnings if "leave" in w]
    assert leaving, plain.warnings  # (the test needs rays that leave the region)
    mean_colour, refused = light_field._mean_colour, []

    def once_out_of_memory(rays, forward=None):
        if not refused:
            refused.append(True)
            raise OUT_OF_MEMORY("the points of a pixel do not fit")
        return mean_colour(rays, forward)

    monkeypatch.setattr(light_field, "_mean_colour", once_out_of_memory)
    retried = light_field.render_view(moved, depth=False, pixel_samples=4)
    assert refused and retried.warnings == plain.warnings
    assert np.allclose(retried.rgb, plain.rgb, atol=1e-6)

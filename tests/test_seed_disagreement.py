"""benchmarks/seed_disagreement.py: depth edges from a render's depth, and the split of the
seeds' difference between the edges and the rest."""

import numpy as np
import pytest


@pytest.fixture(scope="module")
def disagreement(benchmark_script):
    return benchmark_script("seed_disagreement")


def a_near_square(size=40, near=1.0, far=0.25):
    """Inverse depth: a far background with a near square in the middle (a silhouette)."""
    inverse = np.full((size, size), far)
    inverse[10:30, 10:30] = near
    return inverse


def test_depth_edges_lie_along_the_silhouette_only(disagreement):
    edges = disagreement.depth_edges(a_near_square(), radius=2)
    assert edges[10, 20] and edges[29, 20] and edges[20, 9] and edges[20, 30]  # both sides of each side
    assert edges[20, 7] and not edges[20, 6]  # the pixel beside the jump and two more, no further
    assert not edges[20, 20] and not edges[2, 2]  # inside the square, and the background
    smooth = np.linspace(0.5, 1.0, 40)[None, :].repeat(40, 0)  # a slanted plane: 3 % steps at most
    assert not disagreement.depth_edges(smooth).any()


def test_depth_edges_ignore_pixels_without_depth(disagreement):
    inverse = np.full((20, 20), np.nan)
    assert not disagreement.depth_edges(inverse).any()


def test_the_gap_between_seeds_is_split_between_edges_and_the_rest(disagreement):
    rng = np.random.default_rng(0)
    target = rng.uniform(0.2, 0.8, size=(40, 40, 3))
    edges = disagreement.depth_edges(a_near_square())
    best = target + 0.01
    worse = best.copy()
    worse[edges] += 0.1  # the worse seed differs on the edges only
    row = disagreement.attribute(np.stack([worse, best]), target, edges)
    assert row["gap_on_edges"] == pytest.approx(1.0)
    assert row["variance_on_edges"] == pytest.approx(1.0)
    assert row["edge_area"] == pytest.approx(edges.mean())
    assert row["psnr"][1] == pytest.approx(40.0) and row["psnr"][0] < row["psnr"][1]
    spread = best + np.where(edges[..., None], 0.0, 0.05)  # now it differs off the edges only
    row = disagreement.attribute(np.stack([best, spread]), target, edges)
    assert row["gap_on_edges"] == pytest.approx(0.0, abs=1e-9)


def test_a_finished_model_of_the_same_job_is_kept(disagreement, tmp_path):
    stability = disagreement.stability
    job = stability.Job("lambertian", "/nowhere", "/nowhere", 0.5, "fast", 1000, 0,
                        colour_start=stability.preset_colour_start("fast"))
    out = disagreement.model_dir(tmp_path, job)
    out.mkdir(parents=True)
    (out / "model.pt").write_bytes(b"weights")
    (out / "job.json").write_text(job.key)
    assert disagreement.train_kept(job, out).endswith("kept")  # no training (the scene does not exist)
    other = stability.Job("lambertian", "/nowhere", "/nowhere", 0.5, "fast", 3000, 0,
                          colour_start=stability.preset_colour_start("fast"))
    assert disagreement.model_dir(tmp_path, other) != out


def test_image_edges_are_the_share_of_pixels_where_the_colour_changes_most(disagreement):
    image = np.zeros((40, 40, 3))
    image[:, 20:] = 1.0  # one vertical edge
    image += np.random.default_rng(1).uniform(0, 1e-3, image.shape)  # ties broken
    edges = disagreement.image_edges(image, share=0.05)
    assert edges.mean() == pytest.approx(0.05, abs=0.01)
    assert edges[:, 19:21].mean() > 0.9 and not edges[:, :17].any() and not edges[:, 23:].any()

"""Field representations: the published networks' shapes, and the fast field's shear geometry."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from neulf_core.fields import build_field, count_parameters, make_config
from neulf_core.fields.disparity import _features_at, mark_bilinear_footprint, push_pull_fill, slab_geometry
from neulf_core.slab import Slab


def _linear_inputs(module) -> list[int]:
    return [layer.in_features for layer in module.layers]


def test_paper_network_is_as_published():
    field = build_field("mlp", make_config("mlp", {"depth": 20, "width": 256, "skip": "input"}))
    # 20 ReLU layers of 256; the raw 4D input re-enters before layers 5, 9, 13, 17.
    assert len(field.layers) == 20 and all(layer.out_features == 256 for layer in field.layers)
    assert _linear_inputs(field) == [4, 256, 256, 256, 260, 256, 256, 256, 260, 256, 256, 256, 260, 256, 256, 256, 260, 256, 256, 256]
    assert field.feature.out_features == 256
    assert [m.out_features for m in field.colour_head if hasattr(m, "out_features")] == [128, 3]
    assert [m.out_features for m in field.depth_head if hasattr(m, "out_features")] == [128, 1]
    with torch.no_grad():
        rgb, depth = field(torch.rand(7, 4) * 2 - 1)
    assert rgb.shape == (7, 3) and depth.shape == (7, 1)
    assert float(rgb.min()) >= 0 and float(rgb.max()) <= 1 and float(depth.min()) >= 0 and float(depth.max()) <= 1


def test_authors_network_skips_the_embedding():
    field = build_field("mlp", make_config("mlp", {"depth": 8, "width": 256, "skip": "embedding"}))
    assert _linear_inputs(field) == [4, 256, 256, 256, 512, 256, 256, 256]
    assert count_parameters(field) < count_parameters(build_field("mlp", make_config("mlp", {"depth": 20})))


def test_disparity_shear_maps_rays_through_one_point_to_one_texel():
    """Rays from different uv points through the same 3D point read the same texture point
    when delta = z_st / z - 1 (the identity the fast field is built on)."""
    slab = Slab(np.eye(3), np.zeros(3), 0.0, 4.0, 2.0, 8.0, np.array([-0.5, -0.4, -3.0, -2.0]), np.array([0.7, 0.4, 3.0, 2.5]))
    field = build_field("disparity", make_config("disparity", {**slab_geometry(slab), "texture_size": [16, 16], "texture_levels": 1}))
    point = torch.tensor([0.8, -0.3, 3.0], dtype=torch.float64)   # depth 3 in front of the st plane (4)
    uv_points = torch.tensor([[-0.4, -0.3, 0.0], [0.0, 0.0, 0.0], [0.6, 0.35, 0.0]], dtype=torch.float64)
    directions = point - uv_points
    uvst, valid = slab.rays_to_uvst(uv_points, directions / directions.norm(dim=1, keepdim=True))
    assert bool(valid.all())
    delta = slab.z_st / 3.0 - 1.0
    uv = uvst[:, :2].float() * field.uv_half + field.uv_centre
    st = uvst[:, 2:].float() * field.st_half + field.st_centre
    sheared = st + uv * delta
    assert torch.allclose(sheared, sheared[0].expand_as(sheared), atol=1e-5)
    # And the depth the field reports for that delta is the point's depth.
    unit = torch.tensor([(1 / 3.0 - 1 / slab.z_far) / (1 / slab.z_near - 1 / slab.z_far)], dtype=torch.float64)
    assert abs(float(field.disparity(unit)) - delta) < 1e-6
    assert abs(float(slab.depth_from_unit(unit)) - 3.0) < 1e-9


def test_depth_detail_correction_is_shared_by_every_viewpoint_of_a_surface_point():
    """The depth detail is read where the planes' depth puts a ray's surface point in the
    texture's coordinates: rays from anywhere on the uv plane through one point on that depth
    get one correction, rays through another point another; with its zero read-out at the
    start the field's depth is the planes' own.  A second read (the trainer's for few photos)
    looks again where the corrected depth puts the point."""
    slab = Slab(np.eye(3), np.zeros(3), 0.0, 4.0, 2.0, 8.0, np.array([-0.5, -0.4, -3.0, -2.0]), np.array([0.7, 0.4, 3.0, 2.5]))
    options = {**slab_geometry(slab), "texture_size": [32, 32], "depth_detail_shift": 1}
    field = build_field("disparity", make_config("disparity", options))
    assert field.depth_detail.shape == (1, 4, 16, 16)
    uv_points = torch.tensor([[-0.4, -0.3, 0.0], [0.0, 0.0, 0.0], [0.6, 0.35, 0.0], [0.3, -0.2, 0.0]], dtype=torch.float64)

    def rays_through(point):
        directions = torch.tensor(point, dtype=torch.float64) - uv_points
        uvst, valid = slab.rays_to_uvst(uv_points, directions / directions.norm(dim=1, keepdim=True))
        assert bool(valid.all())
        return uvst.float()

    with torch.no_grad():
        planes_unit = torch.sigmoid(field.geometry.decoder[-1].bias[3])  # the start: the planes give every ray this depth
        field.geometry.decoder[-1].weight.zero_()
        first, second = rays_through([0.8, -0.3, 4.0]), rays_through([-1.5, 1.2, 4.0])  # on the st plane (depth 4)
        assert torch.allclose(field.sheared(first)[1], planes_unit.expand(4, 1))
        field.depth_detail.normal_()
        field.depth_detail_readout.weight.normal_()
        unit_first, unit_second = field.sheared(first)[1], field.sheared(second)[1]
    assert float((unit_first - planes_unit).abs().min()) > 1e-3                    # corrected ...
    assert torch.allclose(unit_first, unit_first[0].expand_as(unit_first), atol=1e-6)  # ... alike from every viewpoint
    assert torch.allclose(unit_second, unit_second[0].expand_as(unit_second), atol=1e-6)
    assert abs(float(unit_first[0] - unit_second[0])) > 1e-3                      # another point, another correction
    assert "depth_detail" not in build_field("disparity", make_config("disparity", {**options, "depth_detail_shift": 0})).state_dict()

    twice = build_field("disparity", make_config("disparity", {**options, "depth_detail_reads": 2}))
    twice.load_state_dict(field.state_dict())
    with torch.no_grad():
        uv = first[:, :2] * field.uv_half + field.uv_centre
        scale = 1.0 / (1.0 + field.config.texture_margin)
        again = field._shear(first, uv, unit_first, scale)  # where the first correction put the point
        detail = _features_at(field.depth_detail, again)
        expected = torch.sigmoid(torch.logit(planes_unit).expand(4, 1) + field.depth_detail_readout(detail))
        assert torch.allclose(twice.sheared(first)[1], expected, atol=1e-5)
    assert float((expected - unit_first).abs().max()) > 1e-3  # the second read moved it


def test_the_depth_detail_is_read_twice_for_few_photos():
    from neulf_core.rules import default_coarse_to_fine, default_depth_detail_reads

    assert default_depth_detail_reads(4) == default_depth_detail_reads(13) == 2
    assert default_depth_detail_reads(14) == default_depth_detail_reads(70) == 1  # the synthetic scene's 14: -0.19 dB
    assert all((default_depth_detail_reads(n) == 2) == default_coarse_to_fine(n) for n in range(2, 40))


def test_few_photos_get_a_stronger_smoothness_prior_on_the_geometry():
    from neulf_core.rules import FEW_VIEWS_GEOMETRY_TV, default_coarse_to_fine, default_geometry_tv

    assert default_geometry_tv(4) == default_geometry_tv(13) == FEW_VIEWS_GEOMETRY_TV == 3e-3
    assert default_geometry_tv(14) == make_config("disparity", {}).tv_weight == 1e-3  # the field's own
    assert all((default_geometry_tv(n) == 3e-3) == default_coarse_to_fine(n) for n in range(2, 40))


def test_fast_geometry_planes_are_one_octave_coarser_than_the_fields_own(tiny_scene):
    from neulf_core.scene import load_scene, split_views
    from neulf_core.slab import fit_slab
    from neulf_core.train import _build_field

    assert make_config("disparity", {}).geometry_spatial_res == [32, 64, 128]  # models saved before read as they were
    scene = load_scene(tiny_scene)
    views = split_views(scene)[0]
    slab = fit_slab(scene, views)
    for count in (5, len(views)):  # few photos and all of them alike
        built, _ = _build_field("fast", {}, views[:count], slab, 1.0)
        assert built.config.geometry_spatial_res == [16, 32, 64]
        assert tuple(built.geometry.scales[-1][-1].shape[-2:]) == (64, 64)  # the st plane's finest cells, built
    chosen, _ = _build_field("fast", {"geometry_spatial_res": [8, 16]}, views[:5], slab, 1.0)
    assert chosen.config.geometry_spatial_res == [8, 16]  # the user's choice wins


def test_fast_field_starts_on_the_st_plane():
    """Before training, the fast field's depth output is the st plane: classic single-plane
    light field rendering is the starting point."""
    slab = Slab(np.eye(3), np.zeros(3), 0.0, 4.0, 2.0, 8.0, -np.ones(4), np.ones(4))
    field = build_field("disparity", make_config("disparity", {**slab_geometry(slab), "texture_size": [16, 16]}))
    _, unit = field(torch.rand(50, 4) * 2 - 1)
    depth = slab.depth_from_unit(unit.double())
    assert torch.allclose(depth, torch.full_like(depth, 4.0), rtol=0.02)


def test_rendering_decodes_colour_in_slices_with_the_same_result_as_training():
    """Without gradients on a CPU the colour decoder runs DECODE_ROWS rays at a time (faster:
    the hidden layer stays in cache); the colours must equal one call's, slice edges included."""
    from neulf_core.fields import disparity
    slab = Slab(np.eye(3), np.zeros(3), 0.0, 4.0, 2.0, 8.0, -np.ones(4), np.ones(4))
    torch.manual_seed(0)
    field = build_field("disparity", make_config("disparity", {**slab_geometry(slab), "texture_size": [16, 16], "hidden": 128}))
    uvst = torch.rand(2 * disparity.DECODE_ROWS + 5, 4) * 2 - 1
    whole, unit = field(uvst)  # gradients on: one decoder call
    with torch.no_grad():
        sliced, unit_sliced = field(uvst)
    assert torch.allclose(sliced, whole.detach(), atol=1e-6) and torch.equal(unit_sliced, unit.detach())


def test_push_pull_fill_keeps_seen_texels_and_fills_holes_from_their_neighbours():
    texture = torch.zeros(1, 2, 8, 8)
    texture[:, 0, :, :4] = 1.0     # left half seen, channel 0 at 1
    texture[:, 1, :, :4] = -2.0
    texture[:, :, :, 4:] = 7.0     # right half unseen: whatever it holds must go
    mask = torch.zeros(8, 8, dtype=torch.bool)
    mask[:, :4] = True
    filled = push_pull_fill(texture, mask)
    assert torch.equal(filled[..., :4], texture[..., :4])
    assert torch.allclose(filled[:, 0, :, 4:], torch.ones(8, 4)) and torch.allclose(filled[:, 1, :, 4:], torch.full((8, 4), -2.0))


def test_fast_field_fills_texels_no_training_ray_reads():
    """After training, texels outside every training ray's footprint take the seen texels'
    features (an extrapolated view continues the edge), and seen texels stay bit-identical."""
    slab = Slab(np.eye(3), np.zeros(3), 0.0, 4.0, 2.0, 8.0, -np.ones(4), np.ones(4))
    field = build_field("disparity", make_config("disparity", {**slab_geometry(slab), "texture_size": [16, 16], "texture_levels": 2}))
    with torch.no_grad():
        for texture in field.textures:
            texture.normal_()
    before = [texture.detach().clone() for texture in field.textures]
    rays = torch.rand(4000, 4) * 2 - 1
    rays[:, 2] = rays[:, 2].abs() * 0.5        # training rays read only the right part of s
    unseen = field.fill_unseen_texels([rays[:2000], rays[2000:]])
    assert 0.3 < unseen < 0.8
    grid, _ = field.sheared(rays)
    for texture, old in zip(field.textures, before):
        rows, cols = texture.shape[2:]
        mask = torch.zeros(rows * cols, dtype=torch.bool)
        mark_bilinear_footprint(mask, grid, rows, cols)
        mask = mask.view(rows, cols)
        assert torch.equal(texture.detach()[..., mask], old[..., mask])
        assert not torch.equal(texture.detach()[..., ~mask], old[..., ~mask])
        # A hole's features lie within the range of the seen texels' (an average of them).
        seen = old[..., mask]
        assert bool((texture.detach()[..., ~mask] <= seen.amax(-1, keepdim=True) + 1e-5).all())
        assert bool((texture.detach()[..., ~mask] >= seen.amin(-1, keepdim=True) - 1e-5).all())


def test_fast_field_fills_depth_detail_cells_no_training_ray_reads():
    """The depth detail's cells outside every training ray's reads (at both reads' points) take
    the read cells' features, so an extrapolated view gets no random depth correction; the read
    cells stay bit-identical."""
    slab = Slab(np.eye(3), np.zeros(3), 0.0, 4.0, 2.0, 8.0, -np.ones(4), np.ones(4))
    options = {**slab_geometry(slab), "texture_size": [32, 32], "texture_levels": 1, "depth_detail_shift": 1,
               "depth_detail_reads": 2}
    field = build_field("disparity", make_config("disparity", options))
    with torch.no_grad():
        field.depth_detail.normal_()
        field.depth_detail_readout.weight.normal_()
    before = field.depth_detail.detach().clone()
    rays = torch.rand(4000, 4) * 2 - 1
    rays[:, 2] = rays[:, 2].abs() * 0.5        # training rays read only the right part of s
    reads = []
    field.sheared(rays, reads)
    assert len(reads) == 2 and not torch.equal(reads[0], reads[1])  # the second read is elsewhere
    mask = torch.zeros(16 * 16, dtype=torch.bool)
    for points in reads:
        mark_bilinear_footprint(mask, points, 16, 16)
    mask = mask.view(16, 16)
    assert 0.2 < float(mask.float().mean()) < 0.9
    field.fill_unseen_texels([rays[:2000], rays[2000:]])
    after = field.depth_detail.detach()
    assert torch.equal(after[..., mask], before[..., mask])
    assert not torch.equal(after[..., ~mask], before[..., ~mask])
    seen = before[..., mask]
    assert bool((after[..., ~mask] <= seen.amax(-1, keepdim=True) + 1e-5).all())
    assert bool((after[..., ~mask] >= seen.amin(-1, keepdim=True) - 1e-5).all())


def test_depth_layers_shift_with_the_camera_like_a_surface_at_their_depth():
    """A depth layer's feature at one disparity is read, from every ray through a point at that
    depth, at one place: rays through one 3D point on layer k get layer k's same feature."""
    slab = Slab(np.eye(3), np.zeros(3), 0.0, 4.0, 2.0, 8.0, -np.ones(4), np.ones(4))
    field = build_field("disparity", make_config("disparity", {**slab_geometry(slab), "texture_size": [16, 16], "geometry_layers": 3}))
    # Layer disparities span near..far; the middle one (unit 0.5) sits at inverse depth halfway.
    depth = 1.0 / (0.5 / slab.z_near + 0.5 / slab.z_far)
    point = torch.tensor([0.2, -0.1, depth], dtype=torch.float64)
    uv_points = torch.tensor([[-0.5, -0.4, 0.0], [0.0, 0.0, 0.0], [0.6, 0.5, 0.0]], dtype=torch.float64)
    directions = point - uv_points
    uvst, _ = slab.rays_to_uvst(uv_points, directions / directions.norm(dim=1, keepdim=True))
    uvst = uvst.float()
    uv = uvst[:, :2] * field.uv_half + field.uv_centre
    middle = (uvst[:, 2:] + uv * (field.layer_disparity[1] / field.st_half))
    assert torch.allclose(middle, middle[0].expand_as(middle), atol=1e-5)
    rgb, unit = field(uvst)
    assert rgb.shape == (3, 3) and bool(torch.isfinite(unit).all())


def test_depth_layers_by_default_only_on_shallow_scenes():
    from neulf_core.rules import DEFAULT_DEPTH_LAYERS, default_depth_layers

    def slab(near, far):
        return Slab(np.eye(3), np.zeros(3), 0.0, (near + far) / 2, near, far, -np.ones(4), np.ones(4))

    assert default_depth_layers(slab(10.0, 20.0), 23) == DEFAULT_DEPTH_LAYERS  # Statue-like, far/near 2
    assert default_depth_layers(slab(10.0, 20.0), 13) == 0                     # too few photos
    assert default_depth_layers(slab(1.26, 3.27), 18) == DEFAULT_DEPTH_LAYERS  # HCI's 25 %: 18 views
    assert default_depth_layers(slab(1.26, 3.27), 17) == 0
    assert default_depth_layers(slab(2.0, 6.9), 23) == 0                       # the synthetic scene, 3.3
    assert default_depth_layers(slab(16.8, 77.8), 23) == 0                     # fern, 4.6


def test_train_cli_depth_layers_are_saved_and_render(tiny_scene, tmp_path, capsys):
    from neulf_core.checkpoint import load_checkpoint
    from neulf_core.cli import main
    from neulf_core.render import LightField
    from neulf_core.scene import load_scene

    out = tmp_path / "m"
    args = ["train", str(tiny_scene), "--out", str(out), "--steps", "5", "--batch-size", "256", "--progress", "json",
            "--no-sweep-teacher", "--depth-layers", "2"]
    assert main(args) == 0
    assert load_checkpoint(out)["field_config"]["geometry_layers"] == 2
    assert load_checkpoint(out)["field_config"]["depth_detail_shift"] == 0  # the layers replace the depth detail
    assert main(args[:-1] + ["0", "--out", str(tmp_path / "none")]) == 0  # 0 turns the default off
    assert load_checkpoint(tmp_path / "none")["field_config"]["geometry_layers"] == 0
    assert load_checkpoint(tmp_path / "none")["field_config"]["depth_detail_shift"] == 2
    assert load_checkpoint(tmp_path / "none")["field_config"]["depth_detail_reads"] == 2  # 7 training views
    assert load_checkpoint(tmp_path / "none")["field_config"]["tv_weight"] == 3e-3
    rendering = LightField.load(out, "cpu").render_view(load_scene(tiny_scene).views[0], depth=True)
    assert np.isfinite(rendering.rgb).all()
    capsys.readouterr()
    assert main(["train", str(tiny_scene), "--out", str(tmp_path / "mlp"), "--steps", "1", "--preset", "authors",
                 "--depth-layers", "2"]) != 0
    assert "--depth-layers" in capsys.readouterr().err


def _back_surface_field(**options):
    slab = Slab(np.eye(3), np.zeros(3), 0.0, 4.0, 2.0, 8.0, -np.ones(4), np.ones(4))
    return build_field("disparity", make_config("disparity", {**slab_geometry(slab), "texture_size": [16, 16], "texture_levels": 2,
                                                              "back_surface": True, **options}))


def test_back_surface_stays_behind_the_front_and_blends_two_texture_reads():
    """With a back surface each ray reads the texture at two shears, the back one at a depth
    unit below the front's (farther), and its colour and depth are the weighted blend of the
    two surfaces' -- half and half at the start.  Blending "features" mixes the two reads
    before one decode instead of the two decoded colours."""
    torch.manual_seed(0)
    field = _back_surface_field(depth_detail_shift=0)
    with torch.no_grad():
        for texture in field.textures:
            texture.normal_()
        field.geometry.decoder[-1].weight.normal_()  # surfaces that differ from ray to ray
        rays = torch.rand(500, 4) * 2 - 1
        (front_grid, front_unit), (back_grid, back_unit) = field.surfaces(rays)[0]
        weight = field.surfaces(rays)[1]
        assert bool((back_unit < front_unit).all())
        assert not torch.allclose(front_grid, back_grid)
        rgb, unit = field(rays)
        uv = rays[:, :2]
        front_features, back_features = field._texture_features(front_grid, uv), field._texture_features(back_grid, uv)
        front_rgb, back_rgb = field._colour(front_features, uv), field._colour(back_features, uv)
        assert torch.allclose(rgb, weight * front_rgb + (1 - weight) * back_rgb, atol=1e-6)  # "colour", models saved before
        field.config.back_surface_blend = "features"
        decoded = []
        hook = field.decoder.register_forward_hook(lambda module, inputs, output: decoded.append(inputs[0].shape[0]))
        blended_rgb, blended_unit = field(rays)
        hook.remove()
        assert decoded == [500]  # one decode of N rows, not 2N
        mixed = weight * front_features + (1 - weight) * back_features
        assert torch.allclose(blended_rgb, field._colour(mixed, uv), atol=1e-6)
        assert torch.allclose(blended_unit, unit) and not torch.allclose(blended_rgb, rgb, atol=1e-3)
        assert torch.allclose(unit, weight * front_unit + (1 - weight) * back_unit, atol=1e-6)
        assert torch.equal(field.sheared(rays)[0], front_grid)  # `sheared` is the front surface's
    fresh = _back_surface_field()
    with torch.no_grad():
        (_, front_unit), (_, back_unit) = fresh.surfaces(rays)[0]
        assert torch.allclose(fresh.surfaces(rays)[1], torch.full((500, 1), 0.5), atol=0.02)
        assert torch.allclose(back_unit, front_unit * 0.5, atol=0.02)


def test_back_surface_by_default_on_deep_scenes_and_the_cli_flags(tiny_scene, tmp_path, capsys):
    from neulf_core.checkpoint import load_checkpoint
    from neulf_core.cli import main
    from neulf_core.render import LightField
    from neulf_core.scene import load_scene
    from neulf_core.rules import default_back_surface

    def slab(near, far):
        return Slab(np.eye(3), np.zeros(3), 0.0, (near + far) / 2, near, far, -np.ones(4), np.ones(4))

    assert default_back_surface(slab(2.0, 6.9))        # the synthetic scene, far/near 3.3
    assert default_back_surface(slab(16.8, 77.8))      # fern, 4.6
    assert not default_back_surface(slab(10.0, 20.0))  # Statue-like, 2.0
    out = tmp_path / "m"
    args = ["train", str(tiny_scene), "--out", str(out), "--steps", "5", "--batch-size", "256", "--progress", "json",
            "--no-sweep-teacher", "--back-surface"]
    assert main(args) == 0
    saved = load_checkpoint(out)["field_config"]
    assert saved["back_surface"] is True and saved["back_surface_blend"] == "features"  # the fast preset's
    assert make_config("disparity", {k: v for k, v in saved.items() if k != "back_surface_blend"}).back_surface_blend == "colour"
    rendering = LightField.load(out, "cpu").render_view(load_scene(tiny_scene).views[0], depth=True)
    assert np.isfinite(rendering.rgb).all() and np.isfinite(rendering.depth).all()
    assert main(args[:-1] + ["--no-back-surface", "--out", str(tmp_path / "one")]) == 0
    assert load_checkpoint(tmp_path / "one")["field_config"]["back_surface"] is False
    capsys.readouterr()
    assert main(["train", str(tiny_scene), "--out", str(tmp_path / "mlp"), "--steps", "1", "--preset", "authors",
                 "--back-surface"]) != 0
    assert "--back-surface" in capsys.readouterr().err


RENDER_FRAMES = """
import resource, sys
import numpy as np, torch
from neulf_core.fields import build_field, make_config
from neulf_core.fields.disparity import slab_geometry
from neulf_core.render import LightField
from neulf_core.slab import Slab
slab = Slab(np.eye(3), np.zeros(3), 0.0, 4.0, 2.0, 8.0, -np.ones(4), np.ones(4))
field = build_field("disparity", make_config("disparity", {**slab_geometry(slab), "texture_size": [338, 600], "texture_channels": 4}))
light_field = LightField(field, slab, {}, torch.device("cpu"))
K = np.array([[400.0, 0, 240], [0, 400.0, 135], [0, 0, 1]])
light_field.render(K, 480, 270, np.eye(3), np.zeros(3))
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(FRAMES):
    light_field.render(K, 480, 270, np.eye(3), np.zeros(3))
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""
FRAMES = 6


def test_cpu_render_does_not_page_fault_its_chunk_buffers_in_again():
    """A CPU render's chunks reuse the buffers the previous chunk freed: after a first
    480x270 frame, the next frames of the default field take under 1,000 page faults each on
    average (0 for most frames, a few hundred when the heap grows once; 4,000-16,000 per
    frame with glibc's default thresholds, docs/BENCHMARKS.md).  In a fresh process, so that
    what other tests left in this one's heap does not count."""
    assert int(_last_line_of_fresh_process(f"FRAMES = {FRAMES}\n" + RENDER_FRAMES, threads=2)) < 1000 * FRAMES


def _last_line_of_fresh_process(code: str, *args: str, threads: int) -> str:
    """The last line `code` prints, run with `args` in a new Python process of the repository
    (so that what other tests left in this one's heap does not count); skips where the
    allocator setting these tests measure does not exist (it is glibc's)."""
    import os
    import platform
    import subprocess
    import sys
    from pathlib import Path

    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        pytest.skip("the allocator setting is glibc's")
    done = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True,
                          cwd=Path(__file__).resolve().parents[1], env={**os.environ, "OMP_NUM_THREADS": str(threads)})
    assert done.returncode == 0, done.stderr
    return done.stdout.strip().splitlines()[-1]


TRAIN_STEPS = """
import resource, sys
from neulf_core import device
from neulf_core.train import TrainConfig, train
faults = {}
def progress(event):
    if event.get("event") in ("step", "validate") and event["step"] in (20, 60):
        faults[event["step"]] = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
train(sys.argv[1], sys.argv[2], TrainConfig(steps=60, device="cpu", back_surface=True, refine_poses=False,
                                             checkpoint_seconds=1e9, validate_seconds=1e9), progress=progress)
print(device._allocator_tuned, faults[60] - faults[20])
"""


def test_cpu_training_keeps_its_freed_step_buffers(tiny_scene, tmp_path):
    """Training on a CPU keeps the buffers a step frees for the next step
    (device.keep_freed_cpu_memory), as rendering does: the back surface's 16k-row colour
    batch otherwise made glibc hand them back and page-fault them in again every step in 4
    of 14 runs (2.3 M faults in 400 steps of fern; docs/BENCHMARKS.md).  In a fresh process;
    40 steps of the tiny scene take 13-2,059 faults with the setting, about 180,000 without."""
    tuned, faults = _last_line_of_fresh_process(TRAIN_STEPS, str(tiny_scene), str(tmp_path / "model"), threads=1).split()
    assert tuned == "True"
    assert int(faults) < 40 * 100, f"{faults} page faults in 40 training steps"


def test_appearance_captures_get_eight_geometry_channels_and_resume_keeps_the_saved_shape(tiny_scene, tmp_path, monkeypatch):
    """`--appearance` trains the fast field with 8 geometry channels (the default has 4); a
    resumed model keeps the shape it was saved with even when the defaults changed since:
    the channels, and the colour decoder's width (128 now; models saved with 64 keep it)."""
    from neulf_core import presets
    from neulf_core.checkpoint import load_checkpoint
    from neulf_core.render import LightField
    from neulf_core.train import TrainConfig, train

    def channels(model):
        return load_checkpoint(model)["field_config"]["geometry_channels"]

    def width(model):
        return load_checkpoint(model)["field_config"]["hidden"]

    quick = dict(batch_size=256, teacher=False, validate_seconds=1e9, checkpoint_seconds=1e9)
    train(tiny_scene, tmp_path / "plain", TrainConfig(steps=2, **quick))
    train(tiny_scene, tmp_path / "exposures", TrainConfig(steps=2, appearance=True, **quick))
    assert channels(tmp_path / "plain") == presets.FAST_FIELD["geometry_channels"] == 4
    assert channels(tmp_path / "exposures") == presets.APPEARANCE_GEOMETRY["geometry_channels"] == 8
    monkeypatch.setitem(presets.FAST_FIELD, "geometry_channels", 6)
    result = train(tiny_scene, tmp_path / "plain", TrainConfig(steps=4, **quick), resume=True)
    assert result.step == 4 and channels(tmp_path / "plain") == 4
    assert width(tmp_path / "plain") == presets.FAST_FIELD["hidden"] == 128

    monkeypatch.setitem(presets.FAST_FIELD, "hidden", 64)  # a model saved before the wider decoder
    train(tiny_scene, tmp_path / "narrow", TrainConfig(steps=2, **quick))
    monkeypatch.setitem(presets.FAST_FIELD, "hidden", 128)
    result = train(tiny_scene, tmp_path / "narrow", TrainConfig(steps=4, **quick), resume=True)
    assert result.step == 4 and width(tmp_path / "narrow") == 64
    assert LightField.load(tmp_path / "narrow", "cpu").field.decoder[0].out_features == 64

    assert presets.FAST_FIELD["depth_detail_shift"] == 2 and hasattr(LightField.load(tmp_path / "plain", "cpu").field, "depth_detail")
    monkeypatch.setitem(presets.FAST_FIELD, "depth_detail_shift", 0)  # a model saved before the depth detail
    train(tiny_scene, tmp_path / "flat", TrainConfig(steps=2, **quick))
    monkeypatch.setitem(presets.FAST_FIELD, "depth_detail_shift", 2)
    result = train(tiny_scene, tmp_path / "flat", TrainConfig(steps=4, **quick), resume=True)
    assert result.step == 4 and not hasattr(LightField.load(tmp_path / "flat", "cpu").field, "depth_detail")

    linear = LightField.load(tmp_path / "plain", "cpu").field  # the default: a colour and its (u, v) slope
    assert presets.FAST_FIELD["view_dependence_linear"] and linear.linear_view_dependence
    assert linear.decoder[-1].out_features == 9
    monkeypatch.delitem(presets.FAST_FIELD, "view_dependence_linear")  # a model saved before it
    train(tiny_scene, tmp_path / "uv_input", TrainConfig(steps=2, **quick))
    monkeypatch.setitem(presets.FAST_FIELD, "view_dependence_linear", True)
    result = train(tiny_scene, tmp_path / "uv_input", TrainConfig(steps=4, **quick), resume=True)
    uv_input = LightField.load(tmp_path / "uv_input", "cpu").field
    assert result.step == 4 and not uv_input.linear_view_dependence
    assert uv_input.decoder[-1].out_features == 3 and uv_input.decoder[0].in_features == linear.decoder[0].in_features + 2


def test_fast_decoders_learn_at_the_factor_of_the_preset_rate_and_old_models_keep_theirs(tiny_scene, tmp_path, monkeypatch):
    """The fast field's decoders learn at `decoder_lr_factor` times the preset's rate, the
    feature grids at 10 times it; a model saved before the factor (no key: 1) resumes with
    its decoders at the preset's rate."""
    from neulf_core import presets
    from neulf_core.checkpoint import load_checkpoint
    from neulf_core.fields.disparity import DisparityConfig, DisparityField
    from neulf_core.train import TrainConfig, train

    def group_rates(model):
        saved = load_checkpoint(model)["optimizer"]["param_groups"]
        return {g["name"]: g["initial_lr"] for g in saved if g.get("name")}

    lr = presets.get_preset("fast").lr
    factor = presets.FAST_FIELD["decoder_lr_factor"]
    groups = {g["name"]: g["lr"] for g in DisparityField(DisparityConfig(decoder_lr_factor=factor)).param_groups(lr)}
    assert groups == {"texture": 10 * lr, "geometry planes": 10 * lr, "decoders": factor * lr}

    quick = dict(batch_size=256, teacher=False, validate_seconds=1e9, checkpoint_seconds=1e9)
    train(tiny_scene, tmp_path / "now", TrainConfig(steps=2, **quick))
    assert group_rates(tmp_path / "now")["decoders"] == pytest.approx(factor * lr)
    monkeypatch.delitem(presets.FAST_FIELD, "decoder_lr_factor")  # a model saved before the factor
    train(tiny_scene, tmp_path / "before", TrainConfig(steps=2, **quick))
    monkeypatch.setitem(presets.FAST_FIELD, "decoder_lr_factor", factor)
    result = train(tiny_scene, tmp_path / "before", TrainConfig(steps=4, **quick), resume=True)
    assert result.step == 4 and load_checkpoint(tmp_path / "before")["field_config"].get("decoder_lr_factor", 1.0) == 1.0
    assert group_rates(tmp_path / "before")["decoders"] == pytest.approx(lr)



def test_fast_preset_learning_rate_falls_along_a_cosine_to_one_percent(tiny_scene, tmp_path):
    """The default's schedule (docs/STABILITY.md, "Learning-rate schedule"): a cosine from the
    preset's rate to 1 % of it over the budget; the paper's networks keep their per-epoch decay."""
    from neulf_core.presets import get_preset
    from neulf_core.train import TrainConfig, learning_rate_factor, train

    fast = get_preset("fast")
    factors = [learning_rate_factor(fast, f) for f in np.linspace(0, 1, 21)]
    assert factors[0] == 1.0 and abs(factors[10] - 0.505) < 1e-9 and abs(factors[-1] - 0.01) < 1e-12
    assert all(a > b for a, b in zip(factors, factors[1:]))
    assert learning_rate_factor(fast, 0.25) > 0.1 ** 0.25  # longer at a high rate than the old exponential
    paper = get_preset("paper")
    assert abs(learning_rate_factor(paper, 0.5, epochs=2.0) - 0.995 ** 2) < 1e-12

    # what training uses: the rate logged at each validation follows the cosine
    result = train(tiny_scene, tmp_path / "m", TrainConfig(steps=40, batch_size=256, teacher=False,
                                                           validate_seconds=0.0, checkpoint_seconds=1e9))
    rates = [(record["step"], record["lr"]) for record in result.history]
    for step, lr in rates:  # logged after step `step`, set at its start: fraction (step - 1) / 40
        assert abs(lr - fast.lr * learning_rate_factor(fast, (step - 1) / 40)) < 1e-9
    assert rates[-1][1] < 0.02 * fast.lr


def test_coarse_to_fine_fades_the_finer_geometry_scales_in_and_a_saved_model_keeps_its_weights():
    """geometry_coarse_to_fine = T: the coarsest scale counts from the start, the next ones
    fade in one after another until T of the budget; a model saved part-way (a checkpoint,
    Cancel) loads with the weights it was trained with, not all ones; a weight never drops
    (a model resumed with a larger budget sees a smaller fraction)."""
    slab = Slab(np.eye(3), np.zeros(3), 0.0, 4.0, 2.0, 8.0, -np.ones(4), np.ones(4))
    options = {**slab_geometry(slab), "texture_size": [16, 16], "geometry_spatial_res": [8, 16, 32], "geometry_coarse_to_fine": 0.8}
    field = build_field("disparity", make_config("disparity", options))
    weights = {0.0: field.geometry_scale_weights.tolist()}
    for fraction in (0.2, 0.4, 0.6, 0.8, 1.0):
        field.set_training_progress(fraction)
        weights[fraction] = field.geometry_scale_weights.tolist()
    assert weights[0.0] == [1.0, 0.0, 0.0]
    assert np.allclose(weights[0.2], [1.0, 0.5, 0.0]) and np.allclose(weights[0.6], [1.0, 1.0, 0.5])
    assert weights[0.4] == [1.0, 1.0, 0.0] and weights[0.8] == weights[1.0] == [1.0, 1.0, 1.0]
    field.set_training_progress(0.1)
    assert field.geometry_scale_weights.tolist() == [1.0, 1.0, 1.0]

    partial = build_field("disparity", make_config("disparity", options))
    partial.set_training_progress(0.3)
    uvst = torch.rand(64, 4) * 2 - 1
    with torch.no_grad():  # the finest scale is off at 0.3: its planes do not change the output
        before = partial(uvst)[1]
        partial.geometry.scales[2][5].add_(torch.randn_like(partial.geometry.scales[2][5]))
        assert torch.equal(partial(uvst)[1], before)
    loaded = build_field("disparity", make_config("disparity", options))
    loaded.load_state_dict(partial.state_dict())
    assert np.allclose(loaded.geometry_scale_weights.tolist(), [1.0, 0.75, 0.0])
    with torch.no_grad():
        assert torch.equal(loaded(uvst)[0], partial(uvst)[0])

    off = build_field("disparity", make_config("disparity", {k: v for k, v in options.items() if k != "geometry_coarse_to_fine"}))
    assert "geometry_scale_weights" not in off.state_dict()  # models saved before the option load as before
    off.set_training_progress(0.0)  # and ignore the trainer's calls


def test_coarse_to_fine_by_default_with_few_photos_and_the_cli_flags(tiny_scene, tmp_path, capsys):
    from neulf_core.checkpoint import load_checkpoint
    from neulf_core.cli import main
    from neulf_core.render import LightField
    from neulf_core.scene import load_scene
    from neulf_core.train import TrainConfig, train
    from neulf_core.rules import COARSE_TO_FINE, default_coarse_to_fine

    assert default_coarse_to_fine(4) and default_coarse_to_fine(13)          # 25 % of the synthetic scene, 50 % of CanClip
    assert not default_coarse_to_fine(14) and not default_coarse_to_fine(26)  # all of them
    assert not default_coarse_to_fine(1)

    def ramp(model):
        payload = load_checkpoint(model)
        return payload["field_config"]["geometry_coarse_to_fine"], payload["state_dict"].get("geometry_scale_weights")

    quick = dict(batch_size=256, teacher=False, validate_seconds=1e9, checkpoint_seconds=1e9)
    n_train = len(load_scene(tiny_scene).views) - len(load_scene(tiny_scene).views[::8])
    assert default_coarse_to_fine(n_train)  # the test scene is a capture of few photos
    train(tiny_scene, tmp_path / "default", TrainConfig(steps=10, **quick))
    value, weights = ramp(tmp_path / "default")
    assert value == COARSE_TO_FINE and weights.tolist() == [1.0, 1.0, 1.0]  # the budget's end is past the ramp's
    result = train(tiny_scene, tmp_path / "default", TrainConfig(steps=20, **quick), resume=True)
    assert result.step == 20 and ramp(tmp_path / "default")[1].tolist() == [1.0, 1.0, 1.0]

    args = ["train", str(tiny_scene), "--steps", "3", "--batch-size", "256", "--progress", "json", "--no-sweep-teacher"]
    assert main(args + ["--out", str(tmp_path / "off"), "--no-coarse-to-fine"]) == 0
    assert ramp(tmp_path / "off") == (0.0, None)
    assert main(args + ["--out", str(tmp_path / "short"), "--coarse-to-fine"]) == 0
    value, weights = ramp(tmp_path / "short")  # 3 steps, the last at 2/3 of the budget: inside the ramp
    assert value == COARSE_TO_FINE and weights.tolist()[:2] == [1.0, 1.0] and 0 < weights.tolist()[2] < 1
    view = load_scene(tiny_scene).views[0]
    small = LightField.load(tmp_path / "short", "cpu")                     # model.pt: 8-bit grids, small tensors as saved
    full = LightField.load(tmp_path / "short" / "checkpoint.pt", "cpu")    # float32
    assert small.field.geometry_scale_weights.tolist() == weights.tolist()  # rendered as trained, not all ones
    a, b = small.render_view(view, depth=True), full.render_view(view, depth=True)
    assert np.isfinite(a.rgb).all() and np.abs(a.rgb - b.rgb).mean() < 0.01
    capsys.readouterr()
    assert main(args + ["--out", str(tmp_path / "mlp"), "--preset", "authors", "--coarse-to-fine"]) != 0
    assert "--coarse-to-fine" in capsys.readouterr().err


def test_few_photos_stop_after_a_hundred_passes_over_their_pixels():
    from neulf_core.train import TrainConfig
    from neulf_core.rules import FEW_PHOTOS_MAX_PASSES, default_coarse_to_fine, pass_step_limit

    # The synthetic scene's 4 views at 160x120, 8192-ray steps: 938 steps (its held-out views
    # fall from 28.60 dB at 1000 steps to 28.03 at 5000); its 14 views train on.
    assert pass_step_limit(TrainConfig(), "disparity", 4, 4 * 160 * 120, 8192) == 938 == math.ceil(
        FEW_PHOTOS_MAX_PASSES * 4 * 160 * 120 / 8192)
    assert pass_step_limit(TrainConfig(), "disparity", 14, 14 * 160 * 120, 8192) is None
    assert all((pass_step_limit(TrainConfig(), "disparity", n, 1000, 100) is not None) == default_coarse_to_fine(n)
               for n in range(2, 40))
    assert pass_step_limit(TrainConfig(), "mlp", 4, 1000, 100) is None                # measured on the fast field only
    assert pass_step_limit(TrainConfig(max_passes=0), "disparity", 4, 1000, 100) is None  # no limit
    assert pass_step_limit(TrainConfig(max_passes=2.5), "disparity", 40, 1000, 100) == 25  # asked for, any capture


def test_a_time_budget_ends_at_the_pass_limit_and_resume_can_lift_it(tiny_scene, tmp_path, capsys):
    from neulf_core.checkpoint import load_checkpoint
    from neulf_core.cli import main
    from neulf_core.train import TrainConfig, train
    from neulf_core.rules import pass_step_limit

    events = []
    quick = dict(batch_size=256, teacher=False, validate_seconds=1e9, checkpoint_seconds=1e9)
    result = train(tiny_scene, tmp_path / "m", TrainConfig(minutes=30.0, max_passes=0.5, **quick), progress=events.append)
    meta = load_checkpoint(tmp_path / "m")
    said = [e for e in events if e["event"] == "passes"]
    assert len(said) == 1 and result.status == "finished" and result.step == said[0]["steps"]
    assert result.elapsed < 60.0  # half a pass, not half an hour
    assert meta["progress"]["step"] == result.step and meta["train_config"]["max_passes"] == 0.5
    # The learning rate's schedule ran to its end at the limit, as it would at a step budget.
    assert meta["optimizer"]["param_groups"][0]["lr"] < 0.05 * meta["optimizer"]["param_groups"][0]["initial_lr"]
    # Asked to go on, a model at its limit ends at once and says why; with the limit lifted it trains on.
    more = []
    same = train(tiny_scene, tmp_path / "m", TrainConfig(minutes=30.0, **quick), resume=True, progress=more.append)
    assert same.step == result.step and same.status == "finished"
    assert any("already" in e["message"] and "--max-passes 0" in e["message"] for e in more if e["event"] == "passes")
    again = train(tiny_scene, tmp_path / "m", TrainConfig(steps=result.step + 4, max_passes=0, **quick), resume=True)
    assert again.step == result.step + 4

    # The default limit applies to few photos (the test scene's 8), and the CLI says so.
    args = ["train", str(tiny_scene), "--out", str(tmp_path / "cli"), "--steps", "100000", "--members", "1", "--batch-size", "4096",
            "--no-sweep-teacher", "--validate-seconds", "1e9", "--progress", "json"]
    assert main(args) == 0
    out = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    limit = next(e for e in out if e["event"] == "passes")
    assert "100 passes" in limit["message"] and out[-1]["event"] == "finished" and out[-1]["step"] == limit["steps"]
    assert main(args[:2] + ["--out", str(tmp_path / "bad"), "--max-passes", "-1"]) != 0
    assert "--max-passes" in capsys.readouterr().err


def test_linear_view_dependence_starts_view_independent_and_stays_affine_in_uv():
    """`view_dependence_linear`: the decoder reads the texture only and returns the colour's
    logit and its (u, v) slope, which starts at zero -- the same surface point has one colour
    from every viewpoint at the start (the (u, v)-input decoder's start gives it a random
    function of the viewpoint), and once trained its logit changes linearly between them."""
    options = {"texture_size": [16, 16], "texture_channels": 4, "hidden": 32}
    torch.manual_seed(0)
    linear = build_field("disparity", make_config("disparity", {**options, "view_dependence_linear": True}))
    torch.manual_seed(0)
    default = build_field("disparity", make_config("disparity", options))
    assert linear.decoder[0].in_features == 16 and linear.decoder[-1].out_features == 9
    assert default.decoder[0].in_features == 18 and default.decoder[-1].out_features == 3
    texture = torch.randn(1, 16).expand(5, 16)
    uv = torch.tensor([[-1.0, -1.0], [-0.5, 0.2], [0.0, 0.0], [0.5, -0.2], [1.0, 1.0]])
    with torch.no_grad():
        assert torch.allclose(linear._colour(texture, uv), linear._colour(texture, uv)[:1].expand(5, 3))
        default_colour = default._colour(torch.cat([texture, uv], dim=1), uv)
        assert float((default_colour - default_colour[:1]).abs().max()) > 1e-4
        linear.decoder[-1].weight[3:].normal_(0, 0.3)  # a trained slope
        logit = torch.logit(linear._colour(texture, uv).double())
    assert float((logit[0] - logit[-1]).abs().max()) > 1e-3
    assert torch.allclose(logit[2], (logit[0] + logit[-1]) / 2, atol=1e-5)
    assert torch.allclose(logit[1] + logit[3], 2 * logit[2], atol=1e-5)


def test_linear_view_dependence_decodes_the_same_in_render_sized_chunks():
    """A CPU render decodes in DECODE_ROWS pieces; the slope's (u, v) must stay with its rows."""
    from neulf_core.fields.disparity import DECODE_ROWS
    field = build_field("disparity", make_config("disparity", {"texture_size": [8, 8], "texture_channels": 4,
                                                               "hidden": 16, "view_dependence_linear": True}))
    with torch.no_grad():
        field.decoder[-1].weight[3:].normal_(0, 0.3)
        features, uv = torch.randn(DECODE_ROWS + 37, 16), torch.rand(DECODE_ROWS + 37, 2) * 2 - 1
        chunked = field._colour(features, uv)
        out = field.decoder(features)
        whole = torch.sigmoid(out[:, :3] + out[:, 3:6] * uv[:, :1] + out[:, 6:] * uv[:, 1:])
    assert torch.allclose(chunked, whole, atol=1e-6)


def test_fast_colour_decoder_starts_from_the_packaged_learned_start_for_every_seed():
    """The fast preset's colour decoder starts from neulf_core/fields/starts/<colour_start>.npz,
    not from the seed: a seed then only draws the texture's and geometry's small starts and
    the ray order (docs/STABILITY.md: the decoder's draw was most of the dense captures' seed
    spread).  The colour slopes start at zero, so the field starts view-independent."""
    from neulf_core.fields.disparity import colour_start_path
    from neulf_core.presets import FAST_FIELD

    start = np.load(colour_start_path(FAST_FIELD["colour_start"]))
    fields = []
    for seed in (0, 1):
        torch.manual_seed(seed)
        fields.append(build_field("disparity", make_config("disparity", {**FAST_FIELD, "texture_size": [16, 16]})))
    for name, value in fields[0].decoder.named_parameters():
        assert torch.equal(value, dict(fields[1].decoder.named_parameters())[name])
        assert np.array_equal(value.detach().numpy(), start[name]), name
    assert not fields[0].decoder[-1].weight[3:].any() and not fields[0].decoder[-1].bias[3:].any()
    assert not torch.equal(fields[0].textures[0], fields[1].textures[0])  # the seed still draws the texture


def test_a_decoder_of_another_shape_keeps_its_random_start_and_a_missing_start_says_so():
    from neulf_core.errors import NeulfError
    from neulf_core.presets import FAST_FIELD

    decoders = []
    for seed in (0, 1):
        torch.manual_seed(seed)
        options = {**FAST_FIELD, "texture_size": [16, 16], "hidden": 32}  # the start has 128 hidden units
        decoders.append(build_field("disparity", make_config("disparity", options)).decoder[0].weight)
    assert not torch.equal(*decoders)
    with pytest.raises(NeulfError, match="install it again"):
        build_field("disparity", make_config("disparity", {"texture_size": [16, 16], "colour_start": "no_such_start"}))


def test_fields_saved_before_the_learned_start_keep_the_random_one():
    """DisparityConfig's own default is no start: a model saved before reads as it was built."""
    torch.manual_seed(0)
    a = build_field("disparity", make_config("disparity", {"texture_size": [16, 16]})).decoder[0].weight
    torch.manual_seed(1)
    b = build_field("disparity", make_config("disparity", {"texture_size": [16, 16]})).decoder[0].weight
    assert not torch.equal(a, b)


def test_the_colour_start_script_keeps_the_decoder_with_its_slopes_zeroed(tiny_scene, tmp_path, monkeypatch):
    """scripts/learn_colour_start.py on the tiny scene: a start of the fast decoder's shape, its
    colour slopes zero, that a fast field then starts from; a second scene starts from the first's."""
    import importlib.util
    from pathlib import Path

    from neulf_core.fields import disparity
    from neulf_core.presets import FAST_FIELD

    script_path = Path(__file__).resolve().parents[1] / "scripts" / "learn_colour_start.py"
    spec = importlib.util.spec_from_file_location("learn_colour_start", script_path)
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    monkeypatch.setattr(disparity, "STARTS", tmp_path / "starts")
    out = script.learn([tiny_scene], "tiny_v1", steps=20, scale=1.0)
    start = np.load(out)
    assert start["0.weight"].shape == (128, 16) and start["2.weight"].shape == (9, 128)
    assert not start["2.weight"][3:].any() and not start["2.bias"][3:].any()
    assert json.loads(str(start["meta"]))["scenes"][0]["steps"] == 20
    field = build_field("disparity", make_config("disparity", {**FAST_FIELD, "texture_size": [16, 16], "colour_start": "tiny_v1"}))
    assert np.array_equal(field.decoder[0].weight.detach().numpy(), start["0.weight"])
    again = np.load(script.learn([tiny_scene, tiny_scene], "tiny_v2", steps=20, scale=1.0))
    assert json.loads(str(again["meta"]))["scenes"][1]["steps"] == 20
    assert not np.array_equal(again["0.weight"], start["0.weight"])  # the second scene trained on from the first's


def test_plane_smoothness_taken_in_groups_is_the_sum_over_planes():
    """PlanesField.regularisation stacks planes of one shape and weight: the same value and
    gradients as the total variation of each plane, weighted and summed."""
    from neulf_core.fields.planes import ANGULAR, PAIRS, total_variation

    torch.manual_seed(0)
    field = build_field("planes", make_config("planes", {"tv_weight_spatial": 2e-4}))
    for plane in field.parameters():
        plane.data.normal_()
    planes = list(field.scales.parameters())
    expected = sum((field.config.tv_weight if (a in ANGULAR or b in ANGULAR) else field.config.tv_weight_spatial)
                   * total_variation(plane) for scale in field.scales for plane, (a, b) in zip(scale, PAIRS))
    grouped = field.regularisation()
    assert torch.allclose(grouped, expected, rtol=1e-6)
    for mine, theirs in zip(torch.autograd.grad(grouped, planes), torch.autograd.grad(expected, planes)):
        assert torch.allclose(mine, theirs, rtol=1e-5, atol=1e-12)


def test_total_variation_gradient_is_autograds():
    """planes.total_variation writes its gradient out; it must be the one autograd derives."""
    from neulf_core.fields.planes import total_variation

    torch.manual_seed(1)
    planes = torch.randn(3, 2, 9, 17, dtype=torch.float64, requires_grad=True)
    by_hand = total_variation(planes)
    reference = ((planes[..., 1:, :] - planes[..., :-1, :]) ** 2).mean() + ((planes[..., :, 1:] - planes[..., :, :-1]) ** 2).mean()
    assert torch.allclose(by_hand, reference)
    assert torch.autograd.gradcheck(total_variation, (planes,))
    mine, = torch.autograd.grad(by_hand * 3.0, planes)
    theirs, = torch.autograd.grad(reference * 3.0, planes)
    assert torch.allclose(mine, theirs)


def test_training_says_what_the_rules_chose_for_the_field(tiny_scene, tmp_path, capsys):
    """The README says training prints each choice a rule made: the fast field's depth layers,
    coarse-to-fine ramp and back surface, and the sweep teacher, had been chosen without a word.
    What the user asked for is not repeated as a rule's choice."""
    from neulf_core.cli import main

    args = ["train", str(tiny_scene), "--steps", "2", "--batch-size", "256", "--validate-seconds", "1e9"]
    assert main(args + ["--out", str(tmp_path / "ruled")]) == 0
    ruled = [line for line in capsys.readouterr().err.splitlines() if line.startswith("by rule: ")]
    assert len(ruled) == 1 and all(part in ruled[0] for part in (
        "depth layers (--depth-layers)", "coarse-to-fine on", "back surface off", "plane sweep on")), ruled
    assert main(args + ["--out", str(tmp_path / "asked"), "--depth-layers", "4", "--no-sweep-teacher",
                        "--back-surface"]) == 0
    ruled = [line for line in capsys.readouterr().err.splitlines() if line.startswith("by rule: ")]
    assert ruled == ["by rule: coarse-to-fine on (--coarse-to-fine)"], ruled


@pytest.mark.parametrize("options", [{"back_surface": False}, {}, {"geometry_layers": 2}],
                         ids=["one surface", "back surface", "depth layers"])
def test_depth_alone_is_forward_s_depth_to_the_bit(options):
    """A depth-only query (a render's centre rays, a picked pixel) skips the texture reads and
    the colour decoder: its depth unit is forward's exactly, for one field and for members'
    mean (the render path's MemberMean), so depth maps stay what they were."""
    from neulf_core.fields import depth_unit
    from neulf_core.render import MemberMean

    torch.manual_seed(0)
    fields = [_back_surface_field(**options) for _ in range(2)]
    rays = torch.rand(300, 4) * 2 - 1
    with torch.no_grad():
        for field in fields:
            field.geometry.decoder[-1].weight.normal_()  # surfaces that differ from ray to ray
        for field in [fields[0], MemberMean(fields)]:
            assert torch.equal(depth_unit(field, rays), field(rays)[1])
        mlp = build_field("mlp", make_config("mlp", {"width": 16, "depth": 2}))
        assert torch.equal(depth_unit(mlp, rays), mlp(rays)[1])  # (no depth of its own: its forward's)

"""End-to-end checks of neulf_synth against real Cycles renders (no mocks).

Small rigs (2x2 views at 96x72, few samples) keep the module fast. The geometric checks
compare the rendered ground truth with independent analytic computations: plane depths
from the camera poses, a ray-sphere intersection, Blender's own projection matrix, and
cross-view consistency of depth and poses.
"""

from __future__ import annotations

import json
from pathlib import Path
import subprocess
import sys

import numpy as np
import pytest

bpy = pytest.importorskip("bpy", exc_type=ImportError, reason="bpy cannot load: see scripts/setup_env.sh for its system libraries")
pycolmap = pytest.importorskip("pycolmap")
from PIL import Image  # noqa: E402

from neulf_synth import generate_scene, layout  # noqa: E402
from neulf_synth.cameras import backproject, project  # noqa: E402

GRID = (2, 2)
SIZE = (96, 72)
SAMPLES = 8
REPO_ROOT = Path(__file__).resolve().parents[1]


def _render(out_dir: Path, **options) -> dict:
    """Generate a small scene and capture Blender state the tests compare against."""
    summary = generate_scene(out_dir, grid=GRID, size=SIZE, samples=SAMPLES, **options)
    scene = bpy.context.scene
    depsgraph = bpy.context.evaluated_depsgraph_get()
    width, height = SIZE
    # Blender's own projection matrices, to check K independently of the notes' formulas.
    projections = {
        name: np.array(bpy.data.objects[name].calc_matrix_camera(
            depsgraph, x=width, y=height, scale_x=scene.render.pixel_aspect_x,
            scale_y=scene.render.pixel_aspect_y))
        for name in (Path(p).stem for p in summary["images"])
    }
    sphere_matrix = np.array(bpy.data.objects["NearSphere"].matrix_world)
    return {"summary": summary, "out": Path(summary["out_dir"]), "projections": projections,
            "sphere_matrix": sphere_matrix}


@pytest.fixture(scope="module")
def lambertian(tmp_path_factory):
    return _render(tmp_path_factory.mktemp("lambertian"))


@pytest.fixture(scope="module")
def shiny(tmp_path_factory):
    return _render(tmp_path_factory.mktemp("shiny"), variant="shiny", write_gt_model=False)


@pytest.fixture(scope="module")
def jittered(tmp_path_factory):
    return _render(tmp_path_factory.mktemp("jittered"), exposure_jitter_stops=1.0,
                   write_gt_model=False)


def _cameras(run) -> list[dict]:
    return json.loads((run["out"] / "ground_truth" / "cameras.json").read_text())["views"]


def _scene(run) -> dict:
    return json.loads((run["out"] / "ground_truth" / "scene.json").read_text())


def _image(run, view) -> np.ndarray:
    return np.asarray(Image.open(run["out"] / "images" / view["name"]))


def _truth(run, kind: str, view) -> np.ndarray:
    return np.load(run["out"] / "ground_truth" / f"{kind}_{Path(view['name']).stem}.npy")


def _krt(view):
    return (np.array(view["K"]), np.array(view["R"]), np.array(view["t"]))


def _pass_index(run, name: str) -> int:
    return next(o["pass_index"] for o in _scene(run)["objects"] if o["name"] == name)


def _pixel_centres(width: int, height: int) -> np.ndarray:
    cols, rows = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    return np.column_stack([cols.ravel(), rows.ravel()])


def _plane_depth(view, point, normal) -> np.ndarray:
    """Optical-axis depth of a plane at every pixel centre, from K, R, t alone."""
    K, R, t = _krt(view)
    rays_camera = np.column_stack([_pixel_centres(view["width"], view["height"]),
                                   np.ones(view["width"] * view["height"])]) @ np.linalg.inv(K).T
    # Plane in camera coordinates: n_c . x = d_c; a ray x = z * r (r has unit z) hits at z.
    normal_camera = R @ np.asarray(normal)
    offset_camera = normal_camera @ (R @ np.asarray(point) + t)
    return (offset_camera / (rays_camera @ normal_camera)).reshape(view["height"], view["width"])


def _srgb_to_linear(values: np.ndarray) -> np.ndarray:
    s = values / 255.0
    return np.where(s <= 0.04045, s / 12.92, ((s + 0.055) / 1.055) ** 2.4)


# --- files and images -------------------------------------------------------------------

def test_writes_every_file_with_the_documented_layout(lambertian):
    out = lambertian["out"]
    views = _cameras(lambertian)
    names = sorted(f"view_{r:02d}_{c:02d}.png" for r in range(GRID[0]) for c in range(GRID[1]))
    assert sorted(v["name"] for v in views) == names
    for view in views:
        image = _image(lambertian, view)
        assert image.shape == (SIZE[1], SIZE[0], 3) and image.dtype == np.uint8
        assert image.std() > 20, "image looks flat"
        depth = _truth(lambertian, "depth", view)
        assert depth.shape == (SIZE[1], SIZE[0]) and depth.dtype == np.float32
        assert view["width"] == SIZE[0] and view["height"] == SIZE[1]
    assert (out / "sparse_gt" / "0" / "images.bin").exists()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["timings"]["render_total_s"] > 0
    assert len(summary["images"]) == len(views)


def test_images_are_well_exposed(lambertian):
    for view in _cameras(lambertian):
        image = _image(lambertian, view)
        assert 60 < image.mean() < 190
        assert (image == 255).mean() < 0.02 and (image == 0).mean() < 0.02


# --- depth --------------------------------------------------------------------------------

def test_depth_is_finite_and_within_the_scene_depth_range(lambertian):
    for view in _cameras(lambertian):
        depth = _truth(lambertian, "depth", view)
        assert np.isfinite(depth).all(), "the back wall should leave no background pixels"
        # Nearest object ~2.3 units away, back wall ~6.2: roughly 1:3.
        assert 1.8 < depth.min() < 3.0
        assert layout.WALL_Y - 0.5 < depth.max() < layout.WALL_Y + 1.0
        assert depth.max() / depth.min() > 2.4


@pytest.mark.parametrize("plane_name", ["BackWall", "Floor"])
def test_plane_depth_matches_the_analytic_depth_from_the_pose(lambertian, plane_name):
    # Checks together: depth is along the optical axis (ray length would be off by up to
    # 1/cos(20 deg) = 6%), K and the +0.5 pixel-centre convention (the floor's depth changes
    # by ~1% per pixel near the bottom), R and t, and the row order of the depth maps.
    plane = _scene(lambertian)["planes"][plane_name]
    index = _pass_index(lambertian, plane_name)
    for view in _cameras(lambertian):
        depth = _truth(lambertian, "depth", view)
        mask = _truth(lambertian, "object_index", view) == index
        assert mask.mean() > 0.1
        expected = _plane_depth(view, plane["point"], plane["normal"])
        relative = np.abs(depth[mask] - expected[mask]) / expected[mask]
        assert relative.max() < 1e-3, f"{view['name']}: {relative.max():.2e}"


def test_near_sphere_projects_where_its_front_surface_is_rendered(lambertian):
    sphere = next(o for o in _scene(lambertian)["objects"] if o["name"] == "NearSphere")
    matrix = lambertian["sphere_matrix"]
    np.testing.assert_allclose(matrix, sphere["matrix_world"], atol=1e-6)
    centre, radius = matrix[:3, 3], sphere["size"]["radius"]
    for view in _cameras(lambertian):
        K, R, t = _krt(view)
        pixel, _ = project(K, R, t, centre[None])
        col, row = np.floor(pixel[0]).astype(int)
        assert 0 <= col < view["width"] and 0 <= row < view["height"]
        assert _truth(lambertian, "object_index", view)[row, col] == sphere["pass_index"]
        # Exact hit of the ray through that pixel centre with the true sphere.
        ray = np.linalg.inv(K) @ [col + 0.5, row + 0.5, 1.0]  # unit z: length along it = depth
        centre_camera = R @ centre + t
        a, b, c = ray @ ray, -2 * ray @ centre_camera, centre_camera @ centre_camera - radius**2
        expected = (-b - np.sqrt(b * b - 4 * a * c)) / (2 * a)
        rendered = _truth(lambertian, "depth", view)[row, col]
        # Tolerance: the tessellated sphere deviates from the true one by < 1e-4 units.
        assert abs(rendered - expected) < 2e-3 * expected, (rendered, expected)


def test_depth_and_poses_agree_across_views(lambertian):
    # Back-project view 0's depth and re-project into the other views: where the surface is
    # visible in both, the other view's rendered depth must match.
    # The object index tells occluded points apart (another object is seen there instead).
    views = _cameras(lambertian)
    source = views[0]
    depth = _truth(lambertian, "depth", source)
    source_objects = _truth(lambertian, "object_index", source).ravel()
    pixels = _pixel_centres(source["width"], source["height"])
    points = backproject(*_krt(source), pixels, depth.ravel().astype(np.float64))
    for target in views[1:]:
        projected, z = project(*_krt(target), points)
        cols, rows = np.floor(projected).astype(int).T
        inside = (cols >= 0) & (cols < target["width"]) & (rows >= 0) & (rows < target["height"])
        rendered = _truth(lambertian, "depth", target)[rows[inside], cols[inside]]
        target_objects = _truth(lambertian, "object_index", target)[rows[inside], cols[inside]]
        visible = target_objects == source_objects[inside]
        assert visible.mean() > 0.75
        relative = np.abs(rendered - z[inside])[visible] / z[inside][visible]
        # Nearest-pixel lookup: the floor's depth changes ~2% per pixel at this resolution.
        assert np.median(relative) < 2e-3
        assert (relative < 3e-2).mean() > 0.98


# --- intrinsics, poses and the COLMAP model ------------------------------------------------

def test_intrinsics_match_blenders_projection_matrix(lambertian):
    width, height = SIZE
    for view in _cameras(lambertian):
        P = lambertian["projections"][Path(view["name"]).stem]
        K = np.array(view["K"])
        np.testing.assert_allclose(K[0, 0], P[0][0] * width / 2, rtol=1e-6)
        np.testing.assert_allclose(K[1, 1], P[1][1] * height / 2, rtol=1e-6)
        np.testing.assert_allclose(K[0, 2], width / 2 * (1 - P[0][2]), atol=1e-4)
        np.testing.assert_allclose(K[1, 2], height / 2 * (1 + P[1][2]), atol=1e-4)


def test_poses_are_rotations_with_slight_toe_in(lambertian):
    views = _cameras(lambertian)
    for view in views:
        R = np.array(view["R"])
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) > 0
    forwards = np.array([np.array(v["R"])[2] for v in views])  # optical axes in world
    centres = np.array([-np.array(v["R"]).T @ v["t"] for v in views])
    angles = np.degrees(np.arccos(np.clip(forwards @ forwards.T, -1, 1)))
    # Axes converge on the look-at point ~4 units away: a few degrees apart, ~10 at most.
    assert 0.5 < angles.max() < 12, "cameras should look the same way with slight toe-in"
    assert np.all(forwards[:, 1] > 0.97), "the rig looks along +Y (slightly down)"
    baseline = np.ptp(centres[:, 0])
    nearest = min(_truth(lambertian, "depth", view).min() for view in views)
    assert 0.15 < baseline / nearest < 0.3, "baseline ~15-25% of the nearest object's distance"


def test_gt_model_reads_back_with_identical_poses_and_camera(lambertian):
    reconstruction = pycolmap.Reconstruction(str(lambertian["out"] / "sparse_gt" / "0"))
    views = _cameras(lambertian)
    assert reconstruction.num_images() == len(views)
    assert reconstruction.num_points3D() > 100
    rng = np.random.default_rng(0)
    points_camera = np.column_stack([rng.uniform(-1, 1, (50, 2)), rng.uniform(2, 8, 50)])
    for view in views:
        image = reconstruction.find_image_with_name(view["name"])
        pose = image.cam_from_world()
        K, R, t = _krt(view)
        np.testing.assert_allclose(pose.rotation.matrix(), R, atol=1e-6)
        np.testing.assert_allclose(pose.translation, t, atol=1e-6)
        camera = reconstruction.cameras[image.camera_id]
        assert camera.model.name == "PINHOLE"
        assert (camera.width, camera.height) == (view["width"], view["height"])
        expected = (points_camera @ K.T)[:, :2] / points_camera[:, 2:]
        np.testing.assert_allclose(camera.img_from_cam(points_camera), expected, atol=1e-9)


def test_gt_model_points_lie_on_the_rendered_surfaces(lambertian):
    reconstruction = pycolmap.Reconstruction(str(lambertian["out"] / "sparse_gt" / "0"))
    points = np.array([p.xyz for p in reconstruction.points3D.values()])
    view = _cameras(lambertian)[-1]  # one of the views the points were sampled from
    projected, z = project(*_krt(view), points)
    cols, rows = np.floor(projected).astype(int).T
    inside = (cols >= 0) & (cols < view["width"]) & (rows >= 0) & (rows < view["height"])
    rendered = _truth(lambertian, "depth", view)[rows[inside], cols[inside]]
    assert np.median(np.abs(rendered - z[inside]) / z[inside]) < 2e-3


# --- variants and exposure ------------------------------------------------------------------

def test_shiny_variant_changes_appearance_but_not_geometry(lambertian, shiny):
    sphere = _pass_index(lambertian, "NearSphere")
    for plain_view, shiny_view in zip(_cameras(lambertian), _cameras(shiny)):
        np.testing.assert_allclose(shiny_view["R"], plain_view["R"])
        np.testing.assert_array_equal(_truth(shiny, "depth", shiny_view),
                                      _truth(lambertian, "depth", plain_view))
        difference = np.abs(_image(shiny, shiny_view).astype(float)
                            - _image(lambertian, plain_view).astype(float)).mean(axis=2)
        on_sphere = _truth(lambertian, "object_index", plain_view) == sphere
        assert difference[on_sphere].mean() > 20, "the mirror sphere should look different"


def test_exposure_jitter_scales_linear_brightness_as_recorded(lambertian, jittered):
    plain_views, jittered_views = _cameras(lambertian), _cameras(jittered)
    stops = np.array([v["exposure_stops"] for v in jittered_views])
    assert np.all(np.abs(stops) <= 1.0) and np.ptp(stops) > 0.2
    assert all(v["exposure_stops"] == 0.0 for v in plain_views)
    for plain_view, jittered_view, stop in zip(plain_views, jittered_views, stops):
        plain = _srgb_to_linear(_image(lambertian, plain_view).astype(float))
        brighter = _srgb_to_linear(_image(jittered, jittered_view).astype(float))
        usable = (plain > 0.02) & (plain < 0.9) & (brighter > 0.02) & (brighter < 0.9)
        ratio = np.median(brighter[usable] / plain[usable])
        np.testing.assert_allclose(ratio, 2.0 ** stop, rtol=0.03)


def test_rendering_is_deterministic(tmp_path):
    images = []
    for attempt in ("first", "second"):
        summary = generate_scene(tmp_path / attempt, grid=(1, 1), size=(48, 36), samples=4,
                                 write_gt_model=False)
        images.append(np.asarray(Image.open(summary["images"][0])))
    np.testing.assert_array_equal(images[0], images[1])


def test_cli_renders_and_reports_progress(tmp_path):
    result = subprocess.run(
        [sys.executable, "-m", "neulf_synth", str(tmp_path / "cli"), "--grid", "1x2",
         "--size", "48x36", "--samples", "2", "--variant", "fine", "--no-gt-model"],
        cwd=REPO_ROOT, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    progress = [line for line in result.stdout.splitlines() if line.startswith("[")]
    assert len(progress) == 2 and "view_00_01.png" in progress[1]
    assert (tmp_path / "cli" / "images" / "view_00_01.png").exists()
    assert not (tmp_path / "cli" / "sparse_gt").exists()


def test_rerun_into_the_same_folder_leaves_no_stale_views(tmp_path):
    generate_scene(tmp_path, grid=(1, 2), size=(32, 24), samples=1)
    generate_scene(tmp_path, grid=(1, 1), size=(32, 24), samples=1, write_gt_model=False)
    assert [p.name for p in (tmp_path / "images").iterdir()] == ["view_00_00.png"]
    assert not list((tmp_path / "sparse_gt" / "0").glob("*.bin"))
    views = json.loads((tmp_path / "ground_truth" / "cameras.json").read_text())["views"]
    assert [v["name"] for v in views] == ["view_00_00.png"]


# --- arrangements: scenes the defaults were not chosen on -----------------------------------

def test_an_arrangement_places_every_object_apart_on_the_floor_and_in_view(tmp_path):
    """`--arrangement N` (benchmarks/untuned_scene.py) draws the four objects' places, sizes and
    turns: the tuned layout is arrangement 0, unchanged; another number gives other places,
    the same for the same number, each object resting on the floor, its footprint apart from
    the others', and seen by the rig (its pass in the centre views' object index)."""
    tuned = {spec.name: spec.location for spec in layout.scene_objects()}
    assert tuned == {spec.name: spec.location for spec in layout.scene_objects(0)}
    for arrangement in (1, 2, 3):
        specs = layout.arranged_objects(arrangement)
        assert [s.location for s in specs] == [s.location for s in layout.arranged_objects(arrangement)]
        assert all(s.location != tuned[s.name] for s in specs)
        for spec in specs:
            bottom = {"sphere": spec.size.get("radius"), "cylinder": spec.size.get("depth", 0) / 2,
                      "cube": spec.size.get("size", 0) / 2}.get(spec.kind)
            if bottom is not None:
                assert abs(spec.location[2] - bottom) < 1e-9, spec  # resting on the floor
            assert layout.ARRANGED_DEPTHS[0] <= spec.location[1] <= layout.ARRANGED_DEPTHS[1]
        centres = np.array([s.location[:2] for s in specs])
        gaps = np.linalg.norm(centres[:, None] - centres[None], axis=2) + np.eye(len(specs)) * 9
        assert gaps.min() > 0.5, gaps
    summary = generate_scene(tmp_path / "arranged", grid=GRID, size=SIZE, samples=SAMPLES, arrangement=1)
    assert summary["arrangement"] == 1
    recorded = {o["name"]: np.array(o["matrix_world"])[:3, 3] for o in
                json.loads((tmp_path / "arranged" / "ground_truth" / "scene.json").read_text())["objects"]}
    for spec in layout.scene_objects(1):
        np.testing.assert_allclose(recorded[spec.name], spec.location, atol=1e-5)
    seen = set()
    for view in json.loads((tmp_path / "arranged" / "ground_truth" / "cameras.json").read_text())["views"]:
        seen |= set(np.unique(np.load(tmp_path / "arranged" / "ground_truth"
                                      / f"object_index_{Path(view['name']).stem}.npy")).astype(int))
    assert {3, 4, 5, 6} <= seen, seen

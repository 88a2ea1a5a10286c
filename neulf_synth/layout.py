"""Geometry of the synthetic test scene, in plain numbers (no bpy).

Blender world coordinates, Z up, scene units (metres). The cameras stand near the
origin and look along +Y at a small table-top arrangement in front of a back wall:

    y = 0      camera rig (a roughly planar grid, slight toe-in)
    y ~ 2.6    near object (sphere)           nearest surface ~2.3 units away
    y ~ 3.8    mid-depth object (Suzanne)
    y ~ 5.2    far objects (cylinder, cube)
    y = 6.2    textured back wall filling the background  (depth range ~1:2.8)

Keeping the layout here, separate from the Blender code, lets the tests and the
documentation reason about it without bpy.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math

import numpy as np

# One lens for every view: 50 mm on a 36 mm wide sensor, about 39.6 degrees horizontal FOV.
LENS_MM = 50.0
SENSOR_WIDTH_MM = 36.0

RIG_CENTER = np.array([0.0, 0.0, 0.95])
LOOK_AT = np.array([0.0, 4.2, 0.55])
# Total extent of the camera grid (width, height): about 25% of the nearest object's distance,
# the kind of baseline a careful handheld forward-facing capture has, and enough parallax for
# COLMAP's default initial-pair test (median triangulation angle) to pass.
RIG_EXTENT = (0.6, 0.45)
# Position jitter, as a fraction of the grid spacing, so the rig is not a perfect grid.
POSITION_JITTER = 0.12

WALL_Y = 6.2
FLOOR_Z = 0.0

VARIANTS = ("lambertian", "shiny", "fine")
# How much the `fine` variant raises every texture frequency.
FINE_TEXTURE_FACTOR = 6.0


@dataclass(frozen=True)
class ObjectSpec:
    """One scene object: what to build, where, and which material it wears."""

    name: str
    kind: str  # "quad", "sphere", "cylinder", "cube", "monkey"
    location: tuple[float, float, float]
    material: str
    rotation: tuple[float, float, float] = (0.0, 0.0, 0.0)  # XYZ Euler, radians
    size: dict = field(default_factory=dict)
    pass_index: int = 0  # Cycles object index, also written to the ground truth


def scene_objects(arrangement: int = 0) -> list[ObjectSpec]:
    """The objects of the scene, the same for every variant (only materials change).
    `arrangement` 0 is the layout drawn above; another number places, sizes and turns the four
    objects by a draw of its own (arranged_objects): a scene no default was tuned on."""
    if arrangement:
        return scene_objects()[:2] + arranged_objects(arrangement)
    return [
        # The wall faces the cameras (-Y); it is far wider and taller than any view sees.
        ObjectSpec("BackWall", "quad", (0.0, WALL_Y, 3.0), "wall",
                   rotation=(math.pi / 2, 0.0, 0.0), size={"width": 24.0, "height": 12.0},
                   pass_index=1),
        # The floor runs from behind the cameras to just behind the wall.
        ObjectSpec("Floor", "quad", (0.0, 2.0, FLOOR_Z), "floor",
                   size={"width": 24.0, "height": 8.6}, pass_index=2),
        ObjectSpec("NearSphere", "sphere", (0.45, 2.6, 0.33), "sphere",
                   size={"radius": 0.33}, pass_index=3),
        ObjectSpec("MidMonkey", "monkey", (-0.5, 3.8, 0.45), "monkey",
                   rotation=(0.0, 0.0, math.radians(-20.0)), size={"scale": 0.42},
                   pass_index=4),
        ObjectSpec("FarCylinder", "cylinder", (1.1, 5.0, 0.55), "cylinder",
                   size={"radius": 0.32, "depth": 1.1}, pass_index=5),
        ObjectSpec("FarCube", "cube", (-1.4, 5.35, 0.35), "cube",
                   rotation=(0.0, 0.0, math.radians(35.0)), size={"size": 0.7},
                   pass_index=6),
    ]


# Where arranged_objects may stand: the depth band of the objects above, and a share of the
# half-width the lens sees at each depth (HALF_FOV_TAN: tan of half the 39.6 degree view).
ARRANGED_DEPTHS = (2.6, 5.4)
ARRANGED_WIDTH_SHARE = 0.65
HALF_FOV_TAN = SENSOR_WIDTH_MM / 2.0 / LENS_MM
ARRANGED_SCALES = (0.75, 1.3)
ARRANGED_GAP = 0.12  # floor space kept between two objects' footprints


def arranged_objects(arrangement: int) -> list[ObjectSpec]:
    """The sphere, the monkey, the cylinder and the cube at places, sizes and turns drawn from
    `arrangement` (seeded): each resting on the floor, inside the view, their footprints apart,
    so the occlusions and the depth order are the draw's.  Used to check the defaults on a
    scene they were not chosen on (benchmarks/untuned_scene.py)."""
    rng = np.random.default_rng([arrangement, 11])
    placed: list[tuple[float, float, float]] = []  # (x, y, footprint radius)
    specs = []
    for name, kind, material, pass_index in (("NearSphere", "sphere", "sphere", 3), ("MidMonkey", "monkey", "monkey", 4),
                                             ("FarCylinder", "cylinder", "cylinder", 5), ("FarCube", "cube", "cube", 6)):
        scale = float(rng.uniform(*ARRANGED_SCALES))
        size, height, footprint = {
            "sphere": ({"radius": 0.33 * scale}, 0.33 * scale, 0.33 * scale),
            "monkey": ({"scale": 0.42 * scale}, 0.45 * scale, 0.55 * scale),
            "cylinder": ({"radius": 0.32 * scale, "depth": 1.1 * scale}, 0.55 * scale, 0.32 * scale),
            "cube": ({"size": 0.7 * scale}, 0.35 * scale, 0.5 * scale),
        }[kind]
        for _ in range(1000):  # rejection: a place whose footprint keeps clear of the others
            y = float(rng.uniform(*ARRANGED_DEPTHS))
            half_width = (y - RIG_CENTER[1]) * HALF_FOV_TAN * ARRANGED_WIDTH_SHARE
            x = float(rng.uniform(-half_width, half_width))
            if all(math.hypot(x - px, y - py) >= footprint + pr + ARRANGED_GAP for px, py, pr in placed):
                break
        else:
            raise ValueError(f"arrangement {arrangement}: no room found for {name}")
        placed.append((x, y, footprint))
        turn = float(rng.uniform(-math.pi, math.pi))
        specs.append(ObjectSpec(name, kind, (x, y, height), material, rotation=(0.0, 0.0, turn), size=size,
                                pass_index=pass_index))
    return specs


@dataclass(frozen=True)
class ViewSpec:
    """One camera of the rig: grid cell, position, and exposure offset in stops."""

    row: int
    col: int
    position: np.ndarray
    exposure_stops: float

    @property
    def name(self) -> str:
        return f"view_{self.row:02d}_{self.col:02d}"


def rig_axes() -> tuple[np.ndarray, np.ndarray]:
    """Right and up unit vectors of the rig plane, which faces the look-at point."""
    forward = LOOK_AT - RIG_CENTER
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    return right, up


def grid_offsets(count: int, extent: float) -> np.ndarray:
    """Evenly spaced offsets centred on 0 spanning `extent` (a single camera sits at 0)."""
    if count == 1:
        return np.zeros(1)
    return np.linspace(-extent / 2.0, extent / 2.0, count)


def camera_views(grid: tuple[int, int], seed: int, exposure_jitter_stops: float) -> list[ViewSpec]:
    """Cameras of a `rows x cols` rig; row 0 is the top row, column 0 the leftmost.

    Position jitter and exposure offsets come from independent seeded streams, so
    turning exposure jitter on does not move the cameras.
    """
    rows, cols = grid
    if rows < 1 or cols < 1:
        raise ValueError(f"grid must be at least 1x1, got {rows}x{cols}")
    right, up = rig_axes()
    xs = grid_offsets(cols, RIG_EXTENT[0])
    ys = grid_offsets(rows, RIG_EXTENT[1])[::-1]  # row 0 highest
    spacing = min(RIG_EXTENT[0] / max(cols - 1, 1), RIG_EXTENT[1] / max(rows - 1, 1))
    position_rng = np.random.default_rng([seed, 1])
    exposure_rng = np.random.default_rng([seed, 2])
    views = []
    for row in range(rows):
        for col in range(cols):
            jitter = position_rng.uniform(-1.0, 1.0, size=3) * POSITION_JITTER * spacing
            position = RIG_CENTER + xs[col] * right + ys[row] * up + jitter
            exposure = float(exposure_rng.uniform(-exposure_jitter_stops, exposure_jitter_stops)
                             if exposure_jitter_stops > 0 else 0.0)
            views.append(ViewSpec(row, col, position, exposure))
    return views

"""Scenes: registered photos with their cameras, read from COLMAP models or LLFF pose files.

Everything downstream works in the COLMAP world frame with COLMAP's camera convention
(x right, y down, z forward, world-to-camera poses, pixel centres at +0.5).  Each view
carries its own `pycolmap.Camera`, rescaled to the size of its image file on disk, so
ray directions always come from the camera model's own unprojection (distortion
included).
"""

from __future__ import annotations

import copy
import hashlib
import shlex
import struct
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import pycolmap

from .errors import NeulfError
from .images import LARGEST_IMAGE_SIDE, image_size, list_images, load_rgb_sizes, resolve_image_paths

MODEL_FILES = ("cameras.bin", "cameras.txt")
# Every file of a COLMAP model pycolmap may open (4.x adds rigs and frames to the legacy three).
MODEL_PARTS = ("rigs", "cameras", "frames", "images", "points3D")


@dataclass
class View:
    """One registered photo."""

    name: str                  # the image name as the model stores it
    camera: pycolmap.Camera    # intrinsics at the size of `image_path`
    R: np.ndarray              # (3, 3) world-to-camera rotation
    t: np.ndarray              # (3,) world-to-camera translation
    image_path: Path | None = None
    # The photo's keypoints that the model triangulated, at the size of `camera` (K, 2; pixel
    # (0, 0)'s centre at 0.5, 0.5, as COLMAP's), and the id of each one's 3D point (K,): the
    # observations point_depth.py triangulates again from the training photos alone.  None
    # where the model keeps no tracks (LLFF poses, a model written without 2D points).
    keypoints: np.ndarray | None = None
    point_ids: np.ndarray | None = None

    @property
    def center(self) -> np.ndarray:
        return -self.R.T @ self.t

    @property
    def forward(self) -> np.ndarray:
        """Viewing direction (camera +z) in world coordinates."""
        return self.R[2].copy()

    @property
    def size(self) -> tuple[int, int]:
        return int(self.camera.width), int(self.camera.height)

    @property
    def stem(self) -> str:
        return Path(self.name).stem

    def scaled_camera(self, scale: float) -> pycolmap.Camera:
        """This view's camera for images resized by `scale` (rounded to whole pixels)."""
        camera = copy.copy(self.camera)
        width, height = scaled_size(self.size, scale)
        camera.rescale(width, height)
        return camera

    def load_image(self, scale: float = 1.0) -> np.ndarray:
        return self.load_images([scale])[0]

    def load_images(self, scales) -> list[np.ndarray]:
        """The photo at each of `scales`, decoded once."""
        if self.image_path is None:
            raise NeulfError(f"view {self.name} has no image file; pass --images with the folder that holds it.")
        return load_rgb_sizes(self.image_path, [scaled_size(self.size, scale) for scale in scales])


@dataclass
class Scene:
    root: Path
    views: list[View]                       # sorted by name
    points: np.ndarray                      # (N, 3) sparse 3D points, world frame (may be empty)
    kind: str                               # "colmap" or "llff"
    depth_bounds: np.ndarray | None = None  # (V, 2) near/far per view (LLFF only)
    notes: list[str] = field(default_factory=list)  # what loading had to adapt, for the user
    images_dir: Path | None = None          # the folder the photos were read from

    def images_record(self) -> str | None:
        """The photos' folder as a model records it: relative to the scene folder where it lies
        inside it (LLFF's images_8/ and images_16/ hold the same views at other sizes), so the
        scene folder can move."""
        if self.images_dir is None:
            return None
        try:
            return Path(self.images_dir).absolute().relative_to(Path(self.root).absolute()).as_posix()
        except ValueError:
            return str(Path(self.images_dir).absolute())

    def view(self, name: str) -> View:
        for view in self.views:
            if name in (view.name, view.stem, Path(view.name).name):
                return view
        known = ", ".join(v.name for v in self.views[:5])
        raise NeulfError(f"the scene has no view named '{name}' (it has {len(self.views)} views: {known}, ...).")

    def fingerprint(self) -> str:
        """Identifies the capture (view names and poses), so a checkpoint finds its scene."""
        digest = hashlib.sha256()
        for view in self.views:
            digest.update(view.name.encode())
            digest.update(np.round(view.center, 4).astype(np.float64).tobytes())
        return digest.hexdigest()[:16]


def scaled_size(size: tuple[int, int], scale: float) -> tuple[int, int]:
    check_scale(scale)
    if max(size) * float(scale) > LARGEST_IMAGE_SIDE:
        raise NeulfError(f"--scale {scale:g} makes the {size[0]}x{size[1]} photos {size[0] * float(scale):.4g}x"
                         f"{size[1] * float(scale):.4g} pixels, past the largest image side of {LARGEST_IMAGE_SIDE}; "
                         "give a smaller --scale.")
    return max(1, int(round(size[0] * scale))), max(1, int(round(size[1] * scale)))


def check_scale(scale) -> float:
    """`scale` as a float; a NeulfError where it is not a finite positive number (NaN or
    infinity would fail far downstream, in int(), with Python's own message)."""
    try:
        value = float(scale)
    except (TypeError, ValueError):
        raise NeulfError(f"the image scale must be a number, not {scale!r}; give e.g. --scale 0.5.") from None
    if not np.isfinite(value) or value <= 0:
        raise NeulfError(f"the image scale must be a finite number above 0, not {scale}; give e.g. --scale 0.5.")
    return value


# ----------------------------------------------------------------------------- finding the model


def camera_spacing(centres: np.ndarray) -> float:
    """The rig's camera spacing: the median distance from a camera to its nearest neighbour
    (1.0 for a single camera); the unit pose corrections and pose noise are measured in.
    Photos taken twice from one place (a burst, a duplicated frame) are not each other's
    neighbours; all from one place (a tripod panorama): 1.0, as for one camera.  (A spacing of 0
    had ended training in an SVD traceback.)"""
    centres = np.asarray(centres, dtype=np.float64)
    if len(centres) < 2:
        return 1.0
    extent = float(np.ptp(centres, axis=0).max())
    if extent <= 0:
        return 1.0
    gaps = camera_gaps(centres)
    nearest = np.where(gaps > 1e-6 * extent, gaps, np.inf).min(axis=1)  # (a twin at the same place: not counted)
    return float(np.median(nearest[np.isfinite(nearest)]))


def camera_gaps(centres: np.ndarray) -> np.ndarray:
    """(V, V) distances between camera centres, infinite on the diagonal: a camera is not its
    own neighbour (nearest cameras: argmin / min along axis 1)."""
    centres = np.asarray(centres, dtype=np.float64)
    gaps = np.linalg.norm(centres[:, None] - centres[None], axis=-1)
    np.fill_diagonal(gaps, np.inf)
    return gaps


def find_model_dir(scene_dir: Path) -> Path | None:
    """The folder holding the COLMAP model: sparse/0, sparse, or the folder itself."""
    for candidate in (scene_dir / "sparse" / "0", scene_dir / "sparse", scene_dir):
        if any((candidate / name).is_file() for name in MODEL_FILES):
            return candidate
    sparse = scene_dir / "sparse"
    if sparse.is_dir():  # sparse/1, sparse/2 ... when the mapper split the capture
        for candidate in sorted(p for p in sparse.iterdir() if p.is_dir()):
            if any((candidate / name).is_file() for name in MODEL_FILES):
                return candidate
    return None


def find_images_dir(scene_dir: Path) -> Path | None:
    """`images/` if present, else the full-resolution-most `images_N/` (smallest N)."""
    if (scene_dir / "images").is_dir():
        return scene_dir / "images"
    scaled = []
    for path in scene_dir.glob("images_*"):
        suffix = path.name[len("images_"):]
        if path.is_dir() and suffix.isdigit():
            scaled.append((int(suffix), path))
    return min(scaled)[1] if scaled else None


def select_views(scene: Scene, names: list[str], held_out: list[str]) -> list[View]:
    """The views `names` asks for, each once, in the order first named: a view's name or stem,
    "held-out" (the model's held-out views) or "all" (every view), mixed as the user likes."""
    chosen: dict[str, View] = {}
    for name in names:
        if name == "held-out":
            if not held_out:
                raise NeulfError("the model was trained without held-out views (--holdout-every 0); name views "
                                 "with --views.")
            views = [scene.view(n) for n in held_out]
        elif name == "all":
            views = list(scene.views)
        else:
            views = [scene.view(name)]
        for view in views:
            chosen.setdefault(view.name, view)
    return list(chosen.values())


def load_scene(scene_dir: str | Path, images_dir: str | Path | None = None) -> Scene:
    """Read a scene folder: a COLMAP model (sparse/0 or sparse/) or an LLFF poses_bounds.npy."""
    scene_dir = Path(scene_dir).expanduser()
    if not scene_dir.exists():
        raise NeulfError(f"scene folder {scene_dir} does not exist: check the path (a capture moved or renamed since "
                         "it was imported: import it again from where it is now).")
    if not scene_dir.is_dir():
        raise NeulfError(f"{scene_dir} is not a folder; give the scene folder that holds sparse/0 and images/.")
    if images_dir is not None:
        images_dir = Path(images_dir).expanduser()
        if images_dir.exists() and not images_dir.is_dir():
            raise NeulfError(f"{images_dir} is a file, not a folder: give --images the folder that holds the photos.")
        if not images_dir.is_dir():
            raise NeulfError(f"images folder {images_dir} does not exist.")
    else:
        images_dir = find_images_dir(scene_dir)

    model_dir = find_model_dir(scene_dir)
    if model_dir is not None:
        return replace(_load_colmap(scene_dir, model_dir, images_dir), images_dir=images_dir)
    if (scene_dir / "poses_bounds.npy").is_file():
        return replace(_load_llff(scene_dir, images_dir), images_dir=images_dir)
    if find_model_dir(scene_dir.parent) is not None and scene_dir.name == "sparse":
        raise NeulfError(f"{scene_dir} is the COLMAP model's folder: give the scene folder above it, "
                         f"{scene_dir.parent} (the one holding sparse/ and images/).")
    raise NeulfError(
        f"no camera model in {scene_dir}: expected sparse/0/cameras.bin (or .txt) from COLMAP, "
        f"or poses_bounds.npy from LLFF. To make one from photos run: python -m neulf_core reconstruct PHOTOS --out {shlex.quote(str(scene_dir))}"
    )


def _read_reconstruction(model_dir: Path) -> pycolmap.Reconstruction:
    missing = [n for n in ("cameras", "images") if not any((model_dir / f"{n}.{e}").is_file() for e in ("bin", "txt"))]
    if missing:
        raise NeulfError(f"COLMAP model in {model_dir} is incomplete: {' and '.join(missing)} file missing.")
    _require_readable(model_dir)
    _check_binary_files(model_dir)
    _check_text_rotations(model_dir)
    try:
        return pycolmap.Reconstruction(str(model_dir))
    except Exception as exc:  # pycolmap raises plain RuntimeError/ValueError with C++ messages
        detail = str(exc).strip().splitlines()[-1] if str(exc).strip() else type(exc).__name__
        raise NeulfError(
            f"cannot read the COLMAP model in {model_dir} ({detail}): the files may be truncated or corrupted; "
            "export the model again from COLMAP or rerun reconstruct."
        ) from None


def _require_readable(model_dir: Path) -> None:
    """Refuse a model file the user may not read: pycolmap's 'could not open' reads as a
    damaged model, and exporting again would not help."""
    for path in (model_dir / f"{part}.{ext}" for part in MODEL_PARTS for ext in ("bin", "txt")):
        if not path.is_file():
            continue
        try:
            with open(path, "rb"):
                pass
        except PermissionError:
            raise NeulfError(
                f"cannot read {path}: permission denied (the model's files are not damaged, only not readable by "
                f"you); make them readable, e.g. chmod u+r {shlex.quote(str(path))}, or run as their owner."
            ) from None


# ----------------------------------------------------------------------------- truncated COLMAP files
# COLMAP's binary reader trusts every count it reads and goes on past the end of a short
# file: a truncated cameras.bin loads with zero focal lengths, a truncated images.bin can
# loop for ever, a truncated points3D.bin allocates until memory runs out (16 GB and four
# minutes on a 3 kB file), a truncated frames.bin or an absurd count in it spins for a
# minute or two.  So the record layout is walked first -- counts and lengths only, and the
# rotations, nothing else is decoded -- and a file whose records do not fill it exactly is
# refused.  (Layouts: COLMAP's src/colmap/scene/reconstruction_io_binary.cc.)


class _Truncated(Exception):
    pass


class _ZeroRotation(Exception):
    """A record's rotation quaternion has no direction (zero, NaN or infinite): pycolmap would
    normalise a zero one to the identity rotation and the camera would silently look along +z."""

    def __init__(self, record: str, norm: float):
        super().__init__(record)
        self.record, self.norm = record, norm


class _Records:
    def __init__(self, data: bytes):
        self.data, self.at = data, 0

    def skip(self, size: int) -> None:
        self.at += size
        if self.at > len(self.data):
            raise _Truncated

    def u64(self) -> int:
        self.skip(8)
        return struct.unpack_from("<Q", self.data, self.at - 8)[0]

    def i32(self) -> int:
        self.skip(4)
        return struct.unpack_from("<i", self.data, self.at - 4)[0]

    def u32(self) -> int:
        self.skip(4)
        return struct.unpack_from("<I", self.data, self.at - 4)[0]

    def u8(self) -> int:
        self.skip(1)
        return self.data[self.at - 1]

    def rotation(self, record: str) -> None:
        """Read a pose's quaternion (w, x, y, z doubles) and refuse one with no direction."""
        self.skip(32)
        norm = float(np.linalg.norm(struct.unpack_from("<4d", self.data, self.at - 32)))
        if not (np.isfinite(norm) and norm > 1e-6):
            raise _ZeroRotation(record, norm)

    def string(self) -> None:
        end = self.data.find(b"\0", self.at)
        if end < 0:
            raise _Truncated
        self.at = end + 1


def _param_count(model_id: int) -> int:
    try:
        return len(pycolmap.Camera.create_from_model_id(0, pycolmap.CameraModelId(model_id), 1.0, 1, 1).params)
    except (ValueError, TypeError):  # not a camera model: the bytes are not what COLMAP wrote
        raise _Truncated from None


def _walk_cameras(records: _Records) -> None:
    for _ in range(records.u64()):
        records.skip(4)                       # camera_id
        model_id = records.i32()
        records.skip(16 + 8 * _param_count(model_id))  # width, height, params


def _walk_images(records: _Records) -> None:
    for _ in range(records.u64()):
        image_id = records.u32()
        records.rotation(f"image {image_id}")  # qvec
        records.skip(24 + 4)                  # tvec, camera_id
        records.string()                      # name
        records.skip(24 * records.u64())      # points2D: x, y, point3D_id


def _walk_points(records: _Records) -> None:
    for _ in range(records.u64()):
        records.skip(8 + 24 + 3 + 8)          # point3D_id, xyz, rgb, error
        records.skip(8 * records.u64())       # track: image_id, point2D_idx


def _walk_rigs(records: _Records) -> None:
    """COLMAP 4.x: each rig's reference sensor, then its other sensors with optional poses."""
    for _ in range(records.u64()):
        rig_id = records.u32()
        sensors = records.u32()
        if sensors > 0:
            records.skip(8)                   # reference sensor: type, id
        for _ in range(max(sensors - 1, 0)):
            records.skip(8)                   # sensor: type, id
            if records.u8():                  # has sensor_from_rig
                records.rotation(f"a sensor of rig {rig_id}")
                records.skip(24)              # translation


def _walk_frames(records: _Records) -> None:
    """COLMAP 4.x: each frame's rig_from_world pose and the data (images) it holds."""
    for _ in range(records.u64()):
        frame_id = records.u32()
        records.skip(4)                       # rig_id
        records.rotation(f"frame {frame_id}")
        records.skip(24)                      # translation
        records.skip(16 * records.u32())      # data ids: sensor type, sensor id, data id


BINARY_LAYOUTS = {"rigs.bin": _walk_rigs, "cameras.bin": _walk_cameras, "frames.bin": _walk_frames,
                  "images.bin": _walk_images, "points3D.bin": _walk_points}


def _check_binary_files(model_dir: Path) -> None:
    for name, walk in BINARY_LAYOUTS.items():
        path = model_dir / name
        if not path.is_file():
            continue
        records = _Records(path.read_bytes())
        try:
            walk(records)
            complete = records.at == len(records.data)
        except _Truncated:
            complete = False
        except _ZeroRotation as bad:
            raise NeulfError(
                f"cannot read the COLMAP model in {model_dir}: {name} gives {bad.record} a rotation quaternion of "
                f"length {bad.norm:g} (COLMAP writes unit quaternions, so the file is corrupted); "
                "export the model again from COLMAP or rerun reconstruct."
            ) from None
        if not complete:
            raise NeulfError(
                f"cannot read the COLMAP model in {model_dir}: {name} is truncated or corrupted (its records do not "
                "fill the file); "
                "export the model again from COLMAP or rerun reconstruct."
            )


def _text_rotations(path: Path, first_column: int, lines_per_record: int):
    """(record id, quaternion norm) of each record of a COLMAP text file whose rotation (w, x,
    y, z) starts at `first_column`; records as COLMAP's reader takes them: a record's first
    line is the next that is neither empty nor a comment, and images.txt's second line (its
    points, maybe empty) follows it whatever it holds.  Lines that are not numbers are left
    for pycolmap to refuse."""
    lines = iter(path.read_text(errors="replace").splitlines())
    for line in lines:
        fields = line.split()
        if not fields or fields[0].startswith("#"):
            continue
        for _ in range(lines_per_record - 1):
            next(lines, None)
        try:
            yield fields[0], float(np.linalg.norm([float(v) for v in fields[first_column:first_column + 4]]))
        except (ValueError, IndexError):
            continue


# The rotations of a text model: images.txt (legacy, and beside frames.txt in COLMAP 4.x) and
# frames.txt -- file, column of QW, lines per record, what a record is.
TEXT_ROTATIONS = (("images.txt", 1, 2, "image"), ("frames.txt", 2, 1, "frame"))


def _check_text_rotations(model_dir: Path) -> None:
    """A text model's rotation quaternion of no direction (zero, NaN or infinite) is refused,
    as a binary one's is: pycolmap takes a zero one for the identity without a word."""
    for name, column, lines_per_record, what in TEXT_ROTATIONS:
        path = model_dir / name
        if not path.is_file() or all((model_dir / f"{part}.bin").is_file() for part in ("cameras", "images", "points3D")):
            continue  # (COLMAP reads the binary model where its three files are there)
        for record, norm in _text_rotations(path, column, lines_per_record):
            if not (np.isfinite(norm) and norm > 1e-6):
                raise NeulfError(
                    f"cannot read the COLMAP model in {model_dir}: {name} gives {what} {record} a rotation quaternion "
                    f"of length {norm:g} (COLMAP writes unit quaternions, so the file is damaged); export the model "
                    "again from COLMAP or rerun reconstruct.")


def _load_colmap(scene_dir: Path, model_dir: Path, images_dir: Path | None) -> Scene:
    recon = _read_reconstruction(model_dir)
    registered = sorted((im for im in recon.images.values() if im.has_pose), key=lambda im: im.name)
    if not registered:
        raise NeulfError(f"the COLMAP model in {model_dir} has no registered images.")
    _refuse_duplicate_names(registered, model_dir)
    if images_dir is None:
        raise NeulfError(f"no images folder next to the model in {scene_dir}; pass --images DIR.")
    paths = resolve_image_paths(images_dir, [im.name for im in registered])
    _require_all_images(paths, images_dir)

    notes: list[str] = []
    views = []
    for image in registered:
        _check_colmap_camera(recon.cameras[image.camera_id], image.name, model_dir)
        camera = copy.copy(recon.cameras[image.camera_id])  # views may be rescaled one by one
        path = paths[image.name]
        _fit_camera_to_file(camera, path, notes)
        pose = image.cam_from_world()
        matrix = np.asarray(pose.matrix(), dtype=np.float64)
        if not np.all(np.isfinite(matrix)):
            raise NeulfError(
                f"the COLMAP model in {model_dir} gives image {image.name} a pose that is not finite (NaN or "
                "infinity in its rotation or translation); export the model again from COLMAP or rerun reconstruct."
            )
        keypoints, point_ids = _triangulated_keypoints(image, recon.cameras[image.camera_id], camera)
        views.append(View(image.name, camera, matrix[:, :3].copy(), matrix[:, 3].copy(), path, keypoints, point_ids))
    _check_camera_centres(views, f"the COLMAP model in {model_dir}", "export the model again from COLMAP or rerun "
                          "reconstruct, or remove that image from the model")
    points = np.array([p.xyz for p in recon.points3D.values()], dtype=np.float64).reshape(-1, 3)
    return Scene(scene_dir, views, points, "colmap", notes=_dedupe(notes))


def _refuse_duplicate_names(registered: list, model_dir: Path) -> None:
    """Two images of one name would both read the one photo, each with its own pose."""
    first_id: dict[str, int] = {}
    for image in registered:
        if image.name in first_id:
            ids = sorted((first_id[image.name], image.image_id))
            raise NeulfError(
                f"the COLMAP model in {model_dir} names two images {image.name} (ids {ids[0]} and {ids[1]}): both "
                "would read one photo with two poses; export the model again from COLMAP or rerun reconstruct."
            )
        first_id[image.name] = image.image_id


# A camera further than this many times the rig's median spread from its median centre is a
# damaged pose (a digit lost or added in a translation), not a photo of the scene: real captures
# span a few spreads.  Measured from the median, not the origin, so that georeferenced models
# (cameras 1e7 units from the origin, tests/test_far_origin.py) stay welcome.
FARTHEST_CAMERA_SPREADS = 1e6


def _check_camera_centres(views: list[View], source: str, remedy: str) -> None:
    """Refuse a camera centre that float32 (the training's precision) cannot hold, or that lies
    absurdly far from the other cameras: training would run on NaN rays and write NaN scores.
    `source` names where the poses came from, `remedy` what to do."""
    centres = np.array([view.center for view in views])
    with np.errstate(over="ignore"):  # (1e300 in float32, or squared: infinite, far indeed)
        representable = np.all(np.isfinite(centres.astype(np.float32)), axis=1)
        median = np.median(centres[representable], axis=0) if representable.any() else np.zeros(3)
        distances = np.linalg.norm(centres - median, axis=1)
    spread = float(np.median(distances))
    too_far = ~representable
    if spread > 0:  # (cameras all at one point, a panorama's, have no spread to measure by)
        too_far |= distances > FARTHEST_CAMERA_SPREADS * spread
    if not too_far.any():
        return
    view = views[int(np.argmax(np.where(too_far, distances, -1.0)))]
    shown = ", ".join(f"{v:.3g}" for v in view.center)
    raise NeulfError(
        f"{source} puts image {view.name}'s camera at ({shown}), absurdly far from the other cameras (median "
        f"spread {spread:.3g}): its pose is damaged; {remedy}."
    )



def _check_colmap_camera(camera: pycolmap.Camera, image_name: str, model_dir: Path) -> None:
    """Refuse a camera whose size or intrinsics are unusable (NaN, infinite, not positive).  A side
    past LARGEST_IMAGE_SIDE is a damaged size (a 400 MP sensor is about 23000 pixels a side) --
    often a negative one that pycolmap reads as an unsigned 2**64 - n."""
    if not (1 <= camera.width <= LARGEST_IMAGE_SIDE and 1 <= camera.height <= LARGEST_IMAGE_SIDE):
        raise NeulfError(
            f"the COLMAP model in {model_dir} gives image {image_name} a damaged camera {camera.camera_id}: its size "
            f"{_signed(camera.width)}x{_signed(camera.height)} is not a photo's (1 to {LARGEST_IMAGE_SIDE} pixels "
            "a side); export the model again from COLMAP or rerun reconstruct."
        )
    params = np.asarray(camera.params, dtype=np.float64)
    focal = params[list(camera.focal_length_idxs())]
    if not np.all(np.isfinite(params)) or not np.all(focal > 0):  # (the size was checked above)
        shown = ", ".join(f"{v:g}" for v in params)
        raise NeulfError(
            f"the COLMAP model in {model_dir} gives image {image_name} an unusable camera {camera.camera_id} "
            f"({camera.model_name}, {camera.width}x{camera.height}, params {shown}): the size and focal length must be "
            "positive and every parameter finite; export the model again from COLMAP or rerun reconstruct."
        )


def _signed(size: int) -> int:
    """A camera size as written: COLMAP stores sizes unsigned, so -48 reads back as 2**64 - 48."""
    return size - 2 ** 64 if size >= 2 ** 63 else size


def _triangulated_keypoints(image, model_camera: pycolmap.Camera, camera: pycolmap.Camera):
    """(keypoints at `camera`'s size, their 3D points' ids) of the observations the model
    triangulated; (None, None) where it has none."""
    observed = [(p.xy, p.point3D_id) for p in image.points2D if p.has_point3D()]
    if not observed:
        return None, None
    keypoints = np.array([xy for xy, _ in observed], dtype=np.float64).reshape(-1, 2)
    keypoints *= np.array([camera.width / model_camera.width, camera.height / model_camera.height])
    return keypoints, np.array([pid for _, pid in observed], dtype=np.int64)


def _require_all_images(paths: dict[str, Path | None], images_dir: Path) -> None:
    missing = [name for name, path in paths.items() if path is None]
    if not missing:
        return
    shown = ", ".join(missing[:3]) + (" ..." if len(missing) > 3 else "")
    renamed = " (photos renamed since the reconstruction? give them the model's names again)" if len(missing) == len(
        paths) and len(list_images(images_dir)) == len(paths) else ""
    raise NeulfError(
        f"{len(missing)} of {len(paths)} images the model names are not in {images_dir} ({shown}){renamed}; "
        "put them there or pass --images with the folder that holds them."
    )


def _fit_camera_to_file(camera: pycolmap.Camera, path: Path, notes: list[str]) -> None:
    """Rescale intrinsics when the file is a resized copy of what the model calibrated."""
    width, height = image_size(path)
    if (width, height) == (camera.width, camera.height):
        return
    model_aspect = camera.width / camera.height
    if abs(width / height - model_aspect) > 0.01 * model_aspect:
        raise NeulfError(
            f"image {path.name} is {width}x{height} but the model's camera is {camera.width}x{camera.height} "
            "(another aspect ratio): the photo was cropped or rotated, or belongs to another model."
        )
    notes.append(f"intrinsics scaled from {camera.width}x{camera.height} to the image files' {width}x{height}")
    camera.rescale(width, height)


def _dedupe(items: list[str]) -> list[str]:
    return list(dict.fromkeys(items))


# ----------------------------------------------------------------------------- LLFF


def _load_llff(scene_dir: Path, images_dir: Path | None) -> Scene:
    """LLFF's poses_bounds.npy: per view a 3x5 [down, right, backwards, centre, (h, w, f)]
    camera-to-world matrix, then near and far depth."""
    poses, bounds, bounds_notes = _read_poses_bounds(scene_dir / "poses_bounds.npy")
    if images_dir is None:
        raise NeulfError(f"no images folder in {scene_dir}; pass --images DIR.")
    files = list_images(images_dir)
    if len(files) != len(poses):
        raise NeulfError(
            f"{images_dir} holds {len(files)} images but poses_bounds.npy has {len(poses)} poses; "
            "LLFF pairs them in sorted order, so the counts must match."
        )
    views = []
    notes: list[str] = list(bounds_notes)
    for pose, path in zip(poses, files):
        height, width, focal = pose[:, 4]
        camera = pycolmap.Camera(
            model="PINHOLE", width=int(round(width)), height=int(round(height)),
            params=[focal, focal, width / 2.0, height / 2.0],
        )
        _fit_camera_to_file(camera, path, notes)
        down, right, backwards, centre = pose[:, 0], pose[:, 1], pose[:, 2], pose[:, 3]
        cam_to_world = np.stack([right, down, -backwards], axis=1)  # columns: COLMAP x, y, z
        R = cam_to_world.T
        views.append(View(path.name, camera, R, -R @ centre, path))
    order = np.argsort([v.name for v in views])
    views = [views[i] for i in order]
    _check_camera_centres(views, f"{scene_dir / 'poses_bounds.npy'}", "regenerate poses_bounds.npy (LLFF's imgs2poses)")
    return Scene(scene_dir, views, np.zeros((0, 3)), "llff", depth_bounds=None if bounds is None else bounds[order],
                 notes=_dedupe(notes))


def _read_poses_bounds(path: Path) -> tuple[np.ndarray, np.ndarray | None, list[str]]:
    """((N, 3, 5) poses, (N, 2) near/far or None, notes) from poses_bounds.npy, every row
    checked: a NaN or a zero in a pose fails far downstream (in int(), in an index) without
    saying where, so it is refused, naming the row.  A row's near/far that is not usable
    only narrows what the scene's depth range is read from: it becomes NaN, and a note says so
    (None where no row has usable ones)."""
    try:
        data = np.load(path, allow_pickle=False)
    except Exception as exc:
        detail = str(exc).strip().splitlines()[-1] if str(exc).strip() else type(exc).__name__
        raise NeulfError(f"cannot read {path} ({detail}); it should be LLFF's (N, 17) array of numbers.") from None
    if data.dtype.kind not in "fiu" or data.ndim != 2 or data.shape[1] not in (15, 17) or len(data) == 0:
        raise NeulfError(
            f"{path} holds a {data.dtype} array of shape {data.shape}; LLFF's poses_bounds.npy is an (N, 17) array of "
            "numbers, a row per photo (a 3x5 pose with height, width and focal length, then near and far depth; "
            "(N, 15) without them)."
        )
    data = data.astype(np.float64)
    poses = data[:, :15].reshape(-1, 3, 5)
    bounds = data[:, 15:17] if data.shape[1] == 17 else None
    for row, pose in enumerate(poses):
        where = f"{path.name} row {row} (counting from 0: photo {row + 1} in sorted order)"
        height, width, focal = pose[:, 4]
        if not np.all(np.isfinite(pose[:, 4])) or min(height, width, focal) <= 0 or min(height, width) < 1:
            raise NeulfError(
                f"{where} gives the camera height, width and focal length as {height:g}, {width:g}, {focal:g}: all "
                "three must be finite and positive; regenerate poses_bounds.npy (LLFF's imgs2poses)."
            )
        rotation, centre = pose[:, :3], pose[:, 3]
        if not np.all(np.isfinite(rotation)) or not np.all(np.isfinite(centre)):
            raise NeulfError(
                f"{where} has a camera rotation or centre that is not finite (NaN or infinity): "
                "regenerate poses_bounds.npy (LLFF's imgs2poses)."
            )
        if not np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-2) or np.linalg.det(rotation) < 0:
            raise NeulfError(
                f"{where} has camera axes that are not a rotation (its first three columns must be unit length, at "
                "right angles, and right-handed as [down, right, backwards]): regenerate poses_bounds.npy."
            )
    notes = []
    if bounds is not None:
        with np.errstate(invalid="ignore"):  # (NaN compares False: not usable)
            usable = np.isfinite(bounds).all(axis=1) & (bounds[:, 0] > 0) & (bounds[:, 0] < bounds[:, 1])
        unusable = np.flatnonzero(~usable)
        if len(unusable):
            shown = ", ".join(f"row {row} ({bounds[row, 0]:g}, {bounds[row, 1]:g})" for row in unusable[:5])
            notes.append(f"{path.name} gives near and far depths that are not finite with 0 < near < far in "
                         f"{len(unusable)} of its {len(bounds)} rows ({shown}{' ...' if len(unusable) > 5 else ''}; "
                         "rows count from 0, in sorted photo order): "
                         + ("the scene's depth range is read from the other rows." if usable.any() else
                            "the scene's depth range must be given (--st-depth, --near, --far)."))
        bounds = np.where(usable[:, None], bounds, np.nan) if usable.any() else None
    return poses, bounds, notes


# ----------------------------------------------------------------------------- held-out views


def split_views(scene: Scene, holdout_every: int = 8, exclude: list[str] | None = None) -> tuple[list[View], list[View]]:
    """(train, held_out).  Held out: the named views, or every `holdout_every`-th view in
    name order starting with the first (the NeRF/LLFF convention); 0 holds out none."""
    if len(scene.views) < 2:  # "hold out fewer views" would not help: there is nothing to hold out
        raise NeulfError(
            f"the scene has only {len(scene.views)} registered photo; a light field is learnt from many photos taken "
            "from slightly different positions: add more and run reconstruct again."
        )
    if exclude:
        held = {scene.view(name).name for name in exclude}
    elif holdout_every and holdout_every > 0:
        held = {v.name for i, v in enumerate(scene.views) if i % holdout_every == 0}
    else:
        held = set()
    train = [v for v in scene.views if v.name not in held]
    test = [v for v in scene.views if v.name in held]
    if len(train) < 2:
        raise NeulfError(f"only {len(train)} training views remain after holding out {len(test)}; hold out fewer views (--holdout-every 0 holds out none).")
    return train, test

"""Turn a folder of photos into a COLMAP model with pycolmap (CPU only).

:func:`reconstruct` runs the usual structure-from-motion pipeline (SIFT feature extraction,
feature matching, incremental mapping) and writes a SCENE_DIR::

    out_dir/
        images/        the photos (hard links where possible, else copies; same file names)
        sparse/0/      the COLMAP model, binary (the largest one when COLMAP found several)
        database.db    COLMAP's features and matches, kept for inspection or re-runs

Written against pycolmap 4.2.1, whose API differs from older releases (options live in
``FeatureExtractionOptions`` / ``FeatureMatchingOptions`` / ``IncrementalPipelineOptions``,
the camera sharing is a ``CameraMode``, and the device is an explicit argument).

pycolmap logs through glog straight to stderr; while it runs only ERROR-level messages are
let through, so the progress callback is the one place to watch a run.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from pathlib import Path
from typing import Callable, Iterator, Sequence

import pycolmap

from .errors import NeulfError
from .images import IMAGE_EXTENSIONS, list_images

MIN_PHOTOS = 3
# Exhaustive matching compares every pair: best for small captures, quadratic cost beyond.
EXHAUSTIVE_MATCHING_MAX_PHOTOS = 100
MATCHERS = ("auto", "exhaustive", "sequential")

ProgressCallback = Callable[[dict], None]


def reconstruct(
    images_dir,
    out_dir,
    *,
    progress: ProgressCallback | None = None,
    camera_model: str = "SIMPLE_RADIAL",
    seed: int = 0,
    single_camera: bool = True,
    max_image_size: int = 1600,
    matcher: str = "auto",
    min_registered_fraction: float = 0.5,
) -> Path:
    """Reconstruct camera poses for the photos in ``images_dir`` into ``out_dir``.

    Args:
        images_dir: folder of photos (``IMAGE_EXTENSIONS``, any case; other files, hidden
            files and subfolders are ignored).
        out_dir: SCENE_DIR to write (created if needed). A previous ``database.db`` and
            ``sparse/0`` there are replaced.
        progress: called with ``{"stage", "message", "registered", "total"}`` dicts; stage is
            "features", "matching", "mapping" or "done". Exceptions it raises abort the run
            and propagate unchanged (a way to cancel).
        camera_model: COLMAP camera model name, e.g. "SIMPLE_RADIAL", "OPENCV", "PINHOLE".
        single_camera: all photos share one camera (same device, zoom and resolution); the
            usual handheld capture. False gives every photo its own intrinsics.
        max_image_size: photos are downscaled to this longest side for feature extraction.
        matcher: "exhaustive" (all pairs), "sequential" (neighbours in file-name order, for
            video frames), or "auto" (exhaustive up to 100 photos, sequential beyond).
        min_registered_fraction: fail unless at least this fraction of the photos (and at
            least 3) got a camera pose.

    Returns:
        The path of ``out_dir/sparse/0``.

    Raises:
        NeulfError: for anything the user can fix (bad folder, too few or unreadable photos,
            photos that do not overlap, too few photos registered, COLMAP failing).
    """
    _check_options(camera_model, matcher, max_image_size)
    # COLMAP's RANSAC and mapper are randomised: a fixed seed makes reruns reproducible.
    pycolmap.set_random_seed(seed)
    photos = find_photos(Path(images_dir))
    out_dir = Path(out_dir)
    try:
        scene_images = stage_photos(photos, out_dir / "images")
        database, model_dir = _clear_previous_outputs(out_dir)
    except OSError as error:
        raise NeulfError(
            f"Cannot write the scene folder {out_dir}: {error.strerror or error}; "
            "choose a writable folder with free space."
        ) from error
    names = [photo.name for photo in photos]
    reporter = _ProgressReporter(progress, total=len(names))

    with _quiet_colmap_logging(), _colmap_errors_as_neulf_errors(reporter):
        reporter.report("features", f"Extracting features from {len(names)} photos")
        _extract_features(database, scene_images, names, camera_model, single_camera, max_image_size)
        _check_every_photo_was_read(database, scene_images, names, single_camera)
        reporter.report("features", f"Extracted features from {len(names)} photos")

        use_sequential = _use_sequential_matching(matcher, len(names))
        reporter.report("matching", f"Matching features ({'sequential' if use_sequential else 'exhaustive'})")
        _match_features(database, use_sequential)
        matched_pairs = _count_matched_pairs(database)
        reporter.report("matching", f"Matched {matched_pairs} photo pairs")

        reporter.report("mapping", "Registering photos")
        reconstruction = _map_largest_model(database, scene_images, out_dir, reporter)

        registered = reconstruction.num_reg_images()
        _check_enough_registered(registered, len(names), min_registered_fraction)
        model_dir.mkdir(parents=True)
        reconstruction.write_binary(model_dir)

    reporter.report("done", f"Registered {registered} of {len(names)} photos", registered=registered)
    return model_dir


# --------------------------------------------------------------------------- input checks


def find_photos(images_dir: Path) -> list[Path]:
    """The photos directly inside ``images_dir``, sorted by name; raises if unusable."""
    if not images_dir.exists():
        raise NeulfError(
            f"Photo folder {images_dir} does not exist; pass the folder that holds your photos."
        )
    if not images_dir.is_dir():
        raise NeulfError(f"{images_dir} is a file, not a folder; pass the folder that holds your photos.")
    # Hidden files are skipped: macOS "._IMG_0001.jpg" resource forks look like photos.
    photos = list_images(images_dir)
    if not photos:
        raise NeulfError(
            f"No photos found in {images_dir}; accepted extensions are {', '.join(IMAGE_EXTENSIONS)} "
            "(subfolders are not searched)."
        )
    if len(photos) < MIN_PHOTOS:
        raise NeulfError(
            f"Only {len(photos)} photo(s) in {images_dir}; at least {MIN_PHOTOS} overlapping photos "
            "are needed (20 or more work best)."
        )
    return photos


def _check_options(camera_model: str, matcher: str, max_image_size: int) -> None:
    # These usually come straight from CLI flags or UI fields, so a typo is a user error.
    known_models = [name for name in pycolmap.CameraModelId.__members__ if name != "INVALID"]
    if camera_model not in known_models:
        raise NeulfError(f"Unknown camera model {camera_model!r}; use one of {', '.join(known_models)}.")
    if matcher not in MATCHERS:
        raise NeulfError(f"Unknown matcher {matcher!r}; use one of {', '.join(MATCHERS)}.")
    if max_image_size < 100:
        raise NeulfError(
            f"max_image_size {max_image_size} is too small for feature extraction; use 1000 or more."
        )


# ------------------------------------------------------------------------ scene folder


def stage_photos(photos: Sequence[Path], images_out: Path) -> Path:
    """Put the photos into ``images_out`` under their own names: hard links, else copies."""
    images_out.mkdir(parents=True, exist_ok=True)
    for photo in photos:
        target = images_out / photo.name
        if target.exists() and os.path.samefile(photo, target):
            continue  # images_dir is out_dir/images itself, or a previous run linked it already
        if target.exists() or target.is_symlink():
            target.unlink()
        try:
            os.link(photo, target)
        except OSError:  # another file system, or one without hard links
            shutil.copy2(photo, target)
    return images_out


def _clear_previous_outputs(out_dir: Path) -> tuple[Path, Path]:
    """Remove a previous run's database and model; returns their paths.

    An old database would make COLMAP reuse stale features, and an old model left behind by a
    failed run would look like a valid result for the new photos.
    """
    database = out_dir / "database.db"
    for path in (database, out_dir / "database.db-wal", out_dir / "database.db-shm"):
        path.unlink(missing_ok=True)
    model_dir = out_dir / "sparse" / "0"
    if model_dir.exists():
        shutil.rmtree(model_dir)
    return database, model_dir


# -------------------------------------------------------------------------- pipeline


def _extract_features(
    database: Path,
    images: Path,
    names: list[str],
    camera_model: str,
    single_camera: bool,
    max_image_size: int,
) -> None:
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = max_image_size
    extraction.use_gpu = False
    pycolmap.extract_features(
        database,
        images,
        # Explicit names, so stray files left in out_dir/images by earlier runs are not picked up.
        image_names=names,
        camera_mode=pycolmap.CameraMode.SINGLE if single_camera else pycolmap.CameraMode.PER_IMAGE,
        reader_options=pycolmap.ImageReaderOptions(camera_model=camera_model),
        extraction_options=extraction,
        device=pycolmap.Device.cpu,
    )


def _use_sequential_matching(matcher: str, num_photos: int) -> bool:
    if matcher == "auto":
        return num_photos > EXHAUSTIVE_MATCHING_MAX_PHOTOS
    return matcher == "sequential"


def _match_features(database: Path, sequential: bool) -> None:
    matching = pycolmap.FeatureMatchingOptions()
    matching.use_gpu = False
    if sequential:
        pycolmap.match_sequential(database, matching_options=matching, device=pycolmap.Device.cpu)
    else:
        pycolmap.match_exhaustive(database, matching_options=matching, device=pycolmap.Device.cpu)


def _map_largest_model(
    database: Path, images: Path, out_dir: Path, reporter: _ProgressReporter
) -> pycolmap.Reconstruction:
    """Run incremental mapping and return the model with the most registered photos."""
    # pycolmap writes every model it finds; a scratch folder keeps sparse/ to the chosen one.
    with tempfile.TemporaryDirectory(prefix=".mapping-", dir=out_dir) as scratch:
        reconstructions = pycolmap.incremental_mapping(
            database,
            images,
            scratch,
            pycolmap.IncrementalPipelineOptions(),
            initial_image_pair_callback=reporter.initial_pair_registered,
            next_image_callback=reporter.next_image_registered,
        )
    if not reconstructions:
        raise NeulfError(_NO_MATCHES_MESSAGE)
    return max(reconstructions.values(), key=lambda reconstruction: reconstruction.num_reg_images())


# -------------------------------------------------------------------- result checks

_NO_MATCHES_MESSAGE = (
    "No two photos could be matched: the photos need to overlap (each part of the scene seen "
    "in several photos), be sharp, and show textured surfaces rather than plain walls or sky."
)


def _check_every_photo_was_read(database: Path, images: Path, names: list[str], single_camera: bool) -> None:
    """COLMAP skips photos it cannot use with only a warning; turn that into a clear error."""
    with pycolmap.Database.open(database) as db:
        extracted = {image.name for image in db.read_all_images()}
    skipped = [name for name in names if name not in extracted]
    if not skipped:
        return
    unreadable = [name for name in skipped if pycolmap.Bitmap.read(images / name, False) is None]
    if unreadable:
        raise NeulfError(
            f"Could not read {len(unreadable)} photo(s): {_short_list(unreadable)}; "
            "re-export them as PNG or JPEG, or remove them from the folder."
        )
    # Readable but skipped: with one shared camera, COLMAP rejects photos whose size differs
    # from the first photo it read, which need not be the odd one out; so name the minority.
    odd_sized, common_size = _photos_of_uncommon_size(images, names)
    if single_camera and odd_sized:
        raise NeulfError(
            f"{_short_list(odd_sized)} differ(s) in size from the other photos ({common_size}); with one "
            "shared camera all photos must have the same size: use photos from one camera at one resolution, "
            "or pass single_camera=False."
        )
    raise NeulfError(
        f"COLMAP could not use {_short_list(skipped)}; check that these are valid photos or remove them."
    )


def _photos_of_uncommon_size(images: Path, names: list[str]) -> tuple[list[str], str]:
    """Photos whose size differs from the most common one, and that size as "WxH"."""
    names_by_size: dict[str, list[str]] = {}
    for name in names:
        bitmap = pycolmap.Bitmap.read(images / name, False)
        names_by_size.setdefault(f"{bitmap.width}x{bitmap.height}", []).append(name)
    common_size = max(names_by_size, key=lambda size: len(names_by_size[size]))
    odd_sized = [name for size, group in names_by_size.items() if size != common_size for name in group]
    return sorted(odd_sized), common_size


def _count_matched_pairs(database: Path) -> int:
    """Photo pairs with enough verified matches for mapping to use; raises if there are none."""
    # Checked before mapping, so the user gets this message instead of COLMAP's log error.
    min_matches = pycolmap.IncrementalPipelineOptions().min_num_matches
    with pycolmap.Database.open(database) as db:
        _, inlier_counts = db.read_two_view_geometry_num_inliers()
    matched_pairs = sum(count >= min_matches for count in inlier_counts)
    if matched_pairs == 0:
        raise NeulfError(_NO_MATCHES_MESSAGE)
    return matched_pairs


def _check_enough_registered(registered: int, total: int, min_registered_fraction: float) -> None:
    needed = max(MIN_PHOTOS, min_registered_fraction * total)
    if registered < needed:
        raise NeulfError(
            f"Only {registered} of {total} photos could be placed in one model (need at least {needed:g}); "
            "retake them with more overlap between neighbouring photos, slower camera motion, "
            "and more texture in view."
        )


def _short_list(names: list[str], limit: int = 5) -> str:
    shown = ", ".join(names[:limit])
    return shown if len(names) <= limit else f"{shown} and {len(names) - limit} more"


# ------------------------------------------------------------ progress, logs, errors


class _ProgressReporter:
    """Sends progress dicts to the user's callback and remembers where the run is."""

    def __init__(self, callback: ProgressCallback | None, total: int):
        self.callback = callback
        self.total = total
        self.stage = "starting"
        self.registered = 0
        # An exception from the user's callback (e.g. a cancel) must pass through unchanged,
        # not be mistaken for a COLMAP failure when it surfaces from inside pycolmap.
        self.callback_error: BaseException | None = None

    def report(self, stage: str, message: str, registered: int | None = None) -> None:
        self.stage = stage
        if registered is not None:
            self.registered = registered
        if self.callback is None:
            return
        try:
            event = {"stage": stage, "message": message, "registered": self.registered, "total": self.total}
            self.callback(event)
        except BaseException as error:
            self.callback_error = error
            raise

    def initial_pair_registered(self) -> None:
        # Called again whenever COLMAP starts a further model, so the count restarts at 2.
        self.report("mapping", f"Registered initial pair (2 of {self.total} photos)", registered=2)

    def next_image_registered(self) -> None:
        count = self.registered + 1
        self.report("mapping", f"Registered {count} of {self.total} photos", registered=count)


@contextlib.contextmanager
def _quiet_colmap_logging() -> Iterator[None]:
    """Let only ERROR and FATAL glog messages through while pycolmap runs."""
    previous = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = int(pycolmap.logging.ERROR)
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = previous


@contextlib.contextmanager
def _colmap_errors_as_neulf_errors(reporter: _ProgressReporter) -> Iterator[None]:
    """Wrap exceptions raised by pycolmap into a one-line NeulfError naming the stage."""
    try:
        yield
    except NeulfError:
        raise
    except Exception as error:
        if reporter.callback_error is not None:
            raise
        detail = " ".join(str(error).split()) or type(error).__name__
        raise NeulfError(
            f"COLMAP failed during {reporter.stage}: {detail}; check that the photos are valid "
            "and the output folder is writable."
        ) from error

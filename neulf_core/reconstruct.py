"""Turn a folder of photos into a COLMAP model with pycolmap (CPU only).

:func:`reconstruct` runs the usual structure-from-motion pipeline (SIFT feature extraction,
feature matching, incremental mapping) and writes a SCENE_DIR::

    out_dir/
        images/        the photos (hard links where possible, else copies; same file names,
                       except that WebP photos, which COLMAP cannot read, become PNG copies)
        sparse/0/      the COLMAP model, binary (the largest one when COLMAP found several)
        database.db    COLMAP's features and matches, kept for inspection or re-runs

A run works in a hidden folder inside out_dir (``.reconstruct-*``, with its process recorded
in it) and changes nothing else there until the new model is made: a failed or cancelled run
leaves out_dir as it was (a previous model included), and a photo already in out_dir/images is
never overwritten by a different one of the same name.  The hidden folder of a run killed
outright (SIGKILL, a power cut) is removed by the next run into out_dir; a run into a folder
another run is still reconstructing is refused (the two would install over each other).

Written against pycolmap 4.2.1, whose API differs from older releases (options live in
``FeatureExtractionOptions`` / ``FeatureMatchingOptions`` / ``IncrementalPipelineOptions``,
the camera sharing is a ``CameraMode``, and the device is an explicit argument).

pycolmap logs through glog straight to stderr; while it runs only ERROR-level messages are
let through, so the progress callback is the one place to watch a run.
"""

from __future__ import annotations

import contextlib
import filecmp
import os
import shlex
import shutil
import tempfile
import time
from pathlib import Path
from typing import Callable, Iterator, Sequence

import numpy as np
import pycolmap

from .errors import NeulfError
from .frames import is_video
from .images import IMAGE_EXTENSIONS, list_images, open_upright
from .lock import claim, claim_holder

MIN_PHOTOS = 3
WORK_PREFIX = ".reconstruct-"
WORK_OWNER = "owner.json"  # the process reconstructing in a work folder (lock.claim)
# A work folder without a readable owner record is taken for a run's first instant (or a kill
# in it, or a passing read error) until it is this old; older ones (a kill, or an earlier
# version's run) are removed.
UNCLAIMED_WORK_SECONDS = 3600
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
            ``sparse/0`` there are replaced once the new model is made; photos already in
            ``out_dir/images`` stay, and one that differs from a new photo of the same name
            makes the run refuse before anything is changed.
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
    photos = _drop_converted_duplicates(find_photos(Path(images_dir)))
    out_dir = Path(out_dir).absolute()
    created_out_dir = not out_dir.exists()
    work = None
    try:
        try:
            out_dir.mkdir(parents=True, exist_ok=True)
            # Everything is made in here first; out_dir itself changes only in _install_results.
            work = _start_work_folder(out_dir)
            scene_images = stage_photos(photos, work / "images")
        except OSError as error:
            raise _unwritable(out_dir, error) from error
        names = scene_photo_names(photos)
        _check_no_conflicting_photos(scene_images, names, out_dir / "images")
        database = work / "database.db"
        new_model_dir = work / "sparse"
        model_dir = out_dir / "sparse" / "0"
        reporter = _ProgressReporter(progress, total=len(names))
        left_out = left_out_photos(Path(images_dir))
        if left_out:  # (a mixed folder: those are not in the reconstruction, and nothing else would say so)
            reporter.report("features", f"warning: {len(left_out)} photo(s) in a camera format that cannot be read are "
                                        f"left out ({left_out[0].name}{' ...' if len(left_out) > 1 else ''}): export "
                                        "them as JPEG or PNG to include them")

        with _quiet_colmap_logging(), _colmap_errors_as_neulf_errors(reporter):
            reporter.report("features", f"Extracting features from {len(names)} photos")
            _extract_features(database, scene_images, names, camera_model, single_camera, max_image_size)
            _check_every_photo_was_read(database, scene_images, names, single_camera)
            reporter.report("features", f"Extracted features from {len(names)} photos")

            use_sequential = _use_sequential_matching(matcher, len(names))
            reporter.report("matching", f"Matching features ({'sequential' if use_sequential else 'exhaustive'})")
            _match_features(database, use_sequential)
            matched_pairs = _count_matched_pairs(database, camera_model)
            reporter.report("matching", f"Matched {matched_pairs} photo pairs")

            reporter.report("mapping", "Registering photos")
            reconstruction = _map_largest_model(
                database, scene_images, work, reporter, camera_model, matched_pairs
            )

            registered = reconstruction.num_reg_images()
            _check_enough_registered(registered, len(names), min_registered_fraction)
            new_model_dir.mkdir()
            reconstruction.write_binary(new_model_dir)
        try:
            _install_results(work, scene_images, names, out_dir)
        except OSError as error:
            raise _unwritable(out_dir, error) from error
    finally:
        if work is not None:
            shutil.rmtree(work, ignore_errors=True)
        if created_out_dir:
            with contextlib.suppress(OSError):
                out_dir.rmdir()  # only if empty: a failed run into a new folder leaves nothing

    reporter.report("done", f"Registered {registered} of {len(names)} photos", registered=registered)
    return model_dir


def _start_work_folder(out_dir: Path) -> Path:
    """This run's hidden folder in out_dir, its process recorded; work folders of runs that no
    longer exist are removed first, and a run still going into out_dir is refused (checked again
    once this run's folder is claimed, so two started at once do not both go on)."""
    _refuse_another_run(out_dir, _other_runs(out_dir))
    work = Path(tempfile.mkdtemp(prefix=WORK_PREFIX, dir=out_dir))
    claim(work / WORK_OWNER)
    others = _other_runs(out_dir, own=work)
    if others:
        shutil.rmtree(work, ignore_errors=True)
        _refuse_another_run(out_dir, others)
    return work


def _other_runs(out_dir: Path, own: Path | None = None) -> list[tuple[Path, dict]]:
    """(folder, owner) of the other work folders in out_dir whose process still runs; the
    folders of runs that are gone are deleted on the way."""
    running = []
    for folder in sorted(out_dir.glob(WORK_PREFIX + "*")):
        if (own is not None and folder.name == own.name) or not folder.is_dir():  # (mkdtemp's path is absolute)
            continue
        owner = claim_holder(folder / WORK_OWNER, UNCLAIMED_WORK_SECONDS)
        if owner is not None:
            running.append((folder, owner))
        elif (folder / WORK_OWNER).is_file() or _age_seconds(folder) > UNCLAIMED_WORK_SECONDS:
            _finish_install(folder, out_dir)
            shutil.rmtree(folder, ignore_errors=True)  # its process is gone: nothing else in it is wanted
    return running


def _finish_install(work: Path, out_dir: Path) -> None:
    """A run killed between _install_results' two renames left the scene without sparse/0, its
    old model and its new, complete one (the database already the new one's) in its work folder:
    the new model is put in place, not deleted with the folder."""
    model_dir = out_dir / "sparse" / "0"
    if not (model_dir.exists() or model_dir.is_symlink()) and (work / "sparse").is_dir() and (work / "old-model").exists():
        with contextlib.suppress(OSError):
            os.replace(work / "sparse", model_dir)


def _age_seconds(folder: Path) -> float:
    try:
        return time.time() - folder.stat().st_mtime
    except OSError:
        return 0.0


def _refuse_another_run(out_dir: Path, others: list[tuple[Path, dict]]) -> None:
    if others:
        folder, owner = others[0]
        gone = f" (if that process is gone, delete {folder})"
        raise NeulfError(
            f"{out_dir} is being reconstructed by process {owner['pid']} on {owner['host']}; wait for it to finish "
            f"or stop it, or reconstruct into another folder{gone}."
        )


def _unwritable(out_dir: Path, error: OSError) -> NeulfError:
    return NeulfError(
        f"Cannot write the scene folder {out_dir}: {error.strerror or error}; "
        "choose a writable folder with free space."
    )


# --------------------------------------------------------------------------- input checks


# Cameras' own formats that neither Pillow nor COLMAP reads: an iPhone's default (HEIC), raw files.
CAMERA_ONLY_FORMATS = (".heic", ".heif", ".avif", ".dng", ".cr2", ".cr3", ".nef", ".arw", ".raf", ".orf", ".rw2")


def left_out_photos(images_dir: Path) -> list[Path]:
    """Photos in a camera's own format directly inside `images_dir`, which are not read."""
    return sorted(p for p in Path(images_dir).iterdir()
                  if p.is_file() and not p.name.startswith(".") and p.suffix.lower() in CAMERA_ONLY_FORMATS)


def _camera_formats_note(images_dir: Path) -> str:
    """' (it holds 30 .HEIC photos, which ... : export them as JPEG)', or ''."""
    left_out = left_out_photos(images_dir)
    if not left_out:
        return ""
    kinds = ", ".join(sorted({p.suffix.upper() for p in left_out}))
    return (f" (it holds {len(left_out)} {kinds} photo(s), which cannot be read: export them as JPEG or PNG -- on an "
            "iPhone, Settings > Camera > Formats > Most Compatible takes JPEGs from then on)")


def find_photos(images_dir: Path) -> list[Path]:
    """The photos directly inside ``images_dir``, sorted by name; raises if unusable."""
    if not images_dir.exists():
        raise NeulfError(
            f"Photo folder {images_dir} does not exist; pass the folder that holds your photos."
        )
    if not images_dir.is_dir():
        if is_video(images_dir):
            raise NeulfError(f"{images_dir} is a video: pick its sharpest frames as photos first, with python -m "
                             f"neulf_core frames {shlex.quote(str(images_dir))} --out PHOTOS_DIR, then reconstruct "
                             "PHOTOS_DIR.")
        raise NeulfError(f"{images_dir} is a file, not a folder; pass the folder that holds your photos.")
    # Hidden files are skipped: macOS "._IMG_0001.jpg" resource forks look like photos.
    photos = list_images(images_dir)
    if not photos:
        raise NeulfError(
            f"No photos found in {images_dir}{_camera_formats_note(images_dir)}; accepted extensions are "
            f"{', '.join(IMAGE_EXTENSIONS)} (subfolders are not searched)."
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


# COLMAP (pycolmap 4.2.1) cannot decode these; they are staged as PNG copies made with Pillow.
CONVERTED_EXTENSIONS = (".webp",)


def _needs_conversion(photo: Path) -> bool:
    return photo.suffix.lower() in CONVERTED_EXTENSIONS


def scene_photo_names(photos: Sequence[Path]) -> list[str]:
    """The names the photos get in the scene's images/ (and the COLMAP model), in order.

    A photo keeps its name, except that one COLMAP cannot read becomes "<stem>.png"; or
    "<name>.png" when another photo already has that name.
    """
    taken = {photo.name for photo in photos if not _needs_conversion(photo)}
    names = []
    for photo in photos:
        if _needs_conversion(photo):
            name = f"{photo.stem}.png"
            if name in taken:
                name = f"{photo.name}.png"
            taken.add(name)
            names.append(name)
        else:
            names.append(photo.name)
    return names


def _drop_converted_duplicates(photos: list[Path]) -> list[Path]:
    """Drop a WebP photo whose PNG copy sits beside it (a scene's images/ used as input again)."""
    by_name = {photo.name: photo for photo in photos}
    kept = []
    for photo in photos:
        png = by_name.get(f"{photo.stem}.png")
        if _needs_conversion(photo) and png is not None and _same_pixels(photo, png):
            continue
        kept.append(photo)
    return kept


def _same_pixels(first: Path, second: Path) -> bool:
    try:
        a, b = open_upright(first), open_upright(second)
    except NeulfError:
        return False
    return a.size == b.size and a.mode == b.mode and np.array_equal(np.asarray(a), np.asarray(b))


def _convert_to_png(photo: Path, target: Path) -> None:
    """Save ``photo`` upright (EXIF orientation applied, as training reads it) as a PNG."""
    image = open_upright(photo)  # (as training reads photos: past Pillow's bomb limit too, up to PHOTO_PIXEL_LIMIT)
    if image.mode not in ("1", "L", "LA", "I", "I;16", "P", "RGB", "RGBA"):
        image = image.convert("RGB")
    image.save(target, format="PNG", compress_level=1)


def stage_photos(photos: Sequence[Path], images_out: Path) -> Path:
    """Put the photos into ``images_out`` under their scene names: hard links, else copies.

    WebP photos become PNG copies (see :func:`scene_photo_names`). A file of the same name
    already there is kept if it holds the same photo; if it holds another, this raises
    before anything is written.
    """
    images_out.mkdir(parents=True, exist_ok=True)
    plan = list(zip(photos, scene_photo_names(photos)))
    conflicts = [
        name for photo, name in plan
        if (images_out / name).exists() and not _needs_conversion(photo)
        and not _same_file_contents(photo, images_out / name)
    ]
    if conflicts:
        raise _conflict_error(conflicts, images_out)
    for photo, name in plan:
        target = images_out / name
        if target.exists():
            if not _needs_conversion(photo):
                continue  # images_dir is images_out itself, or a previous run linked it already
            converted = images_out / f".{name}.converting"
            _convert_to_png(photo, converted)
            if not _same_file_contents(converted, target):
                converted.unlink()
                raise _conflict_error([name], images_out)
            converted.unlink()
            continue
        if target.is_symlink():
            target.unlink()  # a dangling link: no photo to lose
        if _needs_conversion(photo):
            _convert_to_png(photo, target)
            continue
        try:
            os.link(photo, target)
        except OSError:  # another file system, or one without hard links
            shutil.copy2(photo, target)
    return images_out


def _same_file_contents(first: Path, second: Path) -> bool:
    try:
        if os.path.samefile(first, second):
            return True
        if not (first.is_file() and second.is_file()):
            return False
        return filecmp.cmp(first, second, shallow=False) or _same_pixels(first, second)
    except OSError:
        return False


def _conflict_error(names: list[str], images: Path) -> NeulfError:
    return NeulfError(
        f"{images} already holds another photo named {_short_list(names)}; nothing was changed: "
        "choose a new --out folder for these photos, or rename the new photo(s)."
    )


def _check_no_conflicting_photos(staged: Path, names: list[str], images_out: Path) -> None:
    """Refuse, before out_dir changes, to put a photo where another of its name already is."""
    conflicts = []
    for name in names:
        target = images_out / name
        if (target.exists() or target.is_symlink()) and not _same_file_contents(staged / name, target):
            if target.is_symlink() and not target.exists():
                continue  # a dangling link holds no photo; it is replaced
            conflicts.append(name)
    if conflicts:
        raise _conflict_error(conflicts, images_out)


def _install_results(work: Path, staged: Path, names: list[str], out_dir: Path) -> None:
    """Move the new photos, database and model from ``work`` into ``out_dir``.

    Photos are only added (one of the same name already there holds the same picture, as
    checked before the run); the database and ``sparse/0`` are swapped by renames, so the old
    model stays in place until the new one is complete.
    """
    images_out = out_dir / "images"
    images_out.mkdir(exist_ok=True)
    for name in names:
        target = images_out / name
        if target.exists():
            continue
        if target.is_symlink():
            target.unlink()
        shutil.move(staged / name, target)
    # An old WAL or shared-memory file would be replayed into the new database.
    for suffix in ("-wal", "-shm"):
        (out_dir / f"database.db{suffix}").unlink(missing_ok=True)
    os.replace(work / "database.db", out_dir / "database.db")
    for suffix in ("-wal", "-shm"):
        if (work / f"database.db{suffix}").exists():
            os.replace(work / f"database.db{suffix}", out_dir / f"database.db{suffix}")
    model_dir = out_dir / "sparse" / "0"
    model_dir.parent.mkdir(exist_ok=True)
    if model_dir.exists() or model_dir.is_symlink():
        os.replace(model_dir, work / "old-model")  # removed with work
    os.replace(work / "sparse", model_dir)


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
    database: Path,
    images: Path,
    work: Path,
    reporter: _ProgressReporter,
    camera_model: str = "SIMPLE_RADIAL",
    matched_pairs: int = 0,
) -> pycolmap.Reconstruction:
    """Run incremental mapping and return the model with the most registered photos."""
    # pycolmap writes every model it finds; a scratch folder keeps sparse/ to the chosen one.
    with tempfile.TemporaryDirectory(prefix=".mapping-", dir=work) as scratch:
        reconstructions = pycolmap.incremental_mapping(
            database,
            images,
            scratch,
            pycolmap.IncrementalPipelineOptions(),
            initial_image_pair_callback=reporter.initial_pair_registered,
            next_image_callback=reporter.next_image_registered,
        )
    if not reconstructions:
        raise NeulfError(_no_model_message(camera_model, matched_pairs))
    return max(reconstructions.values(), key=lambda reconstruction: reconstruction.num_reg_images())


# -------------------------------------------------------------------- result checks

_NO_MATCHES_MESSAGE = (
    "No two photos could be matched: the photos need to overlap (each part of the scene seen "
    "in several photos), be sharp, and show textured surfaces rather than plain walls or sky."
)

# Models COLMAP starts from a focal-length guess alone; the others need their extra
# (distortion or fisheye) parameters right from the first pair, and fail on photos they do not fit.
_SIMPLE_CAMERA_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL")


def _camera_model_message(camera_model: str, opening: str) -> str:
    return (
        f"{opening} with the camera model {camera_model}, the likely cause: run again with the default "
        "camera model (leave out --camera-model, or pass --camera-model SIMPLE_RADIAL), or with one "
        "that fits the lens."
    )


def _no_model_message(camera_model: str, matched_pairs: int) -> str:
    """Why mapping made no model although photo pairs matched (checked before mapping)."""
    if matched_pairs <= 0:
        return _NO_MATCHES_MESSAGE
    if camera_model not in _SIMPLE_CAMERA_MODELS:
        return _camera_model_message(
            camera_model, f"{matched_pairs} photo pair(s) matched, but no pair could start a model"
        )
    return (
        f"{matched_pairs} photo pair(s) matched, but no pair could start a model: the photos need to be "
        "taken from different positions (move the camera between photos rather than only turning it), "
        "sharp and textured."
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
            "shared camera all photos must have the same size: use photos from one camera at one resolution "
            f"(resize these to {common_size}, or remove them from the folder); from Python, "
            "reconstruct(..., single_camera=False) gives every photo its own camera instead."
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


def _count_matched_pairs(database: Path, camera_model: str = "SIMPLE_RADIAL") -> int:
    """Photo pairs with enough verified matches for mapping to use; raises if there are none."""
    # Checked before mapping, so the user gets this message instead of COLMAP's log error.
    min_matches = pycolmap.IncrementalPipelineOptions().min_num_matches
    with pycolmap.Database.open(database) as db:
        _, inlier_counts = db.read_two_view_geometry_num_inliers()
        matched_pairs = sum(count >= min_matches for count in inlier_counts)
        if matched_pairs == 0 and camera_model not in _SIMPLE_CAMERA_MODELS:
            _, raw_matches = db.read_all_matches()
            if any(len(matches) >= min_matches for matches in raw_matches):
                # Features matched, yet no pair's geometry could be verified with this model.
                opening = "The photos share features, but no pair of them could be verified"
                raise NeulfError(_camera_model_message(camera_model, opening))
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

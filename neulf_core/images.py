"""Reading photos: finding the file a model names, and decoding any common photo to RGB.

A COLMAP model names its images ("IMG_4026.JPG"); the folder on disk may hold the same
names, the same stems with another extension ("IMG_4026.png"), or LLFF's downscaled
copies in sorted order ("image000.png", ...).  Photos come as 8 or 16 bit, grayscale,
palette, RGBA, CMYK, with an EXIF orientation.  Everything here turns that into an
(H, W, 3) uint8 array the way the camera saw it.
"""

from __future__ import annotations

import contextlib
import io
import re
import threading
from pathlib import Path

import numpy as np
from PIL import Image, ImageOps, UnidentifiedImageError

from .errors import NeulfError
from .files import atomic_write_bytes

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp")  # what Pillow and COLMAP both read
# The widest or tallest image rendered or trained on: JPEG's own limit, and far past any photo or
# render (a 16K frame is 15360 wide).  A size past it is a typo or a damaged file, which would
# fail deep in numpy or pycolmap (a --scale of 1e300, a camera 1e9 pixels wide).
LARGEST_IMAGE_SIDE = 65535


def is_image_file(path: Path) -> bool:
    return path.is_file() and path.suffix.lower() in IMAGE_EXTENSIONS and not path.name.startswith(".")


def list_images(folder: Path) -> list[Path]:
    """Image files directly inside `folder`, sorted by name."""
    return sorted((p for p in folder.iterdir() if is_image_file(p)), key=lambda p: p.name)


# The most pixels a photo may have.  Pillow refuses more than 179 MP as a possible decompression
# bomb (and warns on stderr past 89 MP), with a traceback; real photos go beyond that: Phase
# One's 150 MP backs, and the 400 MP pixel-shift stills of Fujifilm's GFX100 and Hasselblad's
# H6D-400c (1.2 GB as decoded RGB).  So photos are read up to 400 MP and a header claiming more
# is refused before anything is decoded, naming the photo.
PHOTO_PIXEL_LIMIT = 400_000_000

_own_limit_users = 0
_own_limit_guard = threading.Lock()
_pillow_limit: int | None = None


@contextlib.contextmanager
def _photo_pixel_limit():
    """Pillow's own bomb check off while this module reads a photo, which checks
    PHOTO_PIXEL_LIMIT itself (_check_pixel_count).  Pillow's limit is one global: it is put
    back as soon as the last photo being read is open, so other readers keep theirs."""
    global _own_limit_users, _pillow_limit
    with _own_limit_guard:
        if _own_limit_users == 0:
            _pillow_limit, Image.MAX_IMAGE_PIXELS = Image.MAX_IMAGE_PIXELS, None
        _own_limit_users += 1
    try:
        yield
    finally:
        with _own_limit_guard:
            _own_limit_users -= 1
            if _own_limit_users == 0:
                Image.MAX_IMAGE_PIXELS = _pillow_limit


def _check_pixel_count(path: Path, image: Image.Image) -> None:
    width, height = image.size
    if width * height > PHOTO_PIXEL_LIMIT:
        raise NeulfError(
            f"image {path} claims {width}x{height} pixels ({width * height / 1e6:.0f} MP), more than the "
            f"{PHOTO_PIXEL_LIMIT // 1_000_000} MP a photo may have (or the file is damaged); downscale it, e.g. to "
            "half its width and height."
        )


def open_upright(path: Path) -> Image.Image:
    """The photo at `path`, decoded and turned upright as the camera saw it; past
    PHOTO_PIXEL_LIMIT, or unreadable, a NeulfError naming it."""
    try:
        with _photo_pixel_limit():
            image = Image.open(path)
            _check_pixel_count(path, image)
            image.load()
    except (UnidentifiedImageError, OSError, ValueError) as exc:
        raise NeulfError(f"cannot read image {path}: {exc}. Replace or remove the file.") from None
    # Phones store portrait photos landscape plus an EXIF rotation; COLMAP saw them upright.
    return ImageOps.exif_transpose(image)


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) of the photo as displayed (EXIF orientation applied)."""
    try:
        with _photo_pixel_limit(), Image.open(path) as image:
            _check_pixel_count(path, image)
            width, height = image.size
            orientation = image.getexif().get(0x0112, 1)
    except (UnidentifiedImageError, OSError, ValueError) as exc:
        raise NeulfError(f"cannot read image {path}: {exc}. Replace or remove the file.") from None
    # EXIF orientations 5-8 swap the axes.
    return (height, width) if orientation in (5, 6, 7, 8) else (width, height)


def _to_rgb_uint8(image: Image.Image) -> np.ndarray:
    """Any PIL mode to (H, W, 3) uint8; 16-bit and float images are scaled, not clipped."""
    if image.mode in ("I;16", "I;16B", "I;16L", "I;16N", "I", "F"):
        values = np.asarray(image, dtype=np.float64)
        top = 65535.0 if image.mode.startswith("I;16") or values.max() > 255 else 255.0
        if image.mode == "F":
            top = 1.0 if values.max() <= 1.0 else values.max()
        gray = np.clip(np.round(values / top * 255.0), 0, 255).astype(np.uint8)
        return np.repeat(gray[..., None], 3, axis=2)
    if image.mode in ("RGBA", "LA", "PA") or (image.mode == "P" and "transparency" in image.info):
        # Composite onto black: transparent pixels carry no colour the camera saw.
        rgba = image.convert("RGBA")
        background = Image.new("RGBA", rgba.size, (0, 0, 0, 255))
        image = Image.alpha_composite(background, rgba)
    array = np.asarray(image.convert("RGB"), dtype=np.uint8)
    return np.ascontiguousarray(array)


def load_rgb(path: Path, size: tuple[int, int] | None = None) -> np.ndarray:
    """Decode `path` to (H, W, 3) uint8, resized to `size` = (width, height) if given.

    Downscaling uses an area (box) filter, the anti-aliased choice for a light field's
    training targets; upscaling uses bicubic.
    """
    return load_rgb_sizes(path, [size])[0]


def load_rgb_sizes(path: Path, sizes) -> list[np.ndarray]:
    """load_rgb at each of `sizes` from one decode (each resized from the full photo, so each
    is what load_rgb gives at that size): a run wants its photos at the training size and the
    depth teacher's sweep at a smaller one, and a 12-megapixel JPEG takes 60-200 ms to decode
    (docs/jpeg_half_decode.csv)."""
    rgb = _to_rgb_uint8(open_upright(Path(path)))
    return [_resized(rgb, size) for size in sizes]


def _resized(rgb: np.ndarray, size: tuple[int, int] | None) -> np.ndarray:
    if size is None or (rgb.shape[1], rgb.shape[0]) == tuple(size):
        return rgb
    resample = Image.BOX if size[0] <= rgb.shape[1] else Image.BICUBIC
    return np.asarray(Image.fromarray(rgb).resize(tuple(size), resample=resample))


SAVE_BAND_ROWS = 256  # rows converted at a time: float64 temporaries stay small for any frame size


def to_uint8(rgb: np.ndarray) -> np.ndarray:
    """Float [0, 1] (H, W, C) -> uint8, rounded.  Converted in row bands: a whole-frame
    float64 copy of a 4000x3000 render would be 288 MB, twice, on top of the render itself."""
    out = np.empty(rgb.shape, np.uint8)
    for top in range(0, rgb.shape[0], SAVE_BAND_ROWS):
        band = np.asarray(rgb[top:top + SAVE_BAND_ROWS], dtype=np.float64) * 255.0
        out[top:top + SAVE_BAND_ROWS] = np.clip(np.round(band), 0, 255)
    return out


def save_rgb(path: Path, rgb: np.ndarray) -> None:
    """Save float [0,1] or uint8 (H, W, 3) as an 8-bit image (PNG; the format `path`'s suffix
    names).  Encoded in memory and written atomically (files.atomic_write_bytes): a render
    stopped while writing had left a truncated PNG under the finished one's name."""
    if rgb.dtype != np.uint8:
        rgb = to_uint8(rgb)
    image_format = Image.registered_extensions().get(Path(path).suffix.lower())
    if image_format is None:
        raise ValueError(f"unknown file extension: {Path(path).suffix}")  # (what PIL's save(path) says)
    encoded = io.BytesIO()
    Image.fromarray(rgb).save(encoded, format=image_format)
    atomic_write_bytes(path, encoded.getbuffer())  # (a view, not a copy)


def save_npy(path: Path, array: np.ndarray) -> None:
    """np.save, written atomically as save_rgb writes."""
    encoded = io.BytesIO()
    np.save(encoded, array)
    atomic_write_bytes(path, encoded.getbuffer())  # (no copy: a 12-megapixel depth map is 48 MB)


LLFF_COPY = re.compile(r"image\d+", re.IGNORECASE)  # the stem of LLFF's downsampled copies (image000)


def resolve_image_paths(folder: Path, names: list[str]) -> dict[str, Path | None]:
    """Map each model image name to a file in `folder` (None where no file fits).

    Tried in order, per name: the exact relative path; the same stem with another image
    extension (case-insensitive).  If no name resolves that way and the folder holds exactly
    as many of LLFF's numbered copies (`images_N/image000.png`, numbered in the sorted order of
    the originals), pair them in sorted order.  Photos named otherwise are never paired by
    order: renamed ones ('canclip (1).png' ... after a rename in a file manager) sort otherwise
    than the model's names and had given 29 of 30 views another view's photo without a word.
    """
    files = list_images(folder)
    by_stem: dict[str, Path] = {}
    for path in files:
        by_stem.setdefault(path.stem.lower(), path)
    found: dict[str, Path | None] = {}
    for name in names:
        exact = folder / name
        if exact.is_file():
            found[name] = exact
            continue
        stem_dir = exact.parent
        candidates = [p for p in stem_dir.glob(Path(name).stem + ".*") if is_image_file(p)] if stem_dir.is_dir() else []
        found[name] = sorted(candidates)[0] if candidates else by_stem.get(Path(name).stem.lower())
    if (not any(found.values()) and len(files) == len(names) and names
            and all(LLFF_COPY.fullmatch(path.stem) for path in files)):
        found = dict(zip(sorted(names), files))
    return found

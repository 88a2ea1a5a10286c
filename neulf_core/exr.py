"""Scene-linear float images for compositing: the sRGB decode, and OpenEXR files.

A compositor (Nuke, Blender, Resolve) wants the render as scene-linear floats with its depth
beside it, not an 8-bit PNG and a .npy: `render --exr` writes `<stem>.exr` with the channels
R, G, B (linear), A (0 where a pixel's ray misses the light slab) and, with `--depth`, Z (depth
along the optical axis, scene units), as a renderer writes a single-layer EXR.  Only numpy: the Blender extension imports this module in
Blender's own Python, which has no torch.  The file layout is OpenEXR's ("OpenEXR File Layout",
openexr.com): one part, scanlines, no compression, 32-bit float channels.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from .files import atomic_write_bytes

MAGIC = 20000630
VERSION = 2  # single part, scanlines, short names
FLOAT = 2  # OpenEXR's pixel type for 32-bit float
NO_DEPTH = 1e10  # what Cycles' Depth pass holds where a pixel sees no surface


def srgb_to_linear(rgb: np.ndarray) -> np.ndarray:
    """sRGB-encoded [0, 1] values (the model's colours, as the photos hold them) -> scene-linear."""
    rgb = np.clip(np.asarray(rgb, dtype=np.float32), 0.0, 1.0)
    return np.where(rgb <= 0.04045, rgb / 12.92, ((rgb + 0.055) / 1.055) ** 2.4).astype(np.float32)


def depth_for_compositing(depth: np.ndarray) -> np.ndarray:
    """Depth with NaN (no surface the light field can tell) as NO_DEPTH, as Cycles writes it:
    a compositor's Z Combine then puts CG in front of it, not behind a hole."""
    depth = np.asarray(depth, dtype=np.float32)
    return np.where(np.isfinite(depth), depth, np.float32(NO_DEPTH)).astype(np.float32)


def write_exr(path: str | Path, channels: dict[str, np.ndarray]) -> None:
    """Write (H, W) float channels, row 0 at the top, to an uncompressed OpenEXR file (atomically:
    files.atomic_write_bytes)."""
    if not channels:
        raise ValueError("an EXR file needs at least one channel")
    planes = {name: np.ascontiguousarray(plane, dtype="<f4") for name, plane in sorted(channels.items())}
    shape = next(iter(planes.values())).shape
    if any(plane.shape != shape for plane in planes.values()) or len(shape) != 2:
        raise ValueError("every channel of an EXR file is an image (height, width) of the same size")
    height, width = shape
    if not height or not width:
        raise ValueError("an EXR file holds at least one pixel")
    header = _header(list(planes), width, height)
    line_bytes = 8 + 4 * width * len(planes)  # y, byte count, then each channel's row
    first_line = len(header) + 8 * height  # after the header and the offset table
    offsets = np.arange(height, dtype="<u8") * line_bytes + first_line
    rows = np.stack([planes[name] for name in planes], axis=1)  # (H, channels, W): a scanline's layout
    lines = bytearray()
    for y in range(height):
        lines += struct.pack("<ii", y, 4 * width * len(planes)) + rows[y].tobytes()
    atomic_write_bytes(path, header + offsets.tobytes() + bytes(lines))


def _header(names: list[str], width: int, height: int) -> bytes:
    channel_list = b"".join(name.encode() + b"\0" + struct.pack("<iBBBBii", FLOAT, 0, 0, 0, 0, 1, 1) for name in names)
    box = struct.pack("<iiii", 0, 0, width - 1, height - 1)
    attributes = [("channels", "chlist", channel_list + b"\0"), ("compression", "compression", b"\0"),
                  ("dataWindow", "box2i", box), ("displayWindow", "box2i", box), ("lineOrder", "lineOrder", b"\0"),
                  ("pixelAspectRatio", "float", struct.pack("<f", 1.0)),
                  ("screenWindowCenter", "v2f", struct.pack("<ff", 0.0, 0.0)),
                  ("screenWindowWidth", "float", struct.pack("<f", 1.0))]
    header = struct.pack("<ii", MAGIC, VERSION)
    for name, kind, value in attributes:
        header += name.encode() + b"\0" + kind.encode() + b"\0" + struct.pack("<i", len(value)) + value
    return header + b"\0"


def rendering_channels(rgb: np.ndarray, depth: np.ndarray | None, valid: np.ndarray | None = None
                       ) -> dict[str, np.ndarray]:
    """A rendering's EXR channels: R, G, B scene-linear, Z where depth was rendered, and A where
    `valid` says which rays the light field can represent (1; 0 where a ray misses the slab, whose
    colour is then 0 too: EXR's colours are premultiplied by their alpha)."""
    linear = srgb_to_linear(rgb)
    if valid is not None:
        linear = np.where(np.asarray(valid)[..., None], linear, np.float32(0.0))
    channels = {"R": linear[..., 0], "G": linear[..., 1], "B": linear[..., 2]}
    if valid is not None:
        channels["A"] = np.asarray(valid, dtype=np.float32)
    if depth is not None:
        channels["Z"] = depth_for_compositing(depth)
    return channels

"""Reads an uncompressed OpenEXR file (single- or multi-part scanlines) into numpy, so that
the Blender story can check what F12 wrote to a multilayer EXR -- the file a compositor reads
-- with nothing but numpy (Blender's Python has no OpenEXR module, and loading a multilayer
EXR as an image shows only its first pass).  The layout is OpenEXR's file format
(openexr.com, "OpenEXR File Layout"); only what Blender writes with the codec "None" is read.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

MAGIC = 20000630
MULTIPART_FLAG = 0x1000
PIXEL_TYPES = {0: np.dtype("<u4"), 1: np.dtype("<f2"), 2: np.dtype("<f4")}  # UINT, HALF, FLOAT
NO_COMPRESSION = 0


def _read_header(data: bytes, pos: int) -> tuple[dict[str, bytes], int]:
    """One header's attributes (name -> raw value) and the position after its closing null."""
    header = {}
    while data[pos] != 0:
        name, pos = _read_string(data, pos)
        _kind, pos = _read_string(data, pos)
        (size,) = struct.unpack_from("<i", data, pos)
        header[name] = data[pos + 4:pos + 4 + size]
        pos += 4 + size
    return header, pos + 1


def _read_string(data: bytes, pos: int) -> tuple[str, int]:
    end = data.index(b"\0", pos)
    return data[pos:end].decode(), end + 1


def _channels(raw: bytes) -> list[tuple[str, np.dtype]]:
    """The chlist attribute: names with their pixel types, in the file's (sorted) order."""
    channels, pos = [], 0
    while raw[pos] != 0:
        name, pos = _read_string(raw, pos)
        (pixel_type,) = struct.unpack_from("<i", raw, pos)
        channels.append((name, PIXEL_TYPES[pixel_type]))
        pos += 16  # pixel type, pLinear + 3 reserved bytes, x and y sampling
    return channels


def read_exr(path: str | Path) -> dict[str, np.ndarray]:
    """Every channel as an (H, W) array, row 0 at the top, keyed by its full name
    (Blender's multilayer files: "ViewLayer.Combined.R", "ViewLayer.Depth.Z", ...)."""
    data = Path(path).read_bytes()
    magic, version = struct.unpack_from("<ii", data, 0)
    if magic != MAGIC:
        raise ValueError(f"{path} is not an OpenEXR file")
    multipart = bool(version & MULTIPART_FLAG)
    headers, pos = [], 8
    while True:
        header, pos = _read_header(data, pos)
        headers.append(header)
        if not multipart or data[pos] == 0:
            break
    pos += 1 if multipart else 0  # the empty header that ends a multi-part file's headers
    windows = [struct.unpack("<4i", header["dataWindow"]) for header in headers]
    offset_tables = []
    for x_min, y_min, x_max, y_max in windows:
        lines = y_max - y_min + 1  # uncompressed: one scanline a chunk
        offset_tables.append(struct.unpack_from(f"<{lines}Q", data, pos))
        pos += 8 * lines
    planes = {}
    for header, (x_min, y_min, x_max, y_max), offsets in zip(headers, windows, offset_tables):
        if header["compression"][0] != NO_COMPRESSION:
            raise ValueError(f"{path}: only uncompressed EXR files are read here")
        width, height = x_max - x_min + 1, y_max - y_min + 1
        channels = _channels(header["channels"])
        part = {name: np.empty((height, width), np.float32) for name, _ in channels}
        for offset in offsets:
            chunk = offset + (4 if multipart else 0)  # a multi-part chunk starts with its part number
            (y,) = struct.unpack_from("<i", data, chunk)
            chunk += 8  # y, then the chunk's byte count
            for name, dtype in channels:
                part[name][y - y_min] = np.frombuffer(data, dtype, width, chunk)
                chunk += width * dtype.itemsize
        planes.update(part)
    return planes

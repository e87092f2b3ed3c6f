"""Cem Yuksel's Binary Curve Collection (``.bcc``), the format of public yarn-level cloth models.

Layout (little-endian)::

    bytes  0..2   b"BCC"
    byte   3      0x44: 4-byte integers and 4-byte floats (the only size in use)
    bytes  4..5   curve type: b"C0" uniform Catmull-Rom, b"BS" uniform cubic B-spline,
                  b"BZ" cubic Bezier (3 n + 1 points per curve), b"PL" polyline
    byte   6      dimensions (3)
    byte   7      up dimension (0 = x, 1 = y, 2 = z)
    bytes  8..15  curve count, uint64
    bytes 16..23  total control point count, uint64
    bytes 24..63  file information (free text; not to be trusted)
    then per curve: int32 point count n (negative: a closed loop of |n| points),
                    followed by n float32 triples (x, y, z)

:func:`read_bcc` checks every count against the file's size and refuses anything else
with the reason; :func:`write_bcc` writes the same layout (through a temporary file).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..io import atomic_path

HEADER = struct.Struct("<3sB2sBBQQ40s")   # 64 bytes
TYPES = {b"C0": "catmull_rom", b"BS": "bspline", b"BZ": "bezier", b"PL": "polyline"}
CODES = {v: k for k, v in TYPES.items()}


class BCCError(ValueError):
    """A file that is not a usable Binary Curve Collection (the message says why)."""


@dataclass
class Curve:
    """One curve of a collection: its control points ``[n, 3]`` and whether it is a closed loop."""

    points: np.ndarray
    closed: bool


@dataclass
class CurveCollection:
    curves: list[Curve]
    kind: str = "catmull_rom"      # one of TYPES' values
    up: int = 1                    # 0 = x, 1 = y, 2 = z

    @property
    def point_count(self) -> int:
        return sum(len(c.points) for c in self.curves)


def read_bcc(path) -> CurveCollection:
    """The curves of a ``.bcc`` file; :class:`BCCError` names what is wrong with a bad one."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as e:
        raise BCCError(f"{path}: cannot read ({e.strerror})") from None
    if len(data) < HEADER.size:
        raise BCCError(f"{path}: {len(data)} bytes, shorter than the 64-byte BCC header (truncated, or not a .bcc)")
    magic, sizes, code, dims, up, n_curves, n_points, _info = HEADER.unpack_from(data)
    if magic != b"BCC":
        raise BCCError(f"{path}: not a Binary Curve Collection (starts with {data[:3]!r}, expected b'BCC')")
    if sizes != 0x44:
        raise BCCError(f"{path}: byte 3 is 0x{sizes:02x}; only 0x44 (4-byte integers and floats) is supported")
    if code not in TYPES:
        raise BCCError(f"{path}: curve type {code!r} is not one of {', '.join(t.decode() for t in TYPES)}")
    if dims != 3:
        raise BCCError(f"{path}: {dims} dimensions; only 3D curves are supported")
    if up > 2:
        raise BCCError(f"{path}: up dimension {up} (must be 0, 1 or 2)")
    # each curve takes at least 4 bytes: a count the file cannot hold is refused before reading on
    body = len(data) - HEADER.size
    if n_curves * 4 + n_points * 12 != body:
        raise BCCError(f"{path}: the header promises {n_curves} curves and {n_points} points "
                       f"({n_curves * 4 + n_points * 12} bytes after the header), the file has {body}: "
                       "truncated or corrupt")
    curves, offset, total = [], HEADER.size, 0
    for k in range(n_curves):
        (n,) = struct.unpack_from("<i", data, offset)
        offset += 4
        count = abs(n)
        if offset + 12 * count > len(data):
            raise BCCError(f"{path}: curve {k} claims {count} points, past the end of the file")
        points = np.frombuffer(data, "<f4", 3 * count, offset).reshape(count, 3).astype(np.float64)
        offset += 12 * count
        total += count
        if not np.all(np.isfinite(points)):
            bad = int(np.argmax(~np.isfinite(points).all(1)))
            raise BCCError(f"{path}: curve {k} has a non-finite control point (point {bad}: {points[bad]})")
        curves.append(Curve(points, closed=n < 0))
    if total != n_points:
        raise BCCError(f"{path}: the curves hold {total} points, the header says {n_points}")
    if not curves:
        raise BCCError(f"{path}: holds no curves (a valid header that counts 0); a yarn-level model needs at least "
                       "one yarn")
    return CurveCollection(curves, TYPES[code], up)


def write_bcc(path, collection: CurveCollection, info: str = "bcsdf") -> None:
    """Write ``collection`` as a ``.bcc`` file (through a temporary file)."""
    if collection.kind not in CODES:
        raise BCCError(f"curve type {collection.kind!r} is not one of {', '.join(CODES)}")
    parts = [HEADER.pack(b"BCC", 0x44, CODES[collection.kind], 3, collection.up, len(collection.curves),
                         collection.point_count, info.encode()[:40].ljust(40, b"\0"))]
    for c in collection.curves:
        p = np.asarray(c.points, np.float32).reshape(-1, 3)
        parts.append(struct.pack("<i", -len(p) if c.closed else len(p)))
        parts.append(p.astype("<f4").tobytes())
    with atomic_path(Path(path)) as tmp:
        Path(tmp).write_bytes(b"".join(parts))

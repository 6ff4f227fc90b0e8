"""OpenEXR float depth maps (Pano3D / 3D60 ``*.exr``).

:func:`read_exr` reads through the **OpenEXR** package (``pip install OpenEXR``, the ``pano3d`` extra): every
compression (NONE, RLE, ZIPS, ZIP, PIZ, PXR24, B44, B44A, DWAA, DWAB, HTJ2K, ...), scanline and tiled
single-part files. Without the package it falls back to :func:`read_exr_builtin`, a reader written from the
OpenEXR file layout with no dependency beyond NumPy/zlib (magic ``20000630``, version 2, header attributes, a
chunk offset table, then per chunk ``y``, byte count and the channels of each line in the header's
(alphabetical) order) for single-part **scanline** files with ``NONE``, ``RLE``, ``ZIPS`` or ``ZIP``
compression; any other file is refused with an error naming the file, the feature and the package to install.
(OpenCV reads EXR only when built with it and ``OPENCV_IO_ENABLE_OPENEXR`` is set before ``cv2`` is imported.)

Multi-part and deep files are refused; channels are returned as stored (``HALF`` float16, ``FLOAT`` float32,
``UINT`` uint32). :func:`read_exr_depth` returns one channel as a float32 ``(H, W)`` depth map. A truncated or
corrupt file is an :class:`~omnidl.data.validate.UnreadableFileError` naming it.
"""
from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np

from .validate import UnreadableFileError, invalid

MAGIC = 20000630
_PIXEL = {0: np.dtype("<u4"), 1: np.dtype("<f2"), 2: np.dtype("<f4")}
_COMPRESSION = {0: "NONE", 1: "RLE", 2: "ZIPS", 3: "ZIP", 4: "PIZ", 5: "PXR24", 6: "B44", 7: "B44A", 8: "DWAA",
                9: "DWAB"}
_LINES = {0: 1, 1: 1, 2: 1, 3: 16}


def _cstr(buf: bytes, pos: int, path: Path) -> tuple[str, int]:
    end = buf.find(b"\0", pos)
    if end < 0:
        raise UnreadableFileError(f"truncated EXR header in {path}")
    return buf[pos:end].decode("latin-1"), end + 1


def _header(buf: bytes, path: Path) -> tuple[dict, int]:
    if len(buf) < 8 or struct.unpack_from("<i", buf, 0)[0] != MAGIC:
        raise UnreadableFileError(f"{path} is not an OpenEXR file (no 20000630 magic number)")
    flags = struct.unpack_from("<I", buf, 4)[0]
    if flags & 0xFF != 2:
        raise invalid(path, "EXR version", flags & 0xFF, "2")
    for bit, what in ((0x200, "tiled"), (0x800, "deep"), (0x1000, "multi-part")):
        if flags & bit:
            raise invalid(path, "EXR layout", what, "a single-part scanline image without the OpenEXR package "
                          "(pip install OpenEXR, or omnidl[pano3d])")
    pos, attrs = 8, {}
    while True:
        name, pos = _cstr(buf, pos, path)
        if not name:
            return attrs, pos
        typ, pos = _cstr(buf, pos, path)
        if pos + 4 > len(buf):
            raise UnreadableFileError(f"truncated EXR header in {path}")
        size = struct.unpack_from("<i", buf, pos)[0]
        pos += 4
        attrs[name] = (typ, buf[pos:pos + size])
        pos += size


def _channels(raw: bytes, path: Path) -> list[tuple[str, int]]:
    out, pos = [], 0
    while pos < len(raw) and raw[pos] != 0:
        name, pos = _cstr(raw, pos, path)
        ptype, _, _, xs, ys = struct.unpack_from("<iB3sii", raw, pos)
        pos += 16
        if ptype not in _PIXEL:
            raise invalid(path, f"EXR channel {name!r} pixel type", ptype, "0 (UINT), 1 (HALF) or 2 (FLOAT)")
        if (xs, ys) != (1, 1):
            raise invalid(path, f"EXR channel {name!r} sampling", (xs, ys), "(1, 1)")
        out.append((name, ptype))
    return out


def _undo_predictor(data: bytes) -> bytes:
    t = np.frombuffer(data, np.uint8).astype(np.int64)
    t = (np.cumsum(np.concatenate([t[:1], t[1:] - 128])) % 256).astype(np.uint8)
    half = (len(t) + 1) // 2
    out = np.empty_like(t)
    out[0::2], out[1::2] = t[:half], t[half:]
    return out.tobytes()


def _unrle(data: bytes, path: Path) -> bytes:
    out, i = bytearray(), 0
    while i < len(data):
        n = struct.unpack_from("<b", data, i)[0]
        i += 1
        if n < 0:
            out += data[i:i - n]
            i -= n
        else:
            out += data[i:i + 1] * (n + 1)
            i += 1
    return bytes(out)


def _openexr():
    """The OpenEXR package (3.3 or later: ``OpenEXR.File``), or None."""
    try:
        import OpenEXR
    except ImportError:
        return None
    return OpenEXR if hasattr(OpenEXR, "File") else None


def read_exr(path: str | Path) -> dict[str, np.ndarray]:
    """Every channel of a single-part OpenEXR file as ``{name: (H, W) array}`` (float16/float32/uint32 as stored),
    through the OpenEXR package when it is installed, else :func:`read_exr_builtin` (module docstring)."""
    path = Path(path)
    if not path.is_file():
        raise UnreadableFileError(f"missing file {path} (EXR depth)")
    with open(path, "rb") as f:
        head = f.read(8)
    if len(head) < 8 or struct.unpack_from("<i", head, 0)[0] != MAGIC:
        raise UnreadableFileError(f"{path} is not an OpenEXR file (no 20000630 magic number)")
    exr = _openexr()
    if exr is None:
        return read_exr_builtin(path)
    from .readers import cv2_path
    with cv2_path(path) as name:                                      # a name the native library can take
        try:
            f = exr.File(name, separate_channels=True)
            parts = list(f.parts)
            if len(parts) > 1:
                raise invalid(path, "EXR layout", f"multi-part ({len(parts)} parts)", "a single-part image")
            if not parts:
                raise UnreadableFileError(f"truncated or corrupt EXR file {path} (OpenEXR read no image part)")
            header = f.header()
            kind = str(header.get("type", ""))
            if "deep" in kind:
                raise invalid(path, "EXR layout", "deep", "a flat scanline or tiled image")
            (x0, y0), (x1, y1) = (np.asarray(v).tolist() for v in header["dataWindow"])
            planes = {str(n): np.ascontiguousarray(c.pixels) for n, c in f.channels().items()}
        except (RuntimeError, ValueError, OSError, KeyError, TypeError) as e:
            if isinstance(e, UnreadableFileError):
                raise
            raise UnreadableFileError(f"truncated or corrupt EXR file {path} (OpenEXR: {e})") from e
    w, h = x1 - x0 + 1, y1 - y0 + 1
    for n, a in planes.items():
        if a.shape != (h, w):
            raise invalid(path, f"EXR channel {n!r}", f"of shape {a.shape}", f"({h}, {w}) (the data window; "
                          "subsampled channels are not read)")
    return planes


def read_exr_builtin(path: str | Path) -> dict[str, np.ndarray]:
    """The dependency-free reader (NONE, RLE, ZIPS, ZIP single-part scanline files; module docstring)."""
    path = Path(path)
    if not path.is_file():
        raise UnreadableFileError(f"missing file {path} (EXR depth)")
    buf = path.read_bytes()
    attrs, pos = _header(buf, path)
    for k in ("channels", "compression", "dataWindow"):
        if k not in attrs:
            raise invalid(path, f"EXR header attribute {k!r}", "missing", "a required OpenEXR attribute")
    chans = _channels(attrs["channels"][1], path)
    comp = attrs["compression"][1][0]
    if comp not in _LINES:
        raise invalid(path, "EXR compression", _COMPRESSION.get(comp, comp), "NONE, RLE, ZIPS or ZIP without the "
                      "OpenEXR package (pip install OpenEXR, or omnidl[pano3d], reads every compression)")
    x0, y0, x1, y1 = struct.unpack("<iiii", attrs["dataWindow"][1])
    w, h = x1 - x0 + 1, y1 - y0 + 1
    if w <= 0 or h <= 0:
        raise invalid(path, "EXR dataWindow", (x0, y0, x1, y1), "a non-empty window")
    per_line = sum(_PIXEL[t].itemsize for _, t in chans) * w
    lines = _LINES[comp]
    nchunks = (h + lines - 1) // lines
    if pos + 8 * nchunks > len(buf):
        raise UnreadableFileError(f"truncated EXR file {path} (offset table)")
    offsets = struct.unpack_from(f"<{nchunks}Q", buf, pos)
    planes = {n: np.empty((h, w), _PIXEL[t]) for n, t in chans}
    for off in offsets:
        if off + 8 > len(buf):
            raise UnreadableFileError(f"truncated EXR file {path} (chunk at byte {off} of {len(buf)})")
        y, size = struct.unpack_from("<ii", buf, off)
        data = buf[off + 8:off + 8 + size]
        r0 = y - y0
        n = min(lines, h - r0)
        if len(data) != size or not 0 <= r0 < h:
            raise UnreadableFileError(f"truncated or corrupt EXR file {path} (chunk of line {y})")
        if size < per_line * n:                                     # compressed (else stored raw)
            try:
                data = _unrle(data, path) if comp == 1 else zlib.decompress(data)
            except zlib.error as e:
                raise UnreadableFileError(f"corrupt EXR file {path} (chunk of line {y}: {e})") from e
            data = _undo_predictor(data)
        if len(data) != per_line * n:
            raise UnreadableFileError(f"corrupt EXR file {path} (chunk of line {y} holds {len(data)} bytes, expected "
                                      f"{per_line * n})")
        p = 0
        for r in range(n):
            for name, t in chans:
                nb = _PIXEL[t].itemsize * w
                planes[name][r0 + r] = np.frombuffer(data, _PIXEL[t], w, p)
                p += nb
    return planes


def read_exr_depth(path: str | Path, channel: str | None = None) -> np.ndarray:
    """``(H, W)`` float32 depth from an EXR file: ``channel`` (default: the only channel, else ``Y``, ``R``,
    ``Z`` or ``depth``); NaN/inf are an error naming the file."""
    planes = read_exr(path)
    if channel is None:
        if len(planes) == 1:
            channel = next(iter(planes))
        else:
            channel = next((c for c in ("Y", "R", "Z", "depth", "depth.Y") if c in planes), None)
            if channel is None:
                raise invalid(path, "EXR channels", sorted(planes), "one channel, or one named Y, R, Z or depth "
                              "(pass channel=)")
    if channel not in planes:
        raise invalid(path, "EXR channel", repr(channel), f"one of {sorted(planes)}")
    d = planes[channel].astype(np.float32)
    bad = ~np.isfinite(d)
    if bad.any():
        i, j = np.argwhere(bad)[0]
        raise invalid(path, f"EXR depth channel {channel!r}", f"{d[i, j]} at pixel (row {i}, col {j}) "
                      f"({int(bad.sum())} non-finite value(s))", "finite depths (0 = invalid)")
    return d

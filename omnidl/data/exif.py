"""EXIF orientation of an image file's bytes, read from the header only (no pixel decoding, no size limit).

The orientation tag (EXIF/TIFF tag ``0x0112``, values 1..8) says how the stored pixels must be turned to be
shown upright; viewers, annotation tools and PIL's ``ImageOps.exif_transpose`` apply it. Where it lives:

* JPEG: an ``APP1`` segment starting with ``Exif\\0\\0``, then a TIFF block (EXIF 2.3, section 4.5.4);
* PNG: the ``eXIf`` chunk (PNG extensions 1.5.0), a TIFF block;
* WebP: the ``EXIF`` chunk of the RIFF container (some writers keep the ``Exif\\0\\0`` prefix);
* TIFF: the tag of the file's first IFD (OpenCV's TIFF decoder applies it itself, see :data:`DECODER_APPLIES`).

A TIFF block: byte order ``II`` (little) or ``MM`` (big), 42, the offset of IFD0, then IFD0's 12-byte entries
``(tag, type, count, value)``. Values outside 1..8 are ignored (as PIL does): the image is taken as stored.

:func:`apply_orientation` turns an ``(H, W[, C])`` array exactly as ``exif_transpose`` turns the image.
"""
from __future__ import annotations

import struct

import numpy as np

__all__ = ["image_format", "exif_orientation", "apply_orientation", "jpeg_complete", "DECODER_APPLIES"]

#: formats whose OpenCV decoder already applies the orientation (libtiff's RGBA reader); checked by the tests
DECODER_APPLIES = ("tiff",)


def image_format(data: bytes) -> str:
    """``"jpeg"``, ``"png"``, ``"webp"``, ``"tiff"`` or ``"other"`` from the magic bytes."""
    if data[:3] == b"\xff\xd8\xff":
        return "jpeg"
    if data[:8] == b"\x89PNG\r\n\x1a\n":
        return "png"
    if data[:4] == b"RIFF" and data[8:12] == b"WEBP":
        return "webp"
    if data[:4] in (b"II*\0", b"MM\0*"):
        return "tiff"
    return "other"


def _tiff_orientation(block: bytes) -> int:
    if block[:6] == b"Exif\0\0":
        block = block[6:]
    if len(block) < 8 or block[:2] not in (b"II", b"MM"):
        return 1
    bo = "<" if block[:2] == b"II" else ">"
    if struct.unpack_from(bo + "H", block, 2)[0] != 42:
        return 1
    ifd = struct.unpack_from(bo + "I", block, 4)[0]
    if ifd + 2 > len(block):
        return 1
    n = struct.unpack_from(bo + "H", block, ifd)[0]
    for i in range(n):
        e = ifd + 2 + 12 * i
        if e + 12 > len(block):
            return 1
        tag, typ = struct.unpack_from(bo + "HH", block, e)
        if tag == 0x0112:
            if typ == 3:                                               # SHORT
                v = struct.unpack_from(bo + "H", block, e + 8)[0]
            elif typ == 4:                                             # LONG
                v = struct.unpack_from(bo + "I", block, e + 8)[0]
            else:
                return 1
            return int(v) if 1 <= v <= 8 else 1
    return 1


def _jpeg_segments(data: bytes):
    """``(marker, payload start, payload end)`` of a JPEG's marker segments up to the first SOS (included)."""
    pos = 2
    while pos + 4 <= len(data):
        if data[pos] != 0xFF:
            return
        marker = data[pos + 1]
        if marker == 0xFF:                                             # fill byte
            pos += 1
            continue
        if marker == 0x01 or 0xD0 <= marker <= 0xD7:                   # markers without a length
            pos += 2
            continue
        if marker == 0xD9:
            return
        size = struct.unpack_from(">H", data, pos + 2)[0]
        yield marker, pos + 4, pos + 2 + size
        if marker == 0xDA:                                             # start of scan: entropy-coded data follows
            return
        pos += 2 + size


def jpeg_complete(data: bytes) -> bool:
    """Whether a JPEG has its end-of-image marker after the first scan of the main image (a truncated file has
    not; bytes after the marker, e.g. a motion photo's video, are allowed). ``FF D9`` cannot occur inside
    entropy-coded data (``FF`` is stuffed with ``00`` there), and segments are skipped by their lengths, so an
    EXIF thumbnail's own end marker does not count."""
    sos_end = None
    for marker, _, end in _jpeg_segments(data):
        if marker == 0xDA:
            sos_end = end
    return sos_end is not None and data.find(b"\xff\xd9", sos_end) >= 0


def exif_orientation(data: bytes) -> int:
    """The EXIF orientation (1..8) of a JPEG, PNG or WebP file's bytes; 1 when absent or unreadable.
    TIFF files are read too (their first IFD)."""
    try:
        fmt = image_format(data)
        if fmt == "jpeg":
            for marker, a, b in _jpeg_segments(data):
                if marker == 0xE1 and data[a:a + 6] == b"Exif\0\0":
                    return _tiff_orientation(data[a:b])
            return 1
        if fmt == "png":
            pos = 8
            while pos + 8 <= len(data):
                n = struct.unpack_from(">I", data, pos)[0]
                kind = data[pos + 4:pos + 8]
                if kind == b"eXIf":
                    return _tiff_orientation(data[pos + 8:pos + 8 + n])
                if kind == b"IEND":
                    return 1
                pos += 12 + n
            return 1
        if fmt == "webp":
            pos = 12
            while pos + 8 <= len(data):
                kind = data[pos:pos + 4]
                n = struct.unpack_from("<I", data, pos + 4)[0]
                if kind == b"EXIF":
                    return _tiff_orientation(data[pos + 8:pos + 8 + n])
                pos += 8 + n + (n & 1)
            return 1
        if fmt == "tiff":
            return _tiff_orientation(data)
    except struct.error:
        return 1
    return 1


def apply_orientation(arr: np.ndarray, orientation: int) -> np.ndarray:
    """Turn ``(H, W[, C])`` pixels as stored into the upright view (PIL ``exif_transpose`` semantics):
    2 mirror, 3 rotate 180°, 4 flip, 5 transpose, 6 rotate 90° clockwise, 7 transverse, 8 rotate 90°
    counter-clockwise."""
    if orientation == 2:
        out = arr[:, ::-1]
    elif orientation == 3:
        out = arr[::-1, ::-1]
    elif orientation == 4:
        out = arr[::-1]
    elif orientation == 5:
        out = arr.swapaxes(0, 1)
    elif orientation == 6:
        out = np.rot90(arr, -1)
    elif orientation == 7:
        out = arr.swapaxes(0, 1)[::-1, ::-1]
    elif orientation == 8:
        out = np.rot90(arr, 1)
    else:
        return arr
    return np.ascontiguousarray(out)

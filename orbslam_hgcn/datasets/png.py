"""PNG decoding for the dataset readers, about twice as fast as OpenCV's on their images.

TUM RGB-D, EuRoC and KITTI store every frame as a PNG, and decoding one took longer than
extracting its ORB features: 5.7 ms for a 640x480 colour frame of TUM fr3 and 3.3 ms for a
1241x376 KITTI one through ``cv2.imread`` on a 2.6 GHz Xeon, 4.4 ms of it zlib's inflate
on the 640x480 renders. Here the compressed stream is inflated by Intel's ISA-L (the
``isal`` package, about 2.5 times zlib's speed) and the rows are unfiltered, and turned
grey, by one compiled loop (2.5, 1.6 and 4.7 ms for those three).

It gives the pixels ``cv2.imread`` gives, bit for bit: BGR order for colour, and for grey
from colour the conversion OpenCV asks libpng for (``png_set_rgb_to_gray`` with weights
0.299 and 0.587, which libpng turns into (9797 R + 19234 G + 3737 B) >> 15). It takes the
common case only: 8-bit grey or RGB, not interlaced, with no chunk that could change the
pixels (gamma, colour profile, transparency). Anything else, or a file that fails its
checks (signature, chunk CRCs, stream length, filter types), returns None and the caller
decodes it with OpenCV, which reads every PNG and reports a corrupt one.

PNG: ISO/IEC 15948:2004 (W3C PNG Specification, 2nd edition); the filters of its Sec. 9.
"""

from __future__ import annotations

import struct
import time

import numpy as np
from isal import isal_zlib

from orbslam_hgcn.compiled import jit

SIGNATURE = b"\x89PNG\r\n\x1a\n"
# Chunks that leave an 8-bit grey or RGB image's pixels as they are (text, time, pixel
# size); any other ancillary chunk sends the file to OpenCV.
_PASSIVE = frozenset({b"tEXt", b"zTXt", b"iTXt", b"tIME", b"pHYs"})
_CHANNELS = {0: 1, 2: 3}  # colour type -> samples per pixel


@jit
def _paeth(a, b, c):  # pragma: no cover - compiled
    """The Paeth predictor of a byte from its left (a), upper (b) and upper-left (c)
    neighbours, as int32; branch-free comparisons."""
    bc = b - c
    d = a - c
    pa, pb, pc = abs(bc), abs(d), abs(d + bc)
    r = b if pb <= pc else c
    return a if (pa <= pb) & (pa <= pc) else r


@jit
def _unfilter(raw, h, w, bpp, rows, gray):  # pragma: no cover - compiled
    """Undo the row filters of an inflated 8-bit PNG stream ``raw`` ((h * (w * bpp + 1),)
    uint8: a filter byte, then the row). ``rows``: (h, w * bpp) uint8 that receives the
    samples, or (2, w * bpp) used as two alternating rows when ``gray`` ((h, w) uint8)
    receives libpng's grey of an RGB image instead. Returns False for an unknown filter.

    The left neighbours of the 1- and 3-sample cases stay in registers: each byte depends
    on the one a pixel before it, so that chain is the loop's speed.
    """
    stride = w * bpp
    n_rows = rows.shape[0]
    zero = np.zeros(stride, np.uint8)
    pos = 0
    for y in range(h):
        f = raw[pos]
        pos += 1
        row = rows[y % n_rows]
        prev = rows[(y - 1) % n_rows] if y > 0 else zero
        if f == 0:
            for x in range(stride):
                row[x] = raw[pos + x]
        elif f == 2:
            for x in range(stride):
                row[x] = raw[pos + x] + prev[x]
        elif f > 4:
            return False
        elif bpp == 3:
            a0, a1, a2 = np.int32(0), np.int32(0), np.int32(0)  # the pixel to the left
            c0, c1, c2 = np.int32(0), np.int32(0), np.int32(0)  # the one above that
            for x in range(0, stride, 3):
                r0, r1, r2 = np.int32(raw[pos + x]), np.int32(raw[pos + x + 1]), np.int32(raw[pos + x + 2])
                b0, b1, b2 = np.int32(prev[x]), np.int32(prev[x + 1]), np.int32(prev[x + 2])
                if f == 1:
                    a0, a1, a2 = (r0 + a0) & 255, (r1 + a1) & 255, (r2 + a2) & 255
                elif f == 3:
                    a0, a1, a2 = (r0 + ((a0 + b0) >> 1)) & 255, (r1 + ((a1 + b1) >> 1)) & 255, (r2 + ((a2 + b2) >> 1)) & 255
                else:
                    a0 = (r0 + _paeth(a0, b0, c0)) & 255
                    a1 = (r1 + _paeth(a1, b1, c1)) & 255
                    a2 = (r2 + _paeth(a2, b2, c2)) & 255
                    c0, c1, c2 = b0, b1, b2
                row[x], row[x + 1], row[x + 2] = a0, a1, a2
        elif bpp == 1:
            a, c = np.int32(0), np.int32(0)
            for x in range(stride):
                r, b = np.int32(raw[pos + x]), np.int32(prev[x])
                if f == 1:
                    a = (r + a) & 255
                elif f == 3:
                    a = (r + ((a + b) >> 1)) & 255
                else:
                    a = (r + _paeth(a, b, c)) & 255
                    c = b
                row[x] = a
        else:
            return False
        if gray.size:
            g = gray[y]
            for x in range(w):
                g[x] = (9797 * np.int32(row[3 * x]) + 19234 * np.int32(row[3 * x + 1])
                        + 3737 * np.int32(row[3 * x + 2])) >> 15  # fmt: skip
        pos += stride
    return True


def decode_png(data: bytes, color: bool = False) -> np.ndarray | None:
    """The pixels of a PNG file's bytes as ``cv2.imread`` gives them with IMREAD_GRAYSCALE
    ((H, W) uint8) or, with ``color``, IMREAD_COLOR ((H, W, 3) uint8 BGR); None for a file
    this decoder does not take (see the module docstring), to be decoded by OpenCV."""
    view = memoryview(data)
    if len(data) < 45 or view[:8] != SIGNATURE or view[12:16] != b"IHDR":
        return None
    w, h, depth, ctype, method, filt, interlace = struct.unpack(">IIBBBBB", view[16:29])
    if depth != 8 or ctype not in _CHANNELS or method or filt or interlace or not (0 < w < 1 << 16 and 0 < h < 1 << 16):
        return None
    parts = []
    pos = 8
    while True:
        if pos + 12 > len(data):
            return None  # truncated before IEND
        (n,) = struct.unpack(">I", view[pos : pos + 4])
        kind = bytes(view[pos + 4 : pos + 8])
        end = pos + 8 + n
        if end + 4 > len(data):
            return None
        if kind in (b"IHDR", b"IDAT") and isal_zlib.crc32(view[pos + 4 : end]) != struct.unpack(">I", view[end : end + 4])[0]:
            return None
        if kind == b"IDAT":
            parts.append(view[pos + 8 : end])
        elif kind == b"IEND":
            break
        elif kind != b"IHDR" and kind not in _PASSIVE:
            return None
        pos = end + 4
    bpp = _CHANNELS[ctype]
    size = h * (w * bpp + 1)
    try:
        raw = isal_zlib.decompress(b"".join(parts), bufsize=size)
    except isal_zlib.error:
        return None
    if len(raw) != size:
        return None
    raw = np.frombuffer(raw, np.uint8)
    to_gray = bpp == 3 and not color
    rows = np.empty((2 if to_gray else h, w * bpp), np.uint8)
    gray = np.empty((h, w) if to_gray else (0, 0), np.uint8)
    if not _unfilter(raw, h, w, bpp, rows, gray):
        return None
    if to_gray:
        return gray
    if bpp == 1:
        return np.repeat(rows[:, :, None], 3, axis=2) if color else rows
    return np.ascontiguousarray(rows.reshape(h, w, 3)[:, :, ::-1])  # RGB -> BGR


def warm_up() -> float:
    """Compile (first run after an install) or load from the cache the row kernel, as the
    decoder calls it; returns the seconds it took."""
    t0 = time.perf_counter()
    raw = np.frombuffer(bytes([0, 0, 0, 0, 0, 0, 0, 4, 0, 0, 0, 0, 0, 0]), np.uint8)  # read-only, as decoded
    _unfilter(raw, 2, 2, 3, np.empty((2, 6), np.uint8), np.empty((2, 2), np.uint8))
    _unfilter(raw[:6], 2, 2, 1, np.empty((2, 2), np.uint8), np.empty((0, 0), np.uint8))
    return time.perf_counter() - t0

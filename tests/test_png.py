"""The PNG decoder of the dataset readers against OpenCV's, pixel for pixel."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from orbslam_hgcn.datasets.base import read_image
from orbslam_hgcn.datasets.png import SIGNATURE, decode_png
from orbslam_hgcn.errors import DatasetError


def chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))


def paeth(a: int, b: int, c: int) -> int:
    p = a + b - c
    pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
    return a if pa <= pb and pa <= pc else (b if pb <= pc else c)


def encode(pixels: np.ndarray, filters: list[int], extra: bytes = b"", ctype: int | None = None) -> bytes:
    """A PNG of (H, W) grey or (H, W, 3) RGB uint8 ``pixels`` whose row y is written with
    filter ``filters[y]`` (the specification's Sec. 9 filters, applied here by the book)."""
    h, w = pixels.shape[:2]
    bpp = 1 if pixels.ndim == 2 else 3
    rows = pixels.reshape(h, w * bpp).astype(np.int64)
    out = bytearray()
    for y in range(h):
        f = filters[y]
        out.append(f)
        for x in range(w * bpp):
            a = int(rows[y, x - bpp]) if x >= bpp else 0
            b = int(rows[y - 1, x]) if y > 0 else 0
            c = int(rows[y - 1, x - bpp]) if x >= bpp and y > 0 else 0
            pred = (0, a, b, (a + b) // 2, paeth(a, b, c))[f]
            out.append((int(rows[y, x]) - pred) & 255)
    ctype = (0 if bpp == 1 else 2) if ctype is None else ctype
    ihdr = struct.pack(">IIBBBBB", w, h, 8, ctype, 0, 0, 0)
    return SIGNATURE + chunk(b"IHDR", ihdr) + extra + chunk(b"IDAT", zlib.compress(bytes(out))) + chunk(b"IEND", b"")


def cv2_decode(data: bytes, color: bool) -> np.ndarray:
    return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR if color else cv2.IMREAD_GRAYSCALE)


@pytest.mark.parametrize("channels", [1, 3])
@pytest.mark.parametrize("first", range(5))
def test_every_filter_decodes_as_opencv_does(channels, first):
    """Rows written with each of the five filters, the first row with ``first`` (where the
    row above counts as zeros), on noise and on smooth ramps (where Paeth picks each of
    its three neighbours): the decoder's grey and colour pixels are OpenCV's."""
    rng = np.random.default_rng(first * 10 + channels)
    h, w = 23, 17  # odd sizes: no row is a multiple of a vector width
    shape = (h, w) if channels == 1 else (h, w, 3)
    noise = rng.integers(0, 256, shape, dtype=np.uint8)
    yy, xx = np.mgrid[0:h, 0:w]
    ramp = ((3 * xx + 7 * yy) % 256).astype(np.uint8)
    smooth = ramp if channels == 1 else np.stack([ramp, ramp[::-1], 255 - ramp], axis=2)
    filters = [first] + [int(f) for f in rng.integers(0, 5, h - 1)]
    for pixels in (noise, smooth):
        data = encode(pixels, filters)
        for color in (False, True):
            ours, ref = decode_png(data, color), cv2_decode(data, color)
            assert ours is not None
            assert ours.shape == ref.shape and ours.dtype == np.uint8
            assert np.array_equal(ours, ref)
    if channels == 3:  # and the samples themselves, in BGR order
        assert np.array_equal(decode_png(encode(noise, filters), True), noise[:, :, ::-1])


def real_images(folder: Path, n: int) -> list[Path]:
    paths = sorted(folder.glob("*.png"))
    assert len(paths) >= min(n, 19), folder
    return paths[:: max(1, len(paths) // n)]


def test_real_frames_decode_as_opencv_does(tum_sample, kitti_sample, euroc_sample):
    """The frames of the three shipped samples (TUM's 640x480 RGB, KITTI's and EuRoC's grey,
    written by three different encoders) read as ``cv2.imread`` reads them."""
    folders = {tum_sample / "rgb": 19, kitti_sample / "image_0": 10, euroc_sample / "mav0" / "cam0" / "data": 10}
    for folder, n in folders.items():
        for path in real_images(folder, n):
            data = path.read_bytes()
            for color, flag in ((False, cv2.IMREAD_GRAYSCALE), (True, cv2.IMREAD_COLOR)):
                ours = decode_png(data, color)
                assert ours is not None, path
                assert np.array_equal(ours, cv2.imread(str(path), flag)), path
                assert np.array_equal(read_image(path, color=color), ours)


def test_files_it_does_not_take_go_to_opencv(tmp_path):
    """What the decoder does not take returns None, and read_image then gives OpenCV's
    pixels or, for a broken file, a DatasetError naming it."""
    rng = np.random.default_rng(3)
    rgb = rng.integers(0, 256, (9, 11, 3), dtype=np.uint8)
    good = encode(rgb, [4] * 9)
    assert decode_png(good) is not None
    # 16-bit samples and a gamma chunk: valid files that OpenCV reads (and scales, or may
    # correct), not this decoder.
    path16 = tmp_path / "deep.png"
    cv2.imwrite(str(path16), (rng.integers(0, 65536, (9, 11), dtype=np.uint16)))
    gamma = encode(rgb, [4] * 9, extra=chunk(b"gAMA", struct.pack(">I", 45455)))
    for data in (path16.read_bytes(), gamma):
        assert decode_png(data) is None
    assert np.array_equal(read_image(path16), cv2.imread(str(path16), cv2.IMREAD_GRAYSCALE))
    (tmp_path / "gamma.png").write_bytes(gamma)
    assert np.array_equal(read_image(tmp_path / "gamma.png"), cv2_decode(gamma, False))

    ihdr_at = len(SIGNATURE)
    interlaced = bytearray(good)
    interlaced[ihdr_at + 8 + 12] = 1  # IHDR's interlace byte, CRC made to match
    interlaced[ihdr_at + 21 : ihdr_at + 25] = struct.pack(">I", zlib.crc32(bytes(interlaced[ihdr_at + 4 : ihdr_at + 21])))
    idat_at = good.index(b"IDAT")
    flipped = bytearray(good)
    flipped[idat_at + 10] ^= 0x40  # a bit of the compressed stream: IDAT's CRC no longer matches
    bad_filter = encode(rgb, [4] * 9)
    raw = bytearray(zlib.decompress(bad_filter[idat_at + 4 : bad_filter.index(b"IEND") - 8]))
    raw[3 * (11 * 3 + 1)] = 7  # the fourth row's filter byte: no such filter
    bad_filter = SIGNATURE + chunk(b"IHDR", good[ihdr_at + 8 : ihdr_at + 21]) + chunk(b"IDAT", zlib.compress(bytes(raw))) + chunk(b"IEND", b"")
    short = encode(rgb[:8], [4] * 8).replace(struct.pack(">II", 11, 8), struct.pack(">II", 11, 9), 1)
    short = short[: ihdr_at + 21] + struct.pack(">I", zlib.crc32(short[ihdr_at + 4 : ihdr_at + 21])) + short[ihdr_at + 25 :]
    cases = {
        "interlaced": bytes(interlaced), "flipped": bytes(flipped), "bad_filter": bad_filter,
        "short_stream": short, "truncated": good[: len(good) - 20], "not_png": b"GIF89a" + good[6:],
        "palette": encode(rgb[:, :, 0], [0] * 9, extra=chunk(b"PLTE", bytes(range(256)) * 3), ctype=3),
    }
    for name, data in cases.items():
        assert decode_png(data) is None, name
    for name in ("flipped", "bad_filter", "truncated"):
        path = tmp_path / f"{name}.png"
        path.write_bytes(cases[name])
        ref = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if ref is None:
            with pytest.raises(DatasetError, match=f"{name}.png: cannot read image"):
                read_image(path)
        else:  # what OpenCV makes of it, never a result of this decoder's
            assert np.array_equal(read_image(path), ref), name

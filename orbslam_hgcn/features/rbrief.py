"""Compiled ORB orientation moments and rBRIEF descriptors, equal to OpenCV's.

``cv2.ORB.compute`` on a level image copies it into a bordered buffer, blurs it and
describes the keypoints it is handed as ``cv2.KeyPoint`` objects, one Python object per
keypoint. Here the level image is blurred once and every keypoint is described by one
compiled loop (:func:`rbrief`); the intensity-centroid moments are a compiled loop as well
(:func:`ic_moments`).

The 256 test pairs of OpenCV's 31-pixel patch are the learned pattern of Rublee et al.,
"ORB: an efficient alternative to SIFT or SURF", ICCV 2011. They are not copied here: they
are read off the installed OpenCV by :func:`probe_pattern`, which describes keypoints on
step images and decodes each bit's two sample points from the steps at which it flips.
:func:`opencv_rbrief` then checks the compiled descriptor against ``cv2.ORB.compute`` on a
noise image with random orientations (a pattern read off before is kept in the user's cache,
``rbrief/`` of :func:`~orbslam_hgcn.outputs.cache_root`, per OpenCV version, and goes through the same check, so a
process skips the 45 ms of reading it again), with each candidate blur (with OpenCV 5.0, ORB's
smoothing equals a separable float Gaussian and not the fixed-point ``cv2.GaussianBlur``,
which differs by a grey level here and there), and keeps the blur that matches bit for
bit; when none does, the extractor stays with ``cv2.ORB.compute``.
"""

from __future__ import annotations

import functools
import logging
import math
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from orbslam_hgcn.compiled import jit
from orbslam_hgcn.outputs import cache_root

log = logging.getLogger(__name__)

_BLUR_SIZE, _BLUR_SIGMA = 7, 2.0  # ORB's smoothing before the binary tests (7x7, sigma 2)
_GAUSS = cv2.getGaussianKernel(_BLUR_SIZE, _BLUR_SIGMA)
# 1.5 * 2**23: adding and subtracting it rounds a float32 below 2**22 to the nearest
# integer, ties to even, as cvRound does on x86.
_ROUND = np.float32(12582912.0)
_DEG_TO_RAD = np.float32(math.pi / 180.0)  # (float)(CV_PI / 180.f), as OpenCV's ORB


def _blur_separable(image: np.ndarray) -> np.ndarray:
    return cv2.sepFilter2D(image, -1, _GAUSS, _GAUSS, borderType=cv2.BORDER_REFLECT_101)


def _blur_gaussian(image: np.ndarray) -> np.ndarray:
    size = (_BLUR_SIZE, _BLUR_SIZE)
    return cv2.GaussianBlur(image, size, _BLUR_SIGMA, _BLUR_SIGMA, borderType=cv2.BORDER_REFLECT_101)


_BLURS: tuple[Callable[[np.ndarray], np.ndarray], ...] = (_blur_separable, _blur_gaussian)


@jit
def ic_moments(image, x, y, umax):  # pragma: no cover - compiled
    """(N, 2) float32 moments (m10, m01) of the circular patch of rows ``|u| <= umax[|v|]``
    around each keypoint (x, y) (N,) of a (H, W) uint8 image; integer sums, so exact."""
    n = len(x)
    half = len(umax) - 1
    out = np.empty((n, 2), np.float32)
    for k in range(n):
        cx, cy = x[k], y[k]
        m10 = 0
        m01 = 0
        row = image[cy]
        for u in range(-half, half + 1):
            m10 += u * np.int64(row[cx + u])
        for v in range(1, half + 1):
            d = umax[v]
            below, above = image[cy + v], image[cy - v]
            v_sum = 0
            for u in range(-d, d + 1):
                p = np.int64(below[cx + u])
                m = np.int64(above[cx + u])
                v_sum += p - m
                m10 += u * (p + m)
            m01 += v * v_sum
        out[k, 0] = m10
        out[k, 1] = m01
    return out


@jit
def rbrief(blurred, x, y, angle, px, py, out):  # pragma: no cover - compiled
    """rBRIEF descriptors into ``out`` (N, B/8) uint8 of keypoints (x, y) (N,) int with
    orientation ``angle`` (N,) float32 degrees, on a blurred (H, W) uint8 image.

    px, py: (2B,) float32 test points (pairs of consecutive points, bit j of byte i from
    pair 8i + j: set when the first point is darker). The points are rotated and rounded in
    float32 as OpenCV's computeOrbDescriptors does.
    """
    step = blurred.shape[1]
    flat = blurred.ravel()
    n_points = len(px)
    offsets = np.empty(n_points, np.int32)
    for k in range(len(x)):
        rad = np.float32(angle[k]) * _DEG_TO_RAD
        a = np.float32(math.cos(np.float64(rad)))
        b = np.float32(math.sin(np.float64(rad)))
        for q in range(n_points):
            rx = (px[q] * a - py[q] * b + _ROUND) - _ROUND
            ry = (px[q] * b + py[q] * a + _ROUND) - _ROUND
            offsets[q] = np.int32(ry) * step + np.int32(rx)
        center = y[k] * step + x[k]
        for i in range(out.shape[1]):
            val = 0
            for j in range(8):
                q = 16 * i + 2 * j
                if flat[center + offsets[q]] < flat[center + offsets[q + 1]]:
                    val |= 1 << j
            out[k, i] = val


def probe_pattern(orb: cv2.ORB, patch_size: int) -> np.ndarray | None:
    """(B, 4) int64 test pairs (x1, y1, x2, y2) of ``orb`` (a one-level ``cv2.ORB`` with
    ``patch_size``), or None if they cannot be decoded.

    Every keypoint (orientation 0) lies on its own tile holding a step along x, y or the
    diagonal x + y, bright on one side of an offset t. After the blur, the step is a
    profile f(s - t) of the coordinate s along its direction, flat outside a few pixels
    around t, so a bit, "point 1 darker than point 2", is set exactly for the t at which
    f(s1 - t) < f(s2 - t). Over a range of t that pattern of set bits names (s1, s2) (or
    says s1 == s2): it is looked up among the patterns of all candidate pairs, computed
    on the blurred tiles themselves. Two of the three directions give both points.
    """
    half = patch_size // 2
    # (direction, coordinate range of the test points along it)
    families = (((1, 0), half + 1), ((0, 1), half + 1), ((1, 1), 2 * half + 2))
    cases = [(d, pol, t) for d, r in families for pol in (1, -1) for t in range(-r - 8, r + 9)]
    tile = 2 * (half + 12)
    cols = int(math.ceil(math.sqrt(len(cases))))
    rows = -(-len(cases) // cols)
    pad = 2 * patch_size
    image = np.zeros((rows * tile + 2 * pad, cols * tile + 2 * pad), np.uint8)
    yy, xx = np.mgrid[0:tile, 0:tile] - tile // 2
    centres = []
    for k, (d, pol, t) in enumerate(cases):
        r, c = divmod(k, cols)
        bright = (d[0] * xx + d[1] * yy >= t) == (pol > 0)
        y0, x0 = pad + r * tile, pad + c * tile
        image[y0 : y0 + tile, x0 : x0 + tile] = 255 * bright
        centres.append((x0 + tile // 2, y0 + tile // 2))
    kps = [cv2.KeyPoint(float(cx), float(cy), float(patch_size), 0.0) for cx, cy in centres]
    out, desc = orb.compute(image, kps)
    if desc is None or len(out) != len(kps):
        return None
    bits = np.unpackbits(desc, axis=1, bitorder="little")  # (cases, B)
    blurred = [blur(image) for blur in _BLURS]
    decoded = {}
    for d, r in families:
        sel = [k for k, case in enumerate(cases) if case[0] == d]
        cand = np.arange(-r, r + 1)
        # Sample points at coordinate s = cand along d, inside the tile.
        if d == (1, 0):
            dx, dy = cand, np.zeros_like(cand)
        elif d == (0, 1):
            dx, dy = np.zeros_like(cand), cand
        else:
            dy = cand // 2
            dx = cand - dy
        seen = bytes(np.packbits(bits[sel].T, axis=1).ravel())
        found = None
        for img in blurred:  # the decoding is the same for any blur that is a smooth step
            prof = np.stack([img[centres[k][1] + dy, centres[k][0] + dx] for k in sel]).astype(np.int16)
            pred = (prof[:, :, None] < prof[:, None, :]).reshape(len(sel), -1).T  # (s1 * s2, cases)
            keys = np.packbits(pred, axis=1)
            table: dict[bytes, list[int]] = {}
            for idx, key in enumerate(map(bytes, keys)):
                table.setdefault(key, []).append(idx)
            width = keys.shape[1]
            vals = []
            for i in range(bits.shape[1]):
                hit = table.get(seen[i * width : (i + 1) * width])
                if hit is None:
                    break
                # One pair, or the class of all pairs s1 == s2 (no bit ever set).
                vals.append(tuple(cand[list(divmod(hit[0], len(cand)))]) if len(hit) == 1 else None)
            else:
                found = vals
                break
        if found is None:
            return None
        decoded[d] = found
    pairs = []
    for xs, ys, ss in zip(decoded[(1, 0)], decoded[(0, 1)], decoded[(1, 1)]):
        if xs is None and ys is None or (xs is None or ys is None) and ss is None:
            return None
        if xs is None:  # x1 == x2: from the diagonal
            xs = (ss[0] - ys[0], ss[1] - ys[1])
        if ys is None:
            ys = (ss[0] - xs[0], ss[1] - xs[1])
        if ss is not None and (ss[0] != xs[0] + ys[0] or ss[1] != xs[1] + ys[1]):
            return None
        pairs.append((xs[0], ys[0], xs[1], ys[1]))
    return np.asarray(pairs, dtype=np.int64)


@dataclass(frozen=True, eq=False)
class CompiledRBrief:
    """rBRIEF as OpenCV's ORB computes it: the blur and the test points it uses."""

    blur: Callable[[np.ndarray], np.ndarray]
    px: np.ndarray  # (2B,) float32 test point x
    py: np.ndarray  # (2B,) float32 test point y
    reach: int  # no rotated test point lies farther than this (pixels, per axis) from the keypoint

    def describe(self, image: np.ndarray, x: np.ndarray, y: np.ndarray, angle: np.ndarray) -> np.ndarray:
        """(N, B/8) uint8 descriptors of keypoints (x, y) (N,) int with orientation
        ``angle`` (N,) degrees on a (H, W) uint8 image; every test point must lie in it."""
        out = np.empty((len(x), len(self.px) // 16), np.uint8)
        if len(x) == 0:
            return out
        h, w = image.shape
        x = np.asarray(x, np.int64)
        y = np.asarray(y, np.int64)
        r = self.reach
        if x.min() < r or y.min() < r or x.max() >= w - r or y.max() >= h - r:
            raise ValueError(f"keypoints closer than {r} px to the image border cannot be described")
        rbrief(self.blur(image), x, y, np.asarray(angle, np.float32), self.px, self.py, out)
        return out


@functools.lru_cache(maxsize=4)
def opencv_rbrief(patch_size: int, edge_threshold: int) -> CompiledRBrief | None:
    """The compiled rBRIEF that equals ``cv2.ORB.compute`` (``patch_size``,
    ``edge_threshold``) bit for bit on a check image, or None (use OpenCV's)."""
    orb = cv2.ORB_create(nfeatures=1, nlevels=1, edgeThreshold=edge_threshold, patchSize=patch_size)
    cached = _read_pattern(patch_size, edge_threshold)
    if cached is not None:
        found = _checked(orb, cached, patch_size, edge_threshold)
        if found is not None:
            return found
    pattern = probe_pattern(orb, patch_size)
    if pattern is None:
        log.info("could not read ORB's test pattern off OpenCV %s; describing with OpenCV", cv2.__version__)
        return None
    found = _checked(orb, pattern, patch_size, edge_threshold)
    if found is not None:
        _write_pattern(patch_size, edge_threshold, pattern)
        return found
    log.info("the compiled rBRIEF differs from OpenCV %s's; describing with OpenCV", cv2.__version__)
    return None


def _pattern_file(patch_size: int, edge_threshold: int) -> Path:
    """Where the test pattern read off this OpenCV is kept between runs (the user's cache)."""
    return cache_root() / "rbrief" / f"opencv-{cv2.__version__}-patch{patch_size}-edge{edge_threshold}.npy"


def _read_pattern(patch_size: int, edge_threshold: int) -> np.ndarray | None:
    """The pattern kept by an earlier run (None: none, or unreadable); it is used only after
    :func:`_checked` finds it describes as OpenCV does."""
    try:
        pattern = np.load(_pattern_file(patch_size, edge_threshold), allow_pickle=False)
    except (OSError, ValueError):
        return None
    if pattern.ndim != 2 or pattern.shape[1] != 4 or pattern.dtype.kind != "i" or not len(pattern):
        return None
    return pattern.astype(np.int64)


def _write_pattern(patch_size: int, edge_threshold: int, pattern: np.ndarray) -> None:
    path = _pattern_file(patch_size, edge_threshold)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f".{os.getpid()}.tmp.npy")
        np.save(tmp, np.asarray(pattern, np.int64))
        os.replace(tmp, path)
    except OSError as exc:  # a read-only home: probe again next time
        log.debug("could not keep the rBRIEF pattern in %s: %s", path, exc)


def _checked(orb: cv2.ORB, pattern: np.ndarray, patch_size: int, edge_threshold: int) -> CompiledRBrief | None:
    """The compiled rBRIEF of ``pattern`` when it equals ``orb.compute`` bit for bit on a
    check image with each candidate blur in turn (None: with neither)."""
    points = pattern.reshape(-1, 2).astype(np.float32)
    # A rotated point rounds to at most its distance from the keypoint, rounded.
    reach = int(np.floor(np.linalg.norm(points, axis=1).max() + 0.5))
    # A check image: noise smoothed a little (so the tests are not all ties or all edges),
    # keypoints anywhere they can be described, any orientation.
    rng = np.random.default_rng(0)
    noise = rng.integers(0, 256, (160, 200), dtype=np.uint8)
    image = cv2.GaussianBlur(noise, (3, 3), 0.8)
    margin = max(reach, edge_threshold)
    n = 400
    x = rng.integers(margin, image.shape[1] - margin, n)
    y = rng.integers(margin, image.shape[0] - margin, n)
    angle = rng.uniform(0.0, 360.0, n).astype(np.float32)
    kps = [cv2.KeyPoint(float(u), float(v), float(patch_size), float(a)) for u, v, a in zip(x, y, angle)]
    out, want = orb.compute(image, kps)
    if want is None or len(out) != n:
        return None
    for blur in _BLURS:
        candidate = CompiledRBrief(blur, np.ascontiguousarray(points[:, 0]), np.ascontiguousarray(points[:, 1]), reach)
        if np.array_equal(candidate.describe(image, x, y, angle), want):
            return candidate
    return None

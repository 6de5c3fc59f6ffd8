"""Procedural surface textures for the synthetic scenes.

A texture is built in three layers, all in metric units so that its statistics do not
depend on the texel size:

1. multi-octave value noise (octave amplitudes falling with frequency, an approximately
   1/f spectrum like natural images), optionally stretched along one axis (wood grain);
2. a "dead leaves" layer: opaque shapes (rectangles, ellipses, blobs, outlines, stripes)
   with sizes spread log-uniformly over many octaves, painted largest first, whose
   scale-invariant statistics resemble natural images (Lee, Mumford and Huang, "Occlusion
   models for natural images", IJCV 2001);
3. printed marks: glyph strings (``cv2.putText``) and line segments at several sizes and
   contrasts, and optional grid joints (planks, ceiling tiles).

Every surface draws its texture from its own random generator, so the same seed always
gives the same pixels.
"""

from __future__ import annotations

import logging
import string
from dataclasses import dataclass

import cv2
import numpy as np

log = logging.getLogger(__name__)

_SHIFT = 4  # fractional bits for sub-texel drawing with cv2
_ONE = 1 << _SHIFT
_FONTS = (
    cv2.FONT_HERSHEY_SIMPLEX,
    cv2.FONT_HERSHEY_DUPLEX,
    cv2.FONT_HERSHEY_COMPLEX,
    cv2.FONT_HERSHEY_TRIPLEX,
    cv2.FONT_HERSHEY_PLAIN,
    cv2.FONT_HERSHEY_SCRIPT_SIMPLEX,
)
_CHARS = string.ascii_letters + string.digits + "#%&+-=/<>@"


@dataclass(frozen=True)
class TextureStyle:
    """Parameters of one family of surfaces (BGR colours, sizes in metres)."""

    palette: tuple[tuple[int, int, int], ...]  # base colours to pick from
    noise_contrast: float = 22.0  # std of the value-noise layer in grey levels
    grain: float = 1.0  # value-noise cells this many times longer along u (wood grain)
    leaves: float = 0.06  # fraction of the area covered by shapes, per octave of size
    shape_contrast: float = 0.7  # mean colour distance of shapes from the base (0..1)
    min_shape_m: float = 0.004  # smallest shape size
    max_shape_m: float = 0.5  # largest shape size (also capped by the surface size)
    glyphs: float = 0.005  # strings per (area / size^2), per octave of size (~1.2x coverage)
    lines: float = 0.05  # segments per (area / size^2), per octave of size (~0.1x coverage)
    grid_m: tuple[float, float] = (0.0, 0.0)  # joint spacing along u, v (0: no joints)


STYLES: dict[str, TextureStyle] = {
    "floor": TextureStyle(
        palette=((60, 90, 130), (80, 110, 150), (70, 75, 85), (100, 120, 140)),
        noise_contrast=30.0, grain=6.0, leaves=0.09, shape_contrast=0.9, min_shape_m=0.012,
        max_shape_m=0.6, glyphs=0.004, lines=0.05, grid_m=(1.2, 0.18),
    ),
    "wall": TextureStyle(
        palette=((200, 205, 210), (170, 190, 200), (185, 200, 185), (150, 160, 190)),
        noise_contrast=22.0, leaves=0.1, shape_contrast=0.95, min_shape_m=0.015, max_shape_m=0.8,
        glyphs=0.01, lines=0.04,
    ),
    "ceiling": TextureStyle(
        palette=((215, 215, 215), (200, 205, 210)),
        noise_contrast=14.0, leaves=0.03, shape_contrast=0.4, min_shape_m=0.006,
        max_shape_m=0.3, glyphs=0.001, lines=0.02, grid_m=(0.6, 0.6),
    ),
    "wood": TextureStyle(
        palette=((70, 120, 170), (50, 95, 140), (90, 140, 185)),
        noise_contrast=24.0, grain=8.0, leaves=0.06, shape_contrast=0.7,
        max_shape_m=0.35, glyphs=0.015, lines=0.03,
    ),
    "print": TextureStyle(
        palette=((40, 40, 170), (160, 90, 30), (40, 150, 60), (30, 160, 200), (220, 220, 220), (60, 60, 60)),
        noise_contrast=16.0, leaves=0.09, shape_contrast=0.85, min_shape_m=0.003,
        max_shape_m=0.25, glyphs=0.03, lines=0.05,
    ),
    "furniture": TextureStyle(
        palette=((110, 110, 110), (60, 70, 80), (150, 140, 120), (90, 110, 150)),
        noise_contrast=22.0, grain=3.0, leaves=0.07, shape_contrast=0.75,
        max_shape_m=0.4, glyphs=0.01, lines=0.08,
    ),
    "screen": TextureStyle(
        palette=((90, 50, 30), (40, 40, 40), (200, 200, 200)),
        noise_contrast=10.0, leaves=0.08, shape_contrast=0.9, min_shape_m=0.003,
        max_shape_m=0.2, glyphs=0.05, lines=0.1,
    ),
}


def value_noise(rng: np.random.Generator, h: int, w: int, cell_u: float, cell_v: float,
                interpolation: int = cv2.INTER_CUBIC) -> np.ndarray:
    """(h, w) float32 smooth noise of unit variance per lattice node, lattice spacing in texels."""
    cell_u = max(cell_u, 1.0)
    cell_v = max(cell_v, 1.0)
    gh = int(np.ceil(h / cell_v)) + 4
    gw = int(np.ceil(w / cell_u)) + 4
    grid = rng.standard_normal((gh, gw), dtype=np.float32)
    ox, oy = rng.uniform(1.0, 2.0, 2)
    # dst (x, y) samples the lattice at (ox + x / cell_u, oy + y / cell_v), bicubically.
    M = np.array([[1.0 / cell_u, 0.0, ox], [0.0, 1.0 / cell_v, oy]])
    return cv2.warpAffine(grid, M, (w, h), flags=interpolation | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_REFLECT)


def fractal_noise(rng: np.random.Generator, h: int, w: int, texel_m: float, largest_m: float,
                  grain: float = 1.0, hurst: float = 0.7, smallest_px: float = 2.0) -> np.ndarray:
    """(h, w) float32 multi-octave value noise with zero mean and unit standard deviation.

    Octave sizes halve from ``largest_m`` down to ``smallest_px`` texels; the amplitude of an octave of
    size ``s`` is ``s ** hurst`` (a 1/f-like spectrum for hurst near 1). Octaves coarser
    than 16 texels are summed on an 8x smaller grid and upsampled once; finer ones are
    interpolated linearly.
    """
    coarse_f = 8
    ch, cw = -(-h // coarse_f) + 1, -(-w // coarse_f) + 1
    coarse = np.zeros((ch, cw), np.float32)
    out = np.zeros((h, w), np.float32)
    s = largest_m
    while s / texel_m >= smallest_px:
        amp = np.float32(s ** hurst)
        cell = s / texel_m
        if cell >= 16.0:
            coarse += amp * value_noise(rng, ch, cw, grain * cell / coarse_f, cell / coarse_f)
        else:
            out += amp * value_noise(rng, h, w, grain * cell, cell, cv2.INTER_LINEAR)
        s *= 0.5
    M = np.array([[1.0 / coarse_f, 0.0, 0.0], [0.0, 1.0 / coarse_f, 0.0]])
    out += cv2.warpAffine(coarse, M, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_REPLICATE)
    out -= np.float32(out.mean())
    std = float(out.std())
    return out / np.float32(std) if std > 0 else out


def _colours(rng: np.random.Generator, n: int, base: np.ndarray, style: TextureStyle) -> np.ndarray:
    """(n, 3) float shape colours: palette colours, dark/bright accents or random ones,
    each mixed towards ``base`` by a random contrast."""
    pal = np.asarray(style.palette, np.float64)[rng.integers(len(style.palette), size=n)]
    pal += rng.normal(0, 35, (n, 3))
    accent = np.where(rng.random((n, 1)) < 0.5, 25.0, 235.0) + rng.normal(0, 12, (n, 3))
    rand = rng.uniform(0, 255, (n, 3))
    rand = 0.5 * rand + 0.5 * rand.mean(1, keepdims=True)  # muted, not neon
    r = rng.random((n, 1))
    c = np.where(r < 0.45, pal, np.where(r < 0.75, accent, rand))
    k = np.clip(rng.normal(style.shape_contrast, 0.25, (n, 1)), 0.12, 1.0)
    return np.clip(base + k * (c - base), 0, 255)


def _pts(xy: np.ndarray) -> np.ndarray:
    return np.round(np.asarray(xy) * _ONE).astype(np.int32)


def _draw_leaves(img: np.ndarray, rng: np.random.Generator, size_px: np.ndarray,
                 colours: np.ndarray) -> None:
    """Draw one octave of dead-leaves shapes.

    size_px: (n,) shape sizes in texels; colours: (n, 3). Centres are uniform on the image.
    """
    n = len(size_px)
    if n == 0:
        return
    h, w = img.shape[:2]
    cxy = rng.uniform(0, 1, (n, 2)) * [w, h]
    kind = rng.random(n)
    ang = np.where(rng.random(n) < 0.5, rng.uniform(0, np.pi, n), rng.integers(0, 4, n) * np.pi / 2)
    aspect = np.exp(rng.normal(0, 0.6, n))
    half = 0.5 * size_px[:, None] * np.stack([np.sqrt(aspect), 1 / np.sqrt(aspect)], 1)
    thick = np.maximum(1, np.round(size_px * rng.uniform(0.03, 0.12, n))).astype(int)
    # Rotated rectangle corners for every shape (used by rectangles and outlines).
    unit = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], np.float64)
    ca, sa = np.cos(ang), np.sin(ang)
    local = unit[None] * half[:, None, :]
    corners = np.stack([local[..., 0] * ca[:, None] - local[..., 1] * sa[:, None],
                        local[..., 0] * sa[:, None] + local[..., 1] * ca[:, None]], -1) + cxy[:, None]
    corners_i = _pts(corners)
    centre_i = _pts(cxy).tolist()
    axes_i = _pts(half).tolist()
    deg = np.degrees(ang).tolist()
    col = [tuple(c) for c in colours.tolist()]
    aa = cv2.LINE_AA
    for i in range(n):
        k = kind[i]
        if k < 0.32:
            cv2.fillConvexPoly(img, corners_i[i], col[i], aa, _SHIFT)
        elif k < 0.5:
            cv2.ellipse(img, centre_i[i], axes_i[i], deg[i], 0, 360, col[i], -1, aa, _SHIFT)
        elif k < 0.64:  # blob: star-shaped polygon with a random radius per vertex
            m = int(rng.integers(7, 16))
            t = np.sort(rng.uniform(0, 2 * np.pi, m))
            r = np.exp(0.35 * rng.standard_normal(m))
            poly = cxy[i] + np.stack([r * np.cos(t) * half[i, 0], r * np.sin(t) * half[i, 1]], 1)
            cv2.fillPoly(img, [_pts(poly)], col[i], aa, _SHIFT)
        elif k < 0.76:
            cv2.polylines(img, [corners_i[i]], True, col[i], int(thick[i]), aa, _SHIFT)
        elif k < 0.84:
            cv2.ellipse(img, centre_i[i], axes_i[i], deg[i], 0, 360, col[i], int(thick[i]), aa, _SHIFT)
        elif k < 0.93:  # stripes: barcode-like bars across the rectangle
            m = int(rng.integers(3, 12))
            p0, p1, p3 = corners[i, 0], corners[i, 1], corners[i, 3]
            offs = rng.uniform(0, 1, m)
            widths = rng.uniform(0.02, 0.1, m) * size_px[i] / max(np.linalg.norm(p1 - p0), 1e-9)
            for o, wd in zip(offs, widths):
                a0 = p0 + o * (p1 - p0)
                a1 = p0 + min(o + wd, 1.0) * (p1 - p0)
                quad = np.array([a0, a1, a1 + (p3 - p0), a0 + (p3 - p0)])
                cv2.fillConvexPoly(img, _pts(quad), col[i], aa, _SHIFT)
        else:
            tri = cxy[i] + rng.uniform(-0.6, 0.6, (3, 2)) * size_px[i]
            cv2.fillConvexPoly(img, _pts(tri), col[i], aa, _SHIFT)


def _stamp(img: np.ndarray, cxy: np.ndarray, half: np.ndarray, ang: np.ndarray, kind: str,
           colours: np.ndarray, ring: float = 1.0, chunk: int = 4096) -> None:
    """Paint many small rotated shapes at once: a vectorised path for marks under ~16 texels.

    cxy: (n, 2) centres (x, y) in texels; half: (n, 2) half sizes; ang: (n,) radians;
    kind: "rect", "ellipse" or "ring" (a rectangle outline ``ring`` texels wide);
    colours: (n, 3). Texel centres inside a shape take its colour; within a call, shapes
    are painted in order of size.
    """
    h, w = img.shape[:2]
    extent = np.hypot(half[:, 0], half[:, 1])
    order = np.argsort(extent, kind="stable")  # similar sizes together: tight local windows
    for i0 in range(0, len(cxy), chunk):
        sl = order[i0:i0 + chunk]
        reach = int(np.ceil(extent[sl].max())) + 1
        off = np.arange(-reach, reach + 1, dtype=np.float32)
        dx, dy = (g.ravel() for g in np.meshgrid(off, off))
        base = np.round(cxy[sl])
        fx, fy = (cxy[sl] - base).astype(np.float32).T
        x = dx[None] - fx[:, None]  # (m, K) texel centres relative to the shape centres
        y = dy[None] - fy[:, None]
        ca = np.cos(ang[sl]).astype(np.float32)[:, None]
        sa = np.sin(ang[sl]).astype(np.float32)[:, None]
        lx = np.abs(x * ca + y * sa)
        ly = np.abs(y * ca - x * sa)
        A = half[sl, 0:1].astype(np.float32)
        B = half[sl, 1:2].astype(np.float32)
        if kind == "ellipse":
            inside = (lx / A) ** 2 + (ly / B) ** 2 <= 1.0
        else:
            inside = (lx <= A) & (ly <= B)
            if kind == "ring":
                inside &= (lx > A - ring) | (ly > B - ring)
        k, j = np.nonzero(inside)
        X = base[k, 0].astype(np.int64) + dx[j].astype(np.int64)
        Y = base[k, 1].astype(np.int64) + dy[j].astype(np.int64)
        ok = (X >= 0) & (X < w) & (Y >= 0) & (Y < h)
        img[Y[ok], X[ok]] = np.round(colours[sl][k[ok]]).astype(np.uint8)


def _stamp_leaves(img: np.ndarray, rng: np.random.Generator, size_px: np.ndarray, colours: np.ndarray) -> None:
    """Small dead-leaves shapes (rectangles, ellipses, outlines), vectorised."""
    n = len(size_px)
    h, w = img.shape[:2]
    aspect = np.exp(rng.normal(0, 0.6, n))
    half = np.maximum(0.5 * size_px[:, None] * np.stack([np.sqrt(aspect), 1 / np.sqrt(aspect)], 1), 0.6)
    ang = np.where(rng.random(n) < 0.5, rng.uniform(0, np.pi, n), rng.integers(0, 4, n) * np.pi / 2)
    cxy = rng.uniform(0, 1, (n, 2)) * [w, h]
    kind = rng.random(n)
    for name, sel in (("rect", kind < 0.5), ("ellipse", (kind >= 0.5) & (kind < 0.8)), ("ring", kind >= 0.8)):
        _stamp(img, cxy[sel], half[sel], ang[sel], name, colours[sel])


def _draw_glyphs(img: np.ndarray, rng: np.random.Generator, height_px: np.ndarray,
                 colours: np.ndarray) -> None:
    """Printed strings; height_px: (n,) letter heights in texels; colours: (n, 3)."""
    h, w = img.shape[:2]
    for hp, col in zip(height_px.tolist(), colours.tolist()):
        font = _FONTS[int(rng.integers(len(_FONTS)))]
        scale = hp / 22.0  # Hershey capitals are about 22 units tall at scale 1
        thick = max(1, int(round(scale * rng.uniform(1.0, 3.0))))
        text = "".join(rng.choice(list(_CHARS), int(rng.integers(2, 14))))
        org = (int(rng.integers(-w // 20, w)), int(rng.integers(0, h + int(hp))))
        cv2.putText(img, text, org, font, scale, tuple(col), thick, cv2.LINE_AA)


def _draw_lines(img: np.ndarray, rng: np.random.Generator, length_px: np.ndarray,
                colours: np.ndarray) -> None:
    """Straight segments (cables, edges, pens); length_px: (n,) in texels; colours: (n, 3)."""
    h, w = img.shape[:2]
    n = len(length_px)
    p0 = rng.uniform(0, 1, (n, 2)) * [w, h]
    ang = rng.uniform(0, 2 * np.pi, n)
    p1 = p0 + length_px[:, None] * np.stack([np.cos(ang), np.sin(ang)], 1)
    thick = np.maximum(1, np.round(length_px * rng.uniform(0.01, 0.05, n))).astype(int).tolist()
    for a, b, t, c in zip(_pts(p0).tolist(), _pts(p1).tolist(), thick, colours.tolist()):
        cv2.line(img, a, b, tuple(c), t, cv2.LINE_AA, _SHIFT)


def _draw_grid(img: np.ndarray, rng: np.random.Generator, texel_m: float, base: np.ndarray,
               grid_m: tuple[float, float]) -> None:
    """Joints between planks or tiles: dark lines every grid_m, rows staggered along u."""
    h, w = img.shape[:2]
    gu, gv = grid_m[0] / texel_m, grid_m[1] / texel_m
    dark = tuple(float(v) for v in np.clip(base * 0.45, 0, 255))
    thick = max(1, int(round(0.003 / texel_m)))
    n_rows = int(np.ceil(h / gv)) + 1
    for r in range(n_rows):
        y = r * gv
        cv2.line(img, _pts([0, y]), _pts([w, y]), dark, thick, cv2.LINE_AA, _SHIFT)
        x = rng.uniform(0, gu)
        while x < w:
            cv2.line(img, _pts([x, y]), _pts([x, y + gv]), dark, thick, cv2.LINE_AA, _SHIFT)
            x += gu


def make_texture(rng: np.random.Generator, height: int, width: int, texel_m: float,
                 style: TextureStyle) -> np.ndarray:
    """Generate one surface texture.

    height, width: texture size in texels (rows run along the surface's v axis);
    texel_m: texel edge length in metres. Returns (height, width, 3) uint8 BGR.
    """
    h, w = int(height), int(width)
    area_m2 = h * w * texel_m * texel_m
    base = np.asarray(style.palette[int(rng.integers(len(style.palette)))], np.float64)
    base = np.clip(base + rng.normal(0, 12, 3), 30, 235)
    largest = min(1.5, max(h, w) * texel_m)
    lum = fractal_noise(rng, h, w, texel_m, largest, style.grain)
    img = np.empty((h, w, 3), np.float32)
    tint = rng.normal(0, 0.25, 3).astype(np.float32)
    for c in range(3):
        img[..., c] = base[c] + style.noise_contrast * (1.0 + tint[c]) * lum
    chroma = fractal_noise(rng, h, w, texel_m, largest, 1.0, smallest_px=16.0) * (0.3 * style.noise_contrast)
    img[..., 2] += chroma
    img[..., 0] -= chroma
    np.clip(img, 0, 255, out=img)
    img = img.astype(np.uint8)
    if style.grid_m[0] > 0:
        _draw_grid(img, rng, texel_m, base, style.grid_m)

    # Dead leaves, text and lines octave by octave, largest first so that small marks lie on
    # top; counts per octave scale as area / size^2 (scale invariance).
    smax = min(style.max_shape_m, 0.7 * min(h, w) * texel_m)
    smin = max(style.min_shape_m, 6.0 * texel_m)  # smaller marks would be sub-pixel
    s = smax
    while s >= smin:
        per_s2 = area_m2 / (s * s)
        n = int(rng.poisson(style.leaves * per_s2))
        size_px = s / texel_m * np.exp(rng.uniform(-0.35, 0.35, n))
        small = s / texel_m < 12.0  # marks this small are drawn in one vectorised pass
        (_stamp_leaves if small else _draw_leaves)(img, rng, size_px, _colours(rng, n, base, style))
        if 0.003 <= s <= 0.1:
            n = int(rng.poisson(style.glyphs * per_s2))
            _draw_glyphs(img, rng, 0.5 * s / texel_m * np.exp(rng.uniform(-0.35, 0.35, n)),
                         _colours(rng, n, base, style))
        n = int(rng.poisson(style.lines * per_s2))
        _draw_lines(img, rng, 2.0 * s / texel_m * np.exp(rng.uniform(-0.7, 0.7, n)), _colours(rng, n, base, style))
        s *= 0.5
    return img


def tile_patch(patch: np.ndarray, patch_texel_m: float, height: int, width: int,
               texel_m: float) -> np.ndarray:
    """Fill a (height, width) texture of texel ``texel_m`` by repeating ``patch`` at its metric size.

    patch: (h, w, 3) uint8 with texel ``patch_texel_m``. Returns (height, width, 3) uint8.
    """
    k = patch_texel_m / texel_m
    ph = max(1, int(round(patch.shape[0] * k)))
    pw = max(1, int(round(patch.shape[1] * k)))
    interp = cv2.INTER_AREA if k < 1 else cv2.INTER_LINEAR
    scaled = cv2.resize(patch, (pw, ph), interpolation=interp)
    reps = (int(np.ceil(height / ph)), int(np.ceil(width / pw)), 1)
    return np.tile(scaled, reps)[:height, :width].copy()

"""Rendering of large scenes (streets): textures made on first sight, kept in a bounded
cache, and far surfaces drawn as one coarse tile.

:class:`LodSceneRenderer` renders like :class:`SceneRenderer` (same warps, z-test, edge
blending), with two differences:

* a surface's texture is made (by the ``textures`` provider), lit and cut into tiles the
  first time one of its tiles is drawn, and surfaces unused for longest are dropped when
  the cache passes ``cache_mb``; textures are deterministic, so a dropped surface comes
  back identical;
* tiles are at least ``min_tile`` texels wide (coarse textures get longer tiles);
* every surface of more than one tile also has a coarse copy (texels ``2 ** coarse_level``
  times larger, the whole surface in one or a few tiles), drawn instead of its tiles when
  the whole surface lies in front of the camera, its farthest corner at most ``lod_ratio``
  times as far as its nearest, and its nearest point needs mip level ``coarse_level`` or
  coarser anyway. Far facades and road cells then cost one warp instead of dozens, and
  draw at the level of their nearest point, as a single tile does.
"""

from __future__ import annotations

import logging

import cv2
import numpy as np

from orbslam_hgcn.synth.lighting import contact_edges, shading
from orbslam_hgcn.synth.render import (
    BLOCK,
    TILE_M,
    SceneRenderer,
    _bordered,
    _tile_bounds,
    _tile_geometry,
    _tile_levels,
)
from orbslam_hgcn.synth.scene import Scene
from orbslam_hgcn.geometry.camera import PinholeCamera

log = logging.getLogger(__name__)

_ONE_TILE_M = 1e6  # a tile edge no surface reaches: one tile (up to TILE texels) per surface


class LodSceneRenderer(SceneRenderer):
    """Renders a :class:`Scene` whose textures come from ``textures``: ``textures[i]`` an
    (nv, nu, 3) uint8 BGR image of quad i with ``textures.shape(i) == (nv, nu)``, sides
    multiples of 16."""

    def __init__(self, scene: Scene, camera: PinholeCamera, textures, tile_m: float = TILE_M,
                 coarse_level: int = 2, lod_ratio: float = 2.0, cache_mb: float = 1024.0, min_tile: int = 192):
        self.scene = scene
        self.camera = camera
        self.lod_bias = 0.0
        self.textures = textures
        self.coarse_level = coarse_level
        self.lod_ratio = lod_ratio
        self.cache_bytes = cache_mb * 2 ** 20
        self._contacts = contact_edges(scene)
        self.tiles = []
        self._bounds: list[tuple[int, int, int, int]] = []
        self._quad_tiles: list[list[int]] = []
        coarse_of = []  # per tile: index into the coarse groups, or -1
        is_coarse = []
        self._coarse_sizes: dict[int, tuple[int, int]] = {}
        groups = []  # quads with a coarse copy
        for i, q in enumerate(scene.quads):
            nv, nu = textures.shape(i)
            tu, tv = q.size_u / nu, q.size_v / nv
            bounds = _tile_bounds(nu, nv, tu, tv, max(tile_m, min_tile * max(tu, tv)))
            sets = [(bounds, tu, tv, False)]
            if len(bounds) > 1 and coarse_level > 0:
                f = 2 ** coarse_level
                cnu, cnv = (BLOCK * max(1, int(np.ceil(n / f / BLOCK))) for n in (nu, nv))
                self._coarse_sizes[i] = (cnv, cnu)
                ctu, ctv = q.size_u / cnu, q.size_v / cnv
                sets.append((_tile_bounds(cnu, cnv, ctu, ctv, _ONE_TILE_M), ctu, ctv, True))
                groups.append(i)
            mine = []
            for bs, a, b, coarse in sets:
                for bd in bs:
                    mine.append(len(self.tiles))
                    self.tiles.append(_tile_geometry(q, i, bd, a, b, None))
                    self._bounds.append(bd)
                    is_coarse.append(coarse)
                    coarse_of.append(len(groups) - 1 if i in self._coarse_sizes else -1)
            self._quad_tiles.append(mine)
        self._index_tiles()
        self._is_coarse = np.array(is_coarse)
        self._group_of_tile = np.array(coarse_of)
        self._group_quads = np.array(groups, dtype=int)
        quads = scene.quads
        self._group_origin = np.array([quads[i].origin for i in groups]).reshape(-1, 3)
        self._group_normal = np.array([quads[i].normal for i in groups]).reshape(-1, 3)
        nv_nu = np.array([textures.shape(i) for i in groups]).reshape(-1, 2)
        self._group_texel_area = np.array([quads[i].size_u * quads[i].size_v for i in groups]).reshape(-1) / np.maximum(
            nv_nu.prod(axis=1), 1)
        ct = np.flatnonzero(self._is_coarse)
        self._coarse_tiles = ct
        self._coarse_group = self._group_of_tile[ct]
        self._loaded: dict[int, int] = {}  # quad -> bytes
        self._last_used: dict[int, int] = {}
        self._frame = 0
        self.cache_used = 0
        self.last_draw_count = 0
        self.textures_made = 0

    def _choose(self, visible: np.ndarray, Xc: np.ndarray, C_s: np.ndarray) -> np.ndarray:
        if len(self._group_quads) == 0:
            return visible
        g = len(self._group_quads)
        z = Xc[self._coarse_tiles, :, 2]
        zmin = np.full(g, np.inf)
        zmax = np.full(g, -np.inf)
        np.minimum.at(zmin, self._coarse_group, z.min(axis=1))
        np.maximum.at(zmax, self._coarse_group, z.max(axis=1))
        e = np.abs(np.einsum("ij,ij->i", C_s[None] - self._group_origin, self._group_normal))
        cam = self.camera
        with np.errstate(divide="ignore", invalid="ignore"):
            rho2 = np.maximum(zmin, 1e-6) ** 3 / (self._group_texel_area * cam.fx * cam.fy * np.maximum(e, 1e-9))
            level = 0.5 * np.log2(rho2) + 0.5
        use = (zmin > 0.1) & (zmax < self.lod_ratio * zmin) & (level >= self.coarse_level)
        grp = self._group_of_tile
        on = np.where(grp >= 0, use[np.maximum(grp, 0)] == self._is_coarse, True)
        return visible & on

    def _levels(self, i: int) -> list[np.ndarray]:
        tile = self.tiles[i]
        q = tile.quad_index
        if tile.levels is None:
            self._load(q)
        self._last_used[q] = self._frame
        return tile.levels

    def _load(self, q: int) -> None:
        tex = np.asarray(self.textures[q], np.uint8)
        nv, nu = self.textures.shape(q)
        if tex.shape[:2] != (nv, nu):
            raise ValueError(f"texture {q}: {tex.shape[1]}x{tex.shape[0]} texels, expected {nu}x{nv}")
        if len(self.scene.lights) or len(self._contacts[q]):
            shade = shading(self.scene.quads[q], self.scene.lights, nv, nu, self._contacts[q])
            tex = cv2.multiply(tex, cv2.merge([shade, shade, shade]), dtype=cv2.CV_8U)
        full = _bordered(tex)
        small = None
        size = 0
        for i in self._quad_tiles[q]:
            if self._is_coarse[i]:
                if small is None:
                    cnv, cnu = self._coarse_sizes[q]
                    small = _bordered(cv2.resize(tex, (cnu, cnv), interpolation=cv2.INTER_AREA))
                levels = _tile_levels(small, *self._bounds[i])
            else:
                levels = _tile_levels(full, *self._bounds[i])
            self.tiles[i].levels = levels
            size += sum(lv.nbytes for lv in levels)
        self._loaded[q] = size
        self.cache_used += size
        self.textures_made += 1

    def _evict(self) -> None:
        if self.cache_used <= self.cache_bytes:
            return
        for q in sorted(self._loaded, key=lambda k: self._last_used.get(k, -1)):
            if self._last_used.get(q, -1) >= self._frame or self.cache_used <= 0.8 * self.cache_bytes:
                break
            for i in self._quad_tiles[q]:
                self.tiles[i].levels = None
            self.cache_used -= self._loaded.pop(q)

    def render(self, T_wc: np.ndarray, background: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        self._frame += 1
        out = super().render(T_wc, background)
        self._evict()
        return out

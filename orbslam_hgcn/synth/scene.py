"""Geometry of synthetic scenes: textured planar rectangles, boxes, rooms, ray casting.

A scene lives in its own frame (metres, z up, floor at z = 0) and is placed in the world
by ``T_world_scene``. Every surface is a one-sided :class:`Quad`; closed objects are boxes
of five or six quads. The office layout itself is built in ``layout``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

log = logging.getLogger(__name__)

UP = np.array([0.0, 0.0, 1.0])

# Target texel size (metres) per kind of surface: about 1 mm for things seen from
# 0.5-1.5 m, a few millimetres for room surfaces seen from 1.5 m and beyond.
TEXEL = {
    "object": 0.0011,
    "desk": 0.0012,
    "furniture": 0.0025,
    "poster": 0.002,
    "floor": 0.003,
    "wall": 0.0035,
    "ceiling": 0.006,
}


@dataclass(frozen=True, eq=False)
class Quad:
    """A textured one-sided rectangle in the scene frame.

    Its points are ``origin + a * u_axis + b * v_axis`` for a in [0, size_u], b in
    [0, size_v]; it is seen from the side of ``normal = v_axis x u_axis`` (seen from there,
    u runs to the right and v downwards, like image columns and rows).
    origin, u_axis, v_axis: (3,) float64, the axes orthonormal.
    """

    origin: np.ndarray
    u_axis: np.ndarray
    v_axis: np.ndarray
    size_u: float
    size_v: float
    texel: float  # target texel size in metres
    style: str  # a key of textures.STYLES
    label: str  # the object the face belongs to

    @cached_property
    def normal(self) -> np.ndarray:
        return np.cross(self.v_axis, self.u_axis)

    @cached_property
    def corners(self) -> np.ndarray:
        """(4, 3) corners in order origin, +u, +u+v, +v."""
        u = self.u_axis * self.size_u
        v = self.v_axis * self.size_v
        return np.stack([self.origin, self.origin + u, self.origin + u + v, self.origin + v])


@dataclass
class Scene:
    """quads in the scene frame; T_world_scene (4, 4) places the scene frame in the world;
    lights (L, 3) point lights (scene frame) used for baked shading; layout: JSON-able
    description of the room and objects."""

    quads: list[Quad]
    T_world_scene: np.ndarray = field(default_factory=lambda: np.eye(4))
    lights: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    layout: dict = field(default_factory=dict)


def face(centre, normal, down, size_u: float, size_v: float, style: str, label: str,
         texel: float) -> Quad:
    """A quad centred at ``centre`` facing ``normal``, its v axis as close to ``down`` as possible."""
    n = np.asarray(normal, np.float64)
    n = n / np.linalg.norm(n)
    v = np.asarray(down, np.float64) - np.dot(down, n) * n
    v /= np.linalg.norm(v)
    u = np.cross(n, v)
    origin = np.asarray(centre, np.float64) - 0.5 * size_u * u - 0.5 * size_v * v
    return Quad(origin, u, v, float(size_u), float(size_v), float(texel), style, label)


def box_quads(centre, size, R=None, style: str = "print", label: str = "box", texel: float | None = None,
              bottom: bool = False) -> list[Quad]:
    """The faces of a box: centre (3,), size (3,) edge lengths along the box axes (columns of R)."""
    R = np.eye(3) if R is None else np.asarray(R, np.float64)
    h = 0.5 * np.asarray(size, np.float64)
    c = np.asarray(centre, np.float64)
    texel = TEXEL["object"] if texel is None else texel
    out = []
    for axis in range(3):
        for sign in (1.0, -1.0):
            if axis == 2 and sign < 0 and not bottom:
                continue
            n = sign * R[:, axis]
            down = -sign * R[:, 1] if axis == 2 else -R[:, 2]
            vdir = down - np.dot(down, n) * n
            vdir /= np.linalg.norm(vdir)
            udir = np.cross(n, vdir)
            su = 2.0 * float(np.abs(R.T @ udir) @ h)
            sv = 2.0 * float(np.abs(R.T @ vdir) @ h)
            # Bottom faces are rarely seen (and then in shadow): coarser texels.
            tx = 3.0 * texel if (axis == 2 and sign < 0) else texel
            out.append(face(c + n * h[axis], n, down, su, sv, style, label, tx))
    return out


def rot_z(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rot_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def room_quads(x0: float, x1: float, y0: float, y1: float, height: float, margin: float = 0.1) -> list[Quad]:
    """Floor, ceiling and four walls facing inwards, each extended by ``margin`` past the
    corners (hidden behind its neighbours) so that no seam opens along the edges."""
    cx, cy = 0.5 * (x0 + x1), 0.5 * (y0 + y1)
    lx, ly = x1 - x0 + 2 * margin, y1 - y0 + 2 * margin
    hz = height + 2 * margin
    f, w, c = TEXEL["floor"], TEXEL["wall"], TEXEL["ceiling"]
    return [
        face([cx, cy, 0.0], UP, [0, -1, 0], lx, ly, "floor", "floor", f),
        face([cx, cy, height], -UP, [0, 1, 0], lx, ly, "ceiling", "ceiling", c),
        face([x0, cy, 0.5 * height], [1, 0, 0], -UP, ly, hz, "wall", "wall_x0", w),
        face([x1, cy, 0.5 * height], [-1, 0, 0], -UP, ly, hz, "wall", "wall_x1", w),
        face([cx, y0, 0.5 * height], [0, 1, 0], -UP, lx, hz, "wall", "wall_y0", w),
        face([cx, y1, 0.5 * height], [0, -1, 0], -UP, lx, hz, "wall", "wall_y1", w),
    ]


def raycast(scene: Scene, origins_w: np.ndarray, dirs_w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First surface hit along rays, exactly.

    origins_w, dirs_w: (N, 3) world-frame ray origins and directions (any length).
    Returns ((N,) ray parameter s of the hit, point = origin + s * dir, inf for a miss;
    (N,) int index of the quad hit, -1 for a miss). Only the visible side of a quad is hit.
    """
    R, t = scene.T_world_scene[:3, :3], scene.T_world_scene[:3, 3]
    o = (np.asarray(origins_w, np.float64).reshape(-1, 3) - t) @ R
    d = np.asarray(dirs_w, np.float64).reshape(-1, 3) @ R
    O = np.stack([q.origin for q in scene.quads])  # (Q, 3)
    U = np.stack([q.u_axis for q in scene.quads])
    V = np.stack([q.v_axis for q in scene.quads])
    n = np.cross(V, U)
    size = np.array([[q.size_u, q.size_v] for q in scene.quads])  # (Q, 2)
    denom = d @ n.T  # (N, Q)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.einsum("qk,qk->q", O, n)[None] - o @ n.T
        s = s / denom
    P = o[:, None, :] + s[..., None] * d[:, None, :] - O[None]  # (N, Q, 3) relative to quad origins
    a = np.einsum("nqk,qk->nq", P, U)
    b = np.einsum("nqk,qk->nq", P, V)
    hit = (denom < 0) & (s > 0) & (a >= 0) & (a <= size[None, :, 0]) & (b >= 0) & (b <= size[None, :, 1])
    s = np.where(hit, s, np.inf)
    idx = np.argmin(s, axis=1)
    best = s[np.arange(len(s)), idx]
    return best, np.where(np.isfinite(best), idx, -1)

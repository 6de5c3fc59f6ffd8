"""Textures, sunlight and sky of the synthetic street scenes (``street``).

Every surface starts from the procedural textures of ``textures`` (value noise,
dead leaves, marks) in a street style, with what makes it a street on top:

* ground: asphalt, kerb stones, paving and yards chosen per texel by the distance to the
  route centreline (so corners curve), dashed centre lines, darker gutters and tyre
  tracks; the means of each material are fixed for the whole scene, so neighbouring
  ground cells match;
* buildings: plaster with rows of windows (frames, dark glass with reflections, sills,
  some shutters) per floor, a darker plinth;
* cars: paint with door seams, handles and wheel arches; windows with pillars; wheels
  with rims; lights and number plates front and back; signs on poles; bark; foliage.

Sunlight is baked in: each face is lit by a directional sun and the sky (Lambert, a face
turned away keeps the ambient 55 %), and the ground carries the sun shadows of every box
(buildings, cars, trees dappled, poles), cast analytically, plus a dark patch under each
car. Surface ``i`` draws from ``numpy.random.default_rng([texture_seed, i])``.
The sky is drawn per frame behind everything (:class:`SkyBackground`).
"""

from __future__ import annotations

import cv2
import numpy as np

from orbslam_hgcn.synth.render import BLOCK, _texture_size
from orbslam_hgcn.synth.street import StreetScene
from orbslam_hgcn.synth.textures import TextureStyle, _stamp, make_texture, value_noise
from orbslam_hgcn.geometry.camera import PinholeCamera

AMBIENT = 0.55  # light of a face in shadow, relative to the sunlit ground
_SHIFT = 4
_ONE = 1 << _SHIFT

S = TextureStyle
STYLES = {
    "asphalt": S(palette=((100, 100, 100),), noise_contrast=13.0, leaves=0.04, shape_contrast=0.12,
                 min_shape_m=0.1, max_shape_m=1.2, glyphs=0.0, lines=0.02),
    "paving": S(palette=((150, 152, 155),), noise_contrast=12.0, leaves=0.03, shape_contrast=0.3,
                min_shape_m=0.1, max_shape_m=0.6, glyphs=0.0, lines=0.01, grid_m=(0.35, 0.35)),
    "yard": S(palette=((80, 115, 95),), noise_contrast=26.0, leaves=0.12, shape_contrast=0.6,
              min_shape_m=0.25, max_shape_m=2.0, glyphs=0.0, lines=0.01),
    "plaster": S(palette=((200, 205, 210), (175, 190, 205), (165, 185, 200), (205, 200, 185), (150, 160, 170)),
                 noise_contrast=9.0, leaves=0.012, shape_contrast=0.15, min_shape_m=0.15, max_shape_m=2.5,
                 glyphs=0.0005, lines=0.005),
    "paint": S(palette=((128, 128, 128),), noise_contrast=4.0, leaves=0.005, shape_contrast=0.15,
               min_shape_m=0.05, max_shape_m=0.3, glyphs=0.0, lines=0.0),
    "glass": S(palette=((55, 50, 45),), noise_contrast=10.0, leaves=0.05, shape_contrast=0.5,
               min_shape_m=0.08, max_shape_m=0.5, glyphs=0.0, lines=0.02),
    "rubber": S(palette=((32, 32, 32),), noise_contrast=5.0, leaves=0.0, glyphs=0.0, lines=0.0),
    "metal": S(palette=((125, 125, 120),), noise_contrast=12.0, grain=4.0, leaves=0.02, shape_contrast=0.3,
               min_shape_m=0.03, max_shape_m=0.2, glyphs=0.0, lines=0.01),
    "bark": S(palette=((55, 65, 75),), noise_contrast=22.0, grain=0.25, leaves=0.1, shape_contrast=0.6,
              min_shape_m=0.02, max_shape_m=0.15, glyphs=0.0, lines=0.05),
    "foliage": S(palette=((45, 85, 60), (35, 75, 50), (60, 105, 85)), noise_contrast=30.0, leaves=0.0,
                 glyphs=0.0, lines=0.0),
}
MEANS = {"asphalt": 98.0, "paving": 150.0, "yard": 105.0}  # grey means fixed per ground material


def _pts(xy) -> np.ndarray:
    return np.round(np.asarray(xy, np.float64) * _ONE).astype(np.int32)


def _ramp(x: np.ndarray) -> np.ndarray:
    """0 below -0.5, 1 above 0.5, linear between (x in texels): anti-aliased region edges."""
    return np.clip(x + 0.5, 0.0, 1.0).astype(np.float32)


def _with_mean(tex: np.ndarray, mean: float) -> np.ndarray:
    return tex.astype(np.float32) + np.float32(mean - float(tex.mean()))


def face_light(normal: np.ndarray, sun: np.ndarray) -> float:
    """Brightness factor of a face: ambient plus direct sun, 1 for the sunlit ground."""
    direct = max(0.0, float(normal @ sun)) / float(sun[2])
    return float(min(1.15, AMBIENT + (1.0 - AMBIENT) * direct))


class StreetTextures:
    """The lit texture of every quad of a :class:`StreetScene`, made when indexed.

    ``textures[i]`` is an (nv, nu, 3) uint8 BGR image with sides multiples of 16 (what
    ``SceneRenderer(textures=...)`` takes); texel sizes are the quads' times ``texel_scale``.
    """

    def __init__(self, scene: StreetScene, texture_seed: int, texel_scale: float = 1.0, eye_height: float = 1.8):
        self.scene = scene
        self.seed = int(texture_seed)
        self.texel_scale = float(texel_scale)
        self.eye_height = eye_height  # faces looking up from above this are never seen
        sun = scene.sun
        shift = sun[:2] / sun[2]
        self.shadows = []  # (polygon (k, 2) on the ground, bbox (4,), kind)
        for corners, kind in scene.casters:
            flat = corners[:, :2] - corners[:, 2:3] * shift
            if kind == "car":  # the car's dark footprint as well as its shadow
                low = corners[corners[:, 2] <= corners[:, 2].min() + 1e-6][:, :2]
                poly = cv2.convexHull(low.astype(np.float32)).reshape(-1, 2).astype(np.float64)
                self.shadows.append((poly, np.r_[poly.min(0), poly.max(0)], "under"))
            poly = cv2.convexHull(flat.astype(np.float32)).reshape(-1, 2).astype(np.float64)
            self.shadows.append((poly, np.r_[poly.min(0), poly.max(0)], kind))
        self._bbox = np.array([s[1] for s in self.shadows]).reshape(-1, 4)

    def __len__(self) -> int:
        return len(self.scene.quads)

    def _hidden(self, i: int) -> bool:
        q = self.scene.quads[i]
        return bool(q.normal[2] > 0.99 and q.origin[2] > self.eye_height)  # tops of buildings, trees

    def shape(self, i: int) -> tuple[int, int]:
        """(nv, nu) texels of quad i's texture."""
        if self._hidden(i):
            return BLOCK, BLOCK
        q = self.scene.quads[i]
        return (_texture_size(q.size_v, q.texel * self.texel_scale)[0],
                _texture_size(q.size_u, q.texel * self.texel_scale)[0])

    def __getitem__(self, i: int) -> np.ndarray:
        q = self.scene.quads[i]
        if self._hidden(i):
            return np.full((BLOCK, BLOCK, 3), 90, np.uint8)
        nu, tu = _texture_size(q.size_u, q.texel * self.texel_scale)
        nv, tv = _texture_size(q.size_v, q.texel * self.texel_scale)
        rng = np.random.default_rng([self.seed, int(i)])
        obj = self.scene.objects[self.scene.owner[i]]
        kind = obj["kind"]
        texel = float(np.sqrt(tu * tv))
        if kind == "ground":
            return self._ground(q, rng, nv, nu, tu, tv)
        if kind in ("building", "backrow"):
            img = make_texture(rng, nv, nu, texel, STYLES["plaster"])
            if abs(q.normal[2]) < 0.1:
                _windows(img, q, obj, tu, tv)
        elif kind in ("car", "glass"):
            img = _car_face(rng, q, obj, kind, nv, nu, tu, tv)
        elif kind == "wheel":
            img = make_texture(rng, nv, nu, texel, STYLES["rubber"])
            if abs(q.normal[2]) < 0.1 and abs(q.normal @ _fwd(obj)) < 0.5:  # the sides: tyres with rims
                for sx in (-0.5, 0.5):
                    c = _face_uv(q, np.array(obj["centre"]) + sx * obj["wheel_base"] * _fwd(obj), tu, tv)[0]
                    cv2.circle(img, tuple(_pts(c)), int(0.31 / tu * _ONE), (22, 22, 22), -1, cv2.LINE_AA, _SHIFT)
                    cv2.circle(img, tuple(_pts(c)), int(0.19 / tu * _ONE), (135, 135, 135), -1, cv2.LINE_AA, _SHIFT)
                    cv2.circle(img, tuple(_pts(c)), int(0.06 / tu * _ONE), (70, 70, 70), -1, cv2.LINE_AA, _SHIFT)
        elif kind == "sign":
            img = make_texture(rng, nv, nu, texel, STYLES["metal"])
            if abs(q.normal @ _fwd(obj)) > 0.9 and obj["sign_seed"] % 2 == 0:
                _sign(img, obj["sign_seed"])
        elif kind in ("crown", "hedge"):
            img = _foliage(rng, nv, nu, texel)
        else:
            img = make_texture(rng, nv, nu, texel, STYLES["metal" if kind == "pole" else "bark"])
        light = face_light(q.normal, self.scene.sun)
        return cv2.convertScaleAbs(img, alpha=light)

    def _ground(self, q, rng, nv: int, nu: int, tu: float, tv: float) -> np.ndarray:
        spec = self.scene.spec
        texel = float(np.sqrt(tu * tv))
        # Distance to the centreline at every 4th texel, interpolated (it is smooth).
        j = (np.arange(nu // 4) * 4 + 2.0) * tu
        i = (np.arange(nv // 4) * 4 + 2.0) * tv
        P = q.origin[:2] + j[None, :, None] * q.u_axis[:2] + i[:, None, None] * q.v_axis[:2]
        lat, along = self.scene.centreline.lateral(P.reshape(-1, 2))
        lat = cv2.resize(lat.reshape(P.shape[:2]).astype(np.float32), (nu, nv), interpolation=cv2.INTER_LINEAR)
        along = cv2.resize(along.reshape(P.shape[:2]).astype(np.float32), (nu, nv), interpolation=cv2.INTER_LINEAR)
        a = np.abs(lat) / texel  # in texels
        k0, k1, f = spec.kerb / texel, (spec.kerb + 0.25) / texel, spec.frontage / texel
        weights = {"asphalt": _ramp(k0 - a), "kerb": _ramp(a - k0) * _ramp(k1 - a),
                   "paving": _ramp(a - k1) * _ramp(f - a), "yard": _ramp(a - f)}
        img = np.zeros((nv, nu, 3), np.float32)
        paving = None
        for name, w in weights.items():
            if not w.any():
                continue
            if name == "kerb":
                if paving is None:
                    paving = _with_mean(make_texture(rng, nv, nu, texel, STYLES["paving"]), MEANS["paving"])
                tex = paving * np.float32(1.12)
                joint = np.abs(((along + 0.5) % 1.0) - 0.5) < 0.6 * texel
                tex[joint] *= np.float32(0.6)
            elif name == "paving" and paving is not None:
                tex = paving
            else:
                tex = _with_mean(make_texture(rng, nv, nu, texel, STYLES[name]), MEANS[name])
                if name == "paving":
                    paving = tex
            if name == "asphalt":
                shade = 1.0 - 0.18 * _ramp(a - (k0 - 0.4 / texel))  # gutter
                for track in (-spec.lane_offset - 0.8, -spec.lane_offset + 0.8,
                              spec.lane_offset - 0.8, spec.lane_offset + 0.8):
                    shade *= 1.0 - 0.07 * np.exp(-0.5 * ((lat - track) / 0.25) ** 2)
                tex = tex * shade[..., None]
                dash = _ramp(0.06 / texel - np.abs(lat) / texel) * (np.mod(along, 9.0) < 3.0)
                tex = tex * (1 - dash[..., None]) + np.float32(205.0) * dash[..., None]
            img += tex * w[..., None]
        img *= self._ground_light(q, rng, nv, nu, tu, tv)[..., None]
        return np.clip(img + 0.5, 0, 255).astype(np.uint8)

    def _ground_light(self, q, rng, nv: int, nu: int, tu: float, tv: float) -> np.ndarray:
        """(nv, nu) float32 light of a ground cell: 1 in the sun, AMBIENT in shadow, darker
        under cars; shadows of tree crowns dappled."""
        corners = q.corners[:, :2]
        lo, hi = corners.min(0), corners.max(0)
        sel = np.flatnonzero((self._bbox[:, 0] < hi[0]) & (self._bbox[:, 2] > lo[0]) &
                             (self._bbox[:, 1] < hi[1]) & (self._bbox[:, 3] > lo[1]))
        lit = np.ones((nv, nu), np.float32)
        if len(sel) == 0:
            return lit
        solid = np.full((nv, nu), 255, np.uint8)
        leafy = np.full((nv, nu), 255, np.uint8)
        under = np.full((nv, nu), 255, np.uint8)
        for k in sel:
            poly, _, kind = self.shadows[k]
            rel = poly - q.origin[:2]
            uv = np.stack([rel @ q.u_axis[:2] / tu - 0.5, rel @ q.v_axis[:2] / tv - 0.5], 1)
            target = leafy if kind == "crown" else under if kind == "under" else solid
            cv2.fillPoly(target, [_pts(uv)], 0, cv2.LINE_AA, _SHIFT)
        gaps = value_noise(rng, nv, nu, 0.35 / tu, 0.35 / tv) > 0.6  # sun flecks through the leaves
        leafy[gaps] = 255
        sun = (np.minimum(solid, leafy).astype(np.float32) * np.float32(1 / 255.0))
        sun = cv2.GaussianBlur(sun, (0, 0), 0.05 / tu)  # penumbra of a few centimetres
        lit = AMBIENT + (1.0 - AMBIENT) * sun
        dark = cv2.GaussianBlur(under.astype(np.float32) * np.float32(1 / 255.0), (0, 0), 0.15 / tu)
        return lit * (0.45 + 0.55 * dark)


def _fwd(obj: dict) -> np.ndarray:
    return np.array([np.cos(obj["yaw"]), np.sin(obj["yaw"]), 0.0])


def _face_uv(q, P, tu: float, tv: float) -> np.ndarray:
    """Texel coordinates (cv2 pixel convention) of scene points P (N, 3) on quad q."""
    rel = np.atleast_2d(P) - q.origin
    return np.stack([rel @ q.u_axis / tu - 0.5, rel @ q.v_axis / tv - 0.5], 1)


def _foliage(rng, nv: int, nu: int, texel: float) -> np.ndarray:
    """Leaves: dark noisy green with many small blobs, sunlit and shaded, 4-20 cm."""
    img = make_texture(rng, nv, nu, texel, STYLES["foliage"])
    n = int(3.0 * nv * nu * texel * texel / 0.08 ** 2)
    size = np.exp(rng.uniform(np.log(0.04), np.log(0.2), n)) / texel
    half = np.stack([size, size * rng.uniform(0.5, 1.0, n)], 1) / 2
    grey = np.where(rng.random(n) < 0.35, rng.uniform(15, 40, n), rng.uniform(60, 170, n))
    colours = np.clip(grey[:, None] * np.array([0.8, 1.1, 0.9]) + rng.normal(0, 8, (n, 3)), 0, 255)
    order = np.argsort(-size)  # large first
    _stamp(img, rng.uniform(0, 1, (n, 2))[order] * [nu, nv], half[order], rng.uniform(0, np.pi, n)[order],
           "ellipse", colours[order])
    return img


def _windows(img: np.ndarray, q, obj: dict, tu: float, tv: float) -> None:
    """Rows of windows, one per floor, and a plinth, on a vertical building face."""
    rng = np.random.default_rng([obj["window_seed"], int(round(q.size_u * 100))])
    wrng = np.random.default_rng(obj["window_seed"])
    fh = obj["floor_m"]
    ww, wh = wrng.uniform(0.9, 1.6), wrng.uniform(1.2, 1.6)
    pitch = ww + wrng.uniform(1.0, 2.4)
    frame = (230, 230, 230) if wrng.random() < 0.6 else (70, 70, 75)
    top = q.origin[2]  # v runs down from the top edge
    height = q.size_v
    n_cols = int((q.size_u - 1.0) // pitch)
    if n_cols < 1:
        return
    x0 = 0.5 * (q.size_u - (n_cols - 1) * pitch)
    plinth = wrng.uniform(0.3, 0.8)
    y_p = (top - plinth) / tv
    img[int(y_p):] = (img[int(y_p):] * 0.72).astype(np.uint8)
    n_floors = int((height - 0.5) // fh)
    ledge = tuple(float(v) for v in np.clip(np.asarray(frame, np.float64) * 0.9 + 20, 0, 255))
    for f in range(1, n_floors + 1):  # a ledge at every floor, its shadow below
        yl = (top - f * fh + 0.6) / tv
        if yl * tv < 0.3:
            continue
        cv2.rectangle(img, tuple(_pts([-1, yl - 0.12 / tv])), tuple(_pts([img.shape[1], yl])), ledge, -1,
                      cv2.LINE_AA, _SHIFT)
        cv2.rectangle(img, tuple(_pts([-1, yl])), tuple(_pts([img.shape[1], yl + 0.05 / tv])), (90, 90, 90), -1,
                      cv2.LINE_AA, _SHIFT)
    if wrng.random() < 0.6:  # a drainpipe near one end
        xp = (0.3 if rng.random() < 0.5 else q.size_u - 0.3) / tu
        cv2.rectangle(img, tuple(_pts([xp - 0.05 / tu, -1])), tuple(_pts([xp + 0.05 / tu, img.shape[0]])),
                      (110, 112, 115), -1, cv2.LINE_AA, _SHIFT)
    for f in range(n_floors):
        z0 = 0.9 + f * fh
        if z0 + wh > height - 0.4:
            break
        for c in range(n_cols):
            if rng.random() < 0.06:
                continue
            xc = x0 + c * pitch
            xl, xr = (xc - ww / 2) / tu, (xc + ww / 2) / tu
            yt, yb = (top - z0 - wh) / tv, (top - z0) / tv
            m = 0.06 / tu
            cv2.rectangle(img, tuple(_pts([xl - m, yt - m])), tuple(_pts([xr + m, yb + m])), frame, -1, cv2.LINE_AA,
                          _SHIFT)
            g = rng.uniform(25, 75)
            glass = (g, g * 1.02, g * 1.05)
            cv2.rectangle(img, tuple(_pts([xl, yt])), tuple(_pts([xr, yb])), glass, -1, cv2.LINE_AA, _SHIFT)
            if rng.random() < 0.5:  # a reflection across the pane
                k = rng.uniform(0.2, 0.8)
                band = np.array([[xl + k * (xr - xl), yt], [xl + (k + 0.15) * (xr - xl), yt],
                                 [xl + (k - 0.1) * (xr - xl), yb], [xl + (k - 0.25) * (xr - xl), yb]])
                band[:, 0] = np.clip(band[:, 0], xl, xr)
                lv = min(255.0, g + rng.uniform(30, 90))
                cv2.fillConvexPoly(img, _pts(band), (lv, lv, lv), cv2.LINE_AA, _SHIFT)
            if rng.random() < 0.25:  # shutter partly down
                yd = yt + rng.uniform(0.2, 0.9) * (yb - yt)
                cv2.rectangle(img, tuple(_pts([xl, yt])), tuple(_pts([xr, yd])), (150, 155, 160), -1, cv2.LINE_AA,
                              _SHIFT)
                for ys in np.arange(yt, yd, 0.06 / tv):
                    cv2.line(img, tuple(_pts([xl, ys])), tuple(_pts([xr, ys])), (110, 115, 120), 1, cv2.LINE_AA,
                             _SHIFT)
            if ww > 1.2:  # mullion
                cv2.line(img, tuple(_pts([(xl + xr) / 2, yt])), tuple(_pts([(xl + xr) / 2, yb])), frame,
                         max(1, int(0.05 / tu)), cv2.LINE_AA, _SHIFT)
            cv2.rectangle(img, tuple(_pts([xl - 2 * m, yb + m])), tuple(_pts([xr + 2 * m, yb + 2.5 * m])),
                          (200, 200, 200), -1, cv2.LINE_AA, _SHIFT)


def _car_face(rng, q, obj: dict, kind: str, nv: int, nu: int, tu: float, tv: float) -> np.ndarray:
    """A face of a car body ('car') or of its cabin ('glass')."""
    texel = float(np.sqrt(tu * tv))
    paint = np.asarray(obj["colour"], np.float32)
    fwd = _fwd(obj)
    side = abs(q.normal @ fwd) < 0.5 and abs(q.normal[2]) < 0.5
    end = abs(q.normal @ fwd) > 0.9
    if kind == "glass" and abs(q.normal[2]) < 0.5:
        img = make_texture(rng, nv, nu, texel, STYLES["glass"])
        pillar = 0.09 / tu
        for x in ([0.0, nu] + ([nu / 2] if side else [])):
            cv2.rectangle(img, tuple(_pts([x - pillar, -1])), tuple(_pts([x + pillar, nv + 1])),
                          tuple(paint.tolist()), -1, cv2.LINE_AA, _SHIFT)
        return img
    base = make_texture(rng, nv, nu, texel, STYLES["paint"]).astype(np.float32)
    img = np.clip(base - 128.0 + paint, 0, 255).astype(np.uint8)
    dark = tuple(float(v) for v in np.clip(paint * 0.45, 0, 255))
    centre = np.array(obj["centre"])
    L = obj["size"][0]
    if side:
        for sx in (-0.12, 0.18):  # door seams and handles
            p = _face_uv(q, centre + sx * L * fwd + np.array([0, 0, 0.35]), tu, tv)[0]
            cv2.line(img, tuple(_pts([p[0], 0])), tuple(_pts([p[0], nv])), dark, 1, cv2.LINE_AA, _SHIFT)
            h = _face_uv(q, centre + (sx + 0.08) * L * fwd + np.array([0, 0, 0.2]), tu, tv)[0]
            cv2.rectangle(img, tuple(_pts(h - [0.08 / tu, 0.015 / tv])), tuple(_pts(h + [0.08 / tu, 0.015 / tv])),
                          dark, -1, cv2.LINE_AA, _SHIFT)
        for sx in (-1.0, 1.0):  # wheel arches
            p = _face_uv(q, np.array([*centre[:2], 0.31]) + sx * (L / 2 - 0.8) * fwd, tu, tv)[0]
            cv2.circle(img, tuple(_pts(p)), int(0.4 / tu * _ONE), (25, 25, 25), -1, cv2.LINE_AA, _SHIFT)
    elif end:
        front = q.normal @ fwd > 0
        W = obj["size"][1]
        right = np.cross(q.normal, [0.0, 0.0, 1.0])
        lamp = (215, 215, 215) if front else (40, 40, 150)
        for sy in (-1.0, 1.0):
            p = _face_uv(q, centre + q.normal * 0 + sy * (W / 2 - 0.22) * right + np.array([0, 0, 0.12]), tu, tv)[0]
            cv2.ellipse(img, tuple(_pts(p)), tuple(_pts([0.14 / tu, 0.06 / tv])), 0, 0, 360, lamp, -1, cv2.LINE_AA,
                        _SHIFT)
        p = _face_uv(q, centre + np.array([0, 0, -0.15]), tu, tv)[0]
        cv2.rectangle(img, tuple(_pts(p - [0.26 / tu, 0.055 / tv])), tuple(_pts(p + [0.26 / tu, 0.055 / tv])),
                      (235, 235, 235), -1, cv2.LINE_AA, _SHIFT)
        text = "".join(rng.choice(list("ABCDEFGHKLMNPRSTUVXZ0123456789"), 6))
        cv2.putText(img, text, (int(p[0] - 0.22 / tu), int(p[1] + 0.035 / tv)), cv2.FONT_HERSHEY_SIMPLEX,
                    0.075 / tv / 22.0, (25, 25, 25), max(1, int(0.012 / tu)), cv2.LINE_AA)
    return img


def _sign(img: np.ndarray, seed: int) -> None:
    """A round traffic sign: white disc with a dark ring and a mark."""
    h, w = img.shape[:2]
    c = (w / 2 - 0.5, h / 2 - 0.5)
    r = 0.45 * min(h, w)
    cv2.circle(img, tuple(_pts(c)), int(r * _ONE), (40, 40, 170), -1, cv2.LINE_AA, _SHIFT)
    cv2.circle(img, tuple(_pts(c)), int(0.75 * r * _ONE), (235, 235, 235), -1, cv2.LINE_AA, _SHIFT)
    text = str(10 * (seed % 7 + 2))
    cv2.putText(img, text, (int(c[0] - 0.45 * r), int(c[1] + 0.25 * r)), cv2.FONT_HERSHEY_SIMPLEX,
                0.55 * r / 22.0, (25, 25, 25), max(1, int(r / 12)), cv2.LINE_AA)


class SkyBackground:
    """The sky behind a street scene, seen from any camera orientation.

    Brightness rises from the zenith to the horizon and towards the sun, with faint large
    clouds (a few grey levels, little texture); below the horizon a flat haze. Computed on
    a 4x coarser grid and interpolated: (H, W, 3) uint8 BGR per call.
    """

    def __init__(self, camera: PinholeCamera, sun: np.ndarray, seed: int, T_world_scene: np.ndarray | None = None):
        self.size = (camera.width, camera.height)
        w, h = -(-camera.width // 4), -(-camera.height // 4)
        u = (np.arange(w) * 4 + 1.5 - camera.cx) / camera.fx
        v = (np.arange(h) * 4 + 1.5 - camera.cy) / camera.fy
        rays = np.stack(np.broadcast_arrays(u[None, :], v[:, None], np.ones((h, w))), -1).reshape(-1, 3)
        self.rays = rays / np.linalg.norm(rays, axis=1, keepdims=True)
        self.sun = np.asarray(sun, np.float64)
        self.R_sw = np.eye(3) if T_world_scene is None else np.asarray(T_world_scene)[:3, :3].T
        rng = np.random.default_rng([int(seed), 31])
        self.clouds = value_noise(rng, 256, 1024, 48.0, 16.0) + 0.5 * value_noise(rng, 256, 1024, 12.0, 6.0)
        self._grid = (h, w)

    def __call__(self, T_wc: np.ndarray) -> np.ndarray:
        d = self.rays @ (self.R_sw @ np.asarray(T_wc)[:3, :3]).T  # scene-frame directions
        up = d[:, 2]
        az = (np.arctan2(d[:, 1], d[:, 0]) / (2 * np.pi) + 0.5) * 1024.0
        el = np.clip(up, 0.0, 1.0) * 255.0
        cloud = cv2.remap(self.clouds, az.astype(np.float32).reshape(self._grid), el.astype(np.float32).reshape(
            self._grid), cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP).ravel()
        glow = np.maximum(d @ self.sun, 0.0) ** 8
        grey = 238.0 - 38.0 * np.clip(up, 0.0, 1.0) ** 0.6 + 14.0 * glow + 4.0 * cloud * np.clip(up * 4, 0, 1)
        grey = np.where(up < 0.0, 165.0, grey)
        bgr = np.stack([grey + 6.0, grey + 2.0, grey - 6.0], -1).reshape(*self._grid, 3)
        small = np.clip(bgr + 0.5, 0, 255).astype(np.uint8)
        return cv2.resize(small, self.size, interpolation=cv2.INTER_LINEAR)

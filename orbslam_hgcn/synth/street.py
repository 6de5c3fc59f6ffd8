"""Forward-driving street scenes (KITTI-like) for synthetic sequences.

The route is a chain of straight streets joined by 90-degree corners, alternately left and
right (a staircase, so it never comes back on itself), its centreline filleted at every
corner. The camera drives on the right-hand lane at a cruising speed (KITTI 00: about
8.5 m/s, 0.85 m per frame at 10 Hz), brakes smoothly for each corner and speeds up after
it, with the mild pitch, roll and bounce of a car on a road and body roll in the turns.

Both sides of each street hold, from the centreline out: two driving lanes, a parking lane
with parked cars, a kerb, a sidewalk with trees and poles (some with signs), front yards
with hedges, a row of buildings (windows on every side) and a row of taller buildings
behind. A building closes the far end of the route. Every object keeps clear of the roads
(buildings of the sidewalk, parked cars of the camera's path).

Scene frame: metres, z up, ground at z = 0; the route starts at the origin heading +x.
Camera frames follow OpenCV: x right, y down, z forward. Texturing, lighting and the sky
are in ``street_textures``.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field

import numpy as np
from scipy.ndimage import gaussian_filter1d

from orbslam_hgcn.synth.layout import _footprint_clear, _overlap
from orbslam_hgcn.synth.scene import Quad, Scene, box_quads, face, rot_z

log = logging.getLogger(__name__)

UP = np.array([0.0, 0.0, 1.0])
# Camera axes (x right, y down, z forward) in the vehicle frame (x forward, y left, z up).
R_VEHICLE_CAM = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
START_MARGIN = 30.0  # route metres behind the first camera position
LOOKAHEAD = 150.0  # route metres kept beyond the last camera position
CELL = 16.0  # ground cells along the road (m)

# Texel sizes (m) per kind of street surface: seen from 2-10 m (cars, poles), 6-30 m (road,
# facades) and beyond (back row, yards).
STREET_TEXEL = {
    "road": 0.02, "yard": 0.05, "facade": 0.025, "backrow": 0.06, "car": 0.015, "glass": 0.015,
    "wheel": 0.02, "pole": 0.01, "sign": 0.008, "trunk": 0.012, "crown": 0.03, "hedge": 0.02,
}
SIDE_TEXEL = 1.4  # building faces not facing their street: texels this much larger, back faces 3x


@dataclass(frozen=True)
class StreetSpec:
    """Cross-section of the streets and the way the camera drives them (metres, m/s)."""

    lane: float = 3.5  # centreline to the parking lane: two driving lanes of 3.5 m
    parking: float = 2.2  # parking lane on each side
    sidewalk: float = 3.0
    corner_radius: float = 11.0  # of the centreline at the corners
    lane_offset: float = 1.75  # camera right of the centreline (right-hand traffic)
    camera_height: float = 1.65  # KITTI's camera above the road
    speed: float = 8.5  # cruising speed
    turn_speed: float = 4.5  # speed through the corners
    accel: float = 1.2  # mean braking before and acceleration after a corner (m/s^2)
    band: float = 34.0  # ground and buildings up to this far from the centreline

    @property
    def kerb(self) -> float:
        """Centreline to the kerb."""
        return self.lane + self.parking

    @property
    def frontage(self) -> float:
        """Centreline to the back of the sidewalk."""
        return self.kerb + self.sidewalk


class PlanarPath:
    """A polyline of straight pieces filleted at its corners, offset sideways.

    corners: (n + 1, 2) route corners, consecutive pieces perpendicular; radius: fillet
    radius of the centreline; offset: this path's distance to the left (+) or right (-) of
    the centreline. Arc length ``s`` runs from the first corner.
    """

    def __init__(self, corners: np.ndarray, radius: float, offset: float = 0.0):
        c = np.asarray(corners, np.float64)
        d = np.diff(c, axis=0)
        lengths = np.linalg.norm(d, axis=1)
        d /= lengths[:, None]
        n = np.stack([-d[:, 1], d[:, 0]], 1)  # left normals
        self.prims: list[dict] = []
        s = 0.0
        for k in range(len(d)):
            if k > 0:  # the arc into piece k
                turn = float(np.sign(d[k - 1, 0] * d[k, 1] - d[k - 1, 1] * d[k, 0]))
                centre = c[k] - radius * d[k - 1] + turn * radius * n[k - 1]
                r = radius - turn * offset
                start = c[k] - radius * d[k - 1] + offset * n[k - 1] - centre
                self.prims.append({"kind": "arc", "s0": s, "length": r * np.pi / 2, "centre": centre, "r": r,
                                   "phi0": float(np.arctan2(start[1], start[0])), "turn": turn})
                s += r * np.pi / 2
            a = c[k] + (radius * d[k] if k > 0 else 0.0) + offset * n[k]
            length = lengths[k] - (radius if k > 0 else 0.0) - (radius if k < len(d) - 1 else 0.0)
            if length <= 0:
                raise ValueError(f"route piece {k} ({lengths[k]:.1f} m) is shorter than its corner fillets")
            self.prims.append({"kind": "line", "s0": s, "length": length, "a": a, "d": d[k], "n": n[k]})
            s += length
        self.length = s
        self._s0 = np.array([p["s0"] for p in self.prims])

    def at(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Points (N, 2), headings (N,) (radians from +x) and curvatures (N,) (left +) at s (N,)."""
        s = np.atleast_1d(np.asarray(s, np.float64))
        idx = np.clip(np.searchsorted(self._s0, s, side="right") - 1, 0, len(self.prims) - 1)
        xy = np.zeros((len(s), 2))
        head = np.zeros(len(s))
        kappa = np.zeros(len(s))
        for i in np.unique(idx):
            p = self.prims[i]
            m = idx == i
            ds = s[m] - p["s0"]
            if p["kind"] == "line":
                xy[m] = p["a"] + ds[:, None] * p["d"]
                head[m] = np.arctan2(p["d"][1], p["d"][0])
            else:
                phi = p["phi0"] + p["turn"] * ds / p["r"]
                xy[m] = p["centre"] + p["r"] * np.stack([np.cos(phi), np.sin(phi)], 1)
                head[m] = phi + p["turn"] * np.pi / 2
                kappa[m] = p["turn"] / p["r"]
        return xy, head, kappa

    def lateral(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Signed distance to the left (N,) of points xy (N, 2) from the nearest piece of this
        path, and the arc length (N,) of their foot points."""
        xy = np.asarray(xy, np.float64).reshape(-1, 2)
        best = np.full(len(xy), np.inf)
        lat = np.zeros(len(xy))
        along = np.zeros(len(xy))
        lo, hi = xy.min(0), xy.max(0)
        for p in self.prims:
            if p["kind"] == "line":
                b = p["a"] + p["length"] * p["d"]
                reach = np.maximum(np.maximum(lo - np.maximum(p["a"], b), np.minimum(p["a"], b) - hi), 0.0)
                if np.hypot(*reach) > best.max():
                    continue
                rel = xy - p["a"]
                t = rel @ p["d"]
                side = rel @ p["n"]
                tc = np.clip(t, 0.0, p["length"])
                dist = np.hypot(t - tc, side)
                sgn = np.where(side >= 0, 1.0, -1.0)
                cand_lat, cand_s = sgn * dist, p["s0"] + tc
            else:
                rel = xy - p["centre"]
                rho = np.hypot(rel[:, 0], rel[:, 1])
                phi = np.arctan2(rel[:, 1], rel[:, 0])
                sweep = p["turn"] * ((phi - p["phi0"]) * p["turn"] % (2 * np.pi))
                inside = np.abs(sweep) <= np.pi / 2
                dist = np.where(inside, np.abs(rho - p["r"]), np.inf)
                cand_lat = p["turn"] * (p["r"] - rho)
                cand_s = p["s0"] + np.abs(sweep) * p["r"]
            better = dist < best
            best = np.where(better, dist, best)
            lat = np.where(better, cand_lat, lat)
            along = np.where(better, cand_s, along)
        return lat, along

    def arcs(self) -> np.ndarray:
        """(A, 2) arc-length intervals of the corner arcs."""
        return np.array([[p["s0"], p["s0"] + p["length"]] for p in self.prims if p["kind"] == "arc"]).reshape(-1, 2)


def route_corners(rng: np.random.Generator, distance: float) -> np.ndarray:
    """Corners (n + 1, 2) of a staircase route whose length covers ``distance`` metres of
    driving after START_MARGIN, plus LOOKAHEAD; at least one corner."""
    first = START_MARGIN + float(np.clip(rng.uniform(0.3, 0.5) * distance, 30.0, 130.0))
    lengths = [first]
    while sum(lengths) < START_MARGIN + distance + LOOKAHEAD or len(lengths) < 2:
        lengths.append(float(rng.uniform(110.0, 190.0)))
    turn = 1.0 if rng.random() < 0.5 else -1.0
    d = np.array([1.0, 0.0])
    corners = [np.zeros(2)]
    for k, length in enumerate(lengths):
        corners.append(corners[-1] + length * d)
        d = turn * np.array([-d[1], d[0]])  # 90 degrees to the left (turn +1) or right
        turn = -turn
    return np.array(corners)


class Drive:
    """The camera's motion along a route: speed profile, pose jitter, poses at any time.

    Speed: ``spec.speed`` on the straights and ``spec.turn_speed`` in the corner arcs,
    the squared speed blending between them over the braking distance with a smoothstep.
    Attitude: heading along the path; pitch from braking and acceleration (0.3 deg per
    m/s^2) and roll from the lateral acceleration (0.4 deg per m/s^2), both smoothed, plus
    sinusoidal jitter of pitch (0.3 deg), roll (0.25 deg), yaw (0.15 deg) and height (1 cm).
    """

    def __init__(self, path: PlanarPath, spec: StreetSpec, seed: int, s_start: float = START_MARGIN):
        self.path = path
        self.spec = spec
        ds = 0.05
        s = np.arange(0.0, path.length + ds, ds)
        arcs = path.arcs()
        if len(arcs):
            gap = np.maximum(arcs[None, :, 0] - s[:, None], s[:, None] - arcs[None, :, 1])
            dist = np.maximum(gap, 0.0).min(axis=1)
        else:
            dist = np.full(len(s), np.inf)
        vc2, vt2 = spec.speed ** 2, spec.turn_speed ** 2
        brake = (vc2 - vt2) / (2.0 * spec.accel)
        x = np.clip(dist / brake, 0.0, 1.0)
        v = np.sqrt(vt2 + (vc2 - vt2) * x * x * (3.0 - 2.0 * x))
        t = np.concatenate([[0.0], np.cumsum(ds / (0.5 * (v[1:] + v[:-1])))])
        self._s, self._t, self._v = s, t - np.interp(s_start, s, t), v
        a_long = v * np.gradient(v, ds)
        _, _, kappa = path.at(s)
        a_lat = v * v * gaussian_filter1d(kappa, 2.0 / ds)  # steering eases in over a few metres
        self._pitch = np.radians(0.3) * -gaussian_filter1d(a_long, 1.0 / ds)
        self._roll = np.radians(0.4) * a_lat
        rng = np.random.default_rng([int(seed), 21])

        def wobble(amp):
            f = rng.uniform(0.3, 2.5, 5)
            return f, rng.normal(0, 1, 5) * amp / np.sqrt(2.5), rng.uniform(0, 2 * np.pi, 5)

        self.jitter = {"pitch": wobble(np.radians(0.3)), "roll": wobble(np.radians(0.25)),
                       "yaw": wobble(np.radians(0.15)), "height": wobble(0.01)}
        self.duration_max = float(np.interp(path.length - LOOKAHEAD, s, self._t))

    @staticmethod
    def _wave(w, t):
        f, amp, ph = w
        return np.sin(2 * np.pi * np.outer(t, f) + ph) @ amp

    def arc_length(self, t: np.ndarray) -> np.ndarray:
        return np.interp(t, self._t, self._s)

    def speed(self, t: np.ndarray) -> np.ndarray:
        return np.interp(self.arc_length(t), self._s, self._v)

    def __call__(self, t: np.ndarray) -> np.ndarray:
        """(N, 4, 4) scene-frame camera poses T_sc at times t (N,) seconds."""
        t = np.atleast_1d(np.asarray(t, np.float64))
        s = self.arc_length(t)
        xy, head, _ = self.path.at(s)
        pitch = np.interp(s, self._s, self._pitch) + self._wave(self.jitter["pitch"], t)
        roll = np.interp(s, self._s, self._roll) + self._wave(self.jitter["roll"], t)
        yaw = head + self._wave(self.jitter["yaw"], t)
        cy, sy, cp, sp, cr, sr = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch), np.cos(roll), np.sin(roll)
        # R = Rz(yaw) Ry(pitch) Rx(roll): vehicle -> scene.
        R = np.empty((len(t), 3, 3))
        R[:, 0, 0], R[:, 0, 1], R[:, 0, 2] = cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr
        R[:, 1, 0], R[:, 1, 1], R[:, 1, 2] = sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr
        R[:, 2, 0], R[:, 2, 1], R[:, 2, 2] = -sp, cp * sr, cp * cr
        T = np.tile(np.eye(4), (len(t), 1, 1))
        T[:, :3, :3] = R @ R_VEHICLE_CAM
        T[:, :2, 3] = xy
        T[:, 2, 3] = self.spec.camera_height + self._wave(self.jitter["height"], t)
        return T

    def params(self) -> dict:
        return {"kind": "street", "route_m": self.path.length, "speed_mps": self.spec.speed,
                "turn_speed_mps": self.spec.turn_speed, "camera_height_m": self.spec.camera_height,
                "corners": [p["s0"] for p in self.path.prims if p["kind"] == "arc"]}


@dataclass
class StreetScene(Scene):
    """A street :class:`Scene` with what its textures need: the route centreline, the
    object of each quad (``owner``, an index into ``objects``), shadow casters and the sun."""

    spec: StreetSpec = field(default_factory=StreetSpec)
    centreline: PlanarPath | None = None
    objects: list[dict] = field(default_factory=list)
    owner: list[int] = field(default_factory=list)
    casters: list[tuple[np.ndarray, str]] = field(default_factory=list)  # (8, 3) box corners, kind
    sun: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))


class _Builder:
    """Collects quads with their owning object, and footprints to keep objects apart."""

    def __init__(self, scene: StreetScene):
        self.scene = scene
        self.footprints: list[np.ndarray] = []  # (4, 2) corners of buildings and hedges

    def add(self, kind: str, quads: list[Quad], **params) -> int:
        k = len(self.scene.objects)
        self.scene.objects.append({"kind": kind, **params})
        self.scene.quads.extend(quads)
        self.scene.owner.extend([k] * len(quads))
        return k

    def box(self, kind: str, centre, size, yaw: float, texel: float, bottom: bool = False, shadow: bool = True,
            **params) -> int:
        R = rot_z(yaw)
        quads = box_quads(centre, size, R, kind, kind, texel, bottom)
        if kind == "wheel":  # its top is inside the car body
            quads = [q for q in quads if q.normal[2] < 0.5]
        if shadow:
            h = 0.5 * np.asarray(size, np.float64)
            signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], np.float64)
            self.scene.casters.append((np.asarray(centre, np.float64) + (signs * h) @ R.T, kind))
        return self.add(kind, quads, centre=list(map(float, centre)), size=list(map(float, size)), yaw=float(yaw),
                        **params)


def _rect(centre_xy, half, yaw: float) -> np.ndarray:
    R2 = rot_z(yaw)[:2, :2]
    return np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * np.asarray(half) @ R2.T + np.asarray(centre_xy)


def build_street(scene_seed: int, distance: float, spec: StreetSpec = StreetSpec()) -> tuple[StreetScene, Drive]:
    """The street scene and the drive along it, covering ``distance`` metres of driving."""
    rng = np.random.default_rng([int(scene_seed), 17])
    corners = route_corners(rng, distance)
    centre = PlanarPath(corners, spec.corner_radius)
    drive = Drive(PlanarPath(corners, spec.corner_radius, -spec.lane_offset), spec, scene_seed)
    elev, azim = np.radians(rng.uniform(30.0, 55.0)), rng.uniform(0.0, 2 * np.pi)
    sun = np.array([np.cos(elev) * np.cos(azim), np.cos(elev) * np.sin(azim), np.sin(elev)])
    scene = StreetScene(quads=[], spec=spec, centreline=centre, sun=sun)
    b = _Builder(scene)
    road_pts = centre.at(np.arange(0.0, centre.length, 0.5))[0]
    cam_pts = drive.path.at(np.arange(0.0, drive.path.length, 0.5))[0]
    _ground(b, corners, spec)
    d_all = np.diff(corners, axis=0)
    for k in range(len(d_all)):
        length = float(np.linalg.norm(d_all[k]))
        d = d_all[k] / length
        for side in (1.0, -1.0):
            _kerbside(b, rng, corners[k], d, side, length, k, len(d_all), spec, cam_pts)
            _buildings(b, rng, corners[k], d, side, length, spec, road_pts)
    # A building across the far end of the route.
    d = d_all[-1] / np.linalg.norm(d_all[-1])
    end = corners[-1] + 8.0 * d
    b.box("building", [*end, 9.0], [16.0, 2 * spec.band, 18.0], float(np.arctan2(d[1], d[0])),
          STREET_TEXEL["facade"], **_building_params(rng))
    scene.layout = {"kind": "street", "corners": corners.tolist(), "spec": spec.__dict__,
                    "sun": sun.tolist(), "n_quads": len(scene.quads),
                    "objects": {k: sum(o["kind"] == k for o in scene.objects)
                                for k in sorted({o["kind"] for o in scene.objects})}}
    log.debug("street: %d quads, route %.0f m", len(scene.quads), centre.length)
    return scene, drive


def _ground(b: _Builder, corners: np.ndarray, spec: StreetSpec) -> None:
    """Ground cells along each street: CELL metres long, in three bands across (road and
    sidewalks in the middle, yards on either side). A corner square belongs to the street
    that enters it; the next street's cells start beyond it, so no cells overlap."""
    D, F = spec.band, spec.frontage
    n = len(corners) - 1
    for k in range(n):
        a, e = corners[k], corners[k + 1]
        length = float(np.linalg.norm(e - a))
        d = (e - a) / length
        left = np.array([-d[1], d[0]])
        x0 = D if k > 0 else 0.0
        x1 = length + (D if k < n - 1 else 0.0)
        m = max(1, int(round((x1 - x0) / CELL)))
        xs = np.linspace(x0, x1, m + 1)
        for lo, hi in ((-D, -F), (-F, F), (F, D)):
            texel = STREET_TEXEL["road"] if (lo, hi) == (-F, F) else STREET_TEXEL["yard"]
            for u0, u1 in zip(xs[:-1], xs[1:]):
                c = a + 0.5 * (u0 + u1) * d + 0.5 * (lo + hi) * left
                q = face([c[0], c[1], 0.0], UP, [-left[0], -left[1], 0.0], u1 - u0, hi - lo, "ground", "ground", texel)
                b.add("ground", [q])


def _building_params(rng: np.random.Generator) -> dict:
    return {"floor_m": float(rng.uniform(2.8, 3.4)), "window_seed": int(rng.integers(1 << 30))}


def _buildings(b: _Builder, rng, a, d, side: float, length: float, spec: StreetSpec, road_pts) -> None:
    """Front-row buildings with gaps, hedges before some, and a taller back row."""
    n = side * np.array([-d[1], d[0]])  # away from the road on this side
    yaw = float(np.arctan2(d[1], d[0]))
    D, F = spec.band, spec.frontage
    for row in ("front", "back"):
        x = -D + rng.uniform(0, 6)
        while x < length + D:
            if row == "front":
                size = [rng.uniform(8, 22), rng.uniform(9, 14), rng.uniform(6.5, 16)]
                off = F + rng.uniform(0.5, 5.0)
                gap = 0.0 if rng.random() < 0.35 else rng.uniform(2, 9)
            else:
                size = [rng.uniform(12, 30), rng.uniform(8, 12), rng.uniform(12, 26)]
                off = F + 14.0 + rng.uniform(0, 4)
                gap = rng.uniform(0, 6)
            size[1] = min(size[1], D - off)
            ctr = a + (x + size[0] / 2) * d + (off + size[1] / 2) * n
            rect = _rect(ctr, [size[0] / 2, size[1] / 2], yaw)
            free = _footprint_clear(ctr, [size[0] / 2, size[1] / 2], yaw, road_pts, F + 0.3) and not any(
                _overlap(rect, o) for o in b.footprints if np.abs(o.mean(0) - ctr).max() < 60)
            if free and size[1] > 4:
                b.footprints.append(rect)
                kind = "building" if row == "front" else "backrow"
                texel = STREET_TEXEL["facade" if row == "front" else "backrow"]
                k = b.box(kind, [*ctr, size[2] / 2], size, yaw, texel, **_building_params(rng))
                for j in np.flatnonzero(np.array(b.scene.owner) == k):  # coarser away from the street
                    q = b.scene.quads[j]
                    facing = float(q.normal[:2] @ -n)
                    if facing < 0.9:
                        b.scene.quads[j] = dataclasses.replace(q, texel=texel * (3.0 if facing < -0.9 else SIDE_TEXEL))
                if row == "front" and off > F + 1.5 and rng.random() < 0.5:  # hedge before it
                    h = [size[0] * rng.uniform(0.6, 1.0), 0.7, rng.uniform(0.8, 1.4)]
                    hc = a + (x + size[0] / 2) * d + (F + 0.45) * n
                    if _footprint_clear(hc, [h[0] / 2, 0.35], yaw, road_pts, F + 0.05):
                        b.box("hedge", [*hc, h[2] / 2], h, yaw, STREET_TEXEL["hedge"])
            x += size[0] + gap


def _kerbside(b: _Builder, rng, a, d, side: float, length: float, k: int, n_pieces: int, spec: StreetSpec,
              cam_pts) -> None:
    """Parked cars in runs, trees and poles on the sidewalk, along the straight part."""
    n = side * np.array([-d[1], d[0]])
    yaw = float(np.arctan2(d[1], d[0]))
    lo = spec.corner_radius + spec.kerb + 2.0 if k > 0 else 5.0
    hi = length - (spec.corner_radius + spec.kerb + 2.0 if k < n_pieces - 1 else 0.0)
    x = lo + rng.uniform(0, 10)
    parked = rng.random() < 0.75
    while x < hi - 5:  # parked cars: runs of cars and empty stretches
        run_end = x + (rng.uniform(15, 60) if parked else rng.uniform(5, 35))
        while parked and x < min(hi - 5, run_end):
            L, W = rng.uniform(3.9, 4.8), rng.uniform(1.7, 1.85)
            ctr = a + (x + L / 2) * d + (spec.lane + spec.parking / 2 + rng.normal(0, 0.08)) * n
            cyaw = yaw + rng.normal(0, 0.03) + (np.pi if rng.random() < 0.3 else 0.0)
            if _footprint_clear(ctr, [L / 2, W / 2], cyaw, cam_pts, 1.3):
                _car(b, rng, ctr, L, W, cyaw)
            x += L + rng.uniform(0.6, 2.5)
        x = max(x, run_end)
        parked = not parked
    for kind, spacing in (("tree", (7.0, 16.0)), ("pole", (22.0, 45.0))):
        x = lo + rng.uniform(0, spacing[0])
        while x < hi:
            if kind == "tree" and rng.random() < 0.7:
                p = a + x * d + (spec.kerb + 1.0) * n
                _tree(b, rng, p)
            elif kind == "pole":
                p = a + x * d + (spec.kerb + 0.4 + (0.6 if rng.random() < 0.5 else 0.0)) * n
                h = rng.uniform(4.0, 8.0)
                b.box("pole", [*p, h / 2], [0.14, 0.14, h], yaw, STREET_TEXEL["pole"])
                if rng.random() < 0.5:  # a sign facing the traffic on this side
                    sc = np.array([*p, rng.uniform(2.2, 2.8)]) + np.array([*(-0.1 * side * d), 0.0])
                    b.box("sign", sc, [0.04, 0.65, 0.65], yaw, STREET_TEXEL["sign"], shadow=False,
                          sign_seed=int(rng.integers(1 << 30)))
            x += rng.uniform(*spacing)


def _car(b: _Builder, rng, ctr, L: float, W: float, yaw: float) -> None:
    colour = [(235, 235, 235), (190, 190, 195), (40, 40, 45), (120, 60, 30), (40, 40, 170), (90, 90, 95),
              (30, 90, 40), (150, 140, 110)][int(rng.integers(8))]
    params = {"colour": colour, "car_seed": int(rng.integers(1 << 30))}
    fwd = np.array([np.cos(yaw), np.sin(yaw)])
    b.box("car", [*ctr, 0.65], [L, W, 0.7], yaw, STREET_TEXEL["car"], **params)
    cab = ctr - 0.06 * L * fwd
    b.box("glass", [*cab, 1.25], [0.52 * L, W - 0.14, 0.5], yaw, STREET_TEXEL["glass"], **params)
    # Wheels and the dark space between them: one box under the body, rims painted on.
    b.box("wheel", [*ctr, 0.31], [L - 1.0, W - 0.04, 0.62], yaw, STREET_TEXEL["wheel"], shadow=False,
          wheel_base=L - 1.6)


def _tree(b: _Builder, rng, p) -> None:
    h = rng.uniform(2.2, 3.2)
    b.box("trunk", [*p, h / 2], [0.3, 0.3, h], rng.uniform(0, np.pi), STREET_TEXEL["trunk"])
    for _ in range(int(rng.integers(1, 3))):
        s = rng.uniform(2.0, 3.8, 3)
        c = np.array([*(p + rng.normal(0, 0.5, 2)), h + s[2] / 2 - 0.2 + rng.uniform(0, 1.2)])
        b.box("crown", c, s, rng.uniform(0, np.pi), STREET_TEXEL["crown"], bottom=True)

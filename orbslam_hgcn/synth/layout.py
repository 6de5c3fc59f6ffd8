"""Office layouts for the synthetic scenes.

A room (floor, ceiling, four walls, posters and a door), a desk (top, legs, a drawer
block) centred at the scene origin with its long side along x, carrying monitors, a
laptop, a keyboard, papers and boxes; around it cabinets and shelves against the walls,
crates (some stacked), a chair, and side tables with things on them near the places the
camera looks at (``focus``). Objects that would come within ``clearance`` of the camera
path (``keep_out``) are left out, so a trajectory never passes through furniture.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from orbslam_hgcn.synth.scene import TEXEL, UP, Quad, Scene, box_quads, face, rot_x, rot_z, room_quads

log = logging.getLogger(__name__)


def _footprint_clear(centre_xy, half_xy, yaw: float, keep_out_xy: np.ndarray, clearance: float) -> bool:
    """True when no keep-out point (K, 2) lies within ``clearance`` of the oriented rectangle."""
    if keep_out_xy is None or len(keep_out_xy) == 0:
        return True
    d = keep_out_xy - np.asarray(centre_xy)[None]
    c, s = np.cos(yaw), np.sin(yaw)
    local = np.abs(np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], 1))
    gap = np.linalg.norm(np.maximum(local - np.asarray(half_xy)[None], 0.0), axis=1)
    return bool(gap.min() >= clearance)


def _overlap(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether two rectangles given by their corners (4, 2) overlap (separating axis test)."""
    for poly in (a, b):
        for i in (0, 1):
            n = (poly[i, 1] - poly[i + 1, 1], poly[i + 1, 0] - poly[i, 0])
            pa = a[:, 0] * n[0] + a[:, 1] * n[1]
            pb = b[:, 0] * n[0] + b[:, 1] * n[1]
            if pa.max() < pb.min() or pb.max() < pa.min():
                return False
    return True


@dataclass(frozen=True)
class DeskSpec:
    """Desk top size (m) along scene x and y, and top height above the floor (m)."""

    length: float = 1.6
    depth: float = 0.85
    height: float = 0.74


def _desk(quads: list[Quad], layout: dict, desk: DeskSpec) -> None:
    L, D, H = desk.length, desk.depth, desk.height
    t = 0.03
    quads += box_quads([0, 0, H - t / 2], [L, D, t], style="wood", label="desk_top", texel=TEXEL["desk"], bottom=True)
    for sx in (-1, 1):
        for sy in (-1, 1):
            quads += box_quads([sx * (L / 2 - 0.06), sy * (D / 2 - 0.06), (H - t) / 2], [0.05, 0.05, H - t],
                               style="furniture", label="desk_leg", texel=TEXEL["furniture"])
    quads += box_quads([L / 2 - 0.3, 0.0, 0.33], [0.42, D - 0.2, 0.6], style="furniture", label="drawers",
                       texel=TEXEL["furniture"])
    layout["desk"] = {"centre": [0.0, 0.0], "length": L, "depth": D, "height": H}


def _desk_objects(rng: np.random.Generator, quads: list[Quad], layout: dict, desk: DeskSpec) -> None:
    """Monitor, laptop, keyboard, boxes, books and papers on the desk top (no overlaps)."""
    H = desk.height
    placed: list[tuple[np.ndarray, tuple, float]] = []  # footprint corners (4, 2), centre, radius
    objects = layout.setdefault("objects", [])

    def place(half_x: float, half_y: float, yaw: float, tries: int = 80, back: bool = False):
        """A free spot for an oriented footprint on the desk top, or None."""
        R2 = rot_z(yaw)[:2, :2]
        corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * [half_x + 0.01, half_y + 0.01] @ R2.T
        ext = np.abs(corners).max(axis=0)
        if np.any(2 * ext > [desk.length - 0.02, desk.depth - 0.02]):
            return None
        for _ in range(tries):
            x = rng.uniform(-desk.length / 2 + ext[0], desk.length / 2 - ext[0])
            lo_y = -desk.depth / 2 + ext[1] if not back else min(0.05, desk.depth / 2 - ext[1])
            y = rng.uniform(lo_y, desk.depth / 2 - ext[1])
            mine = corners + [x, y]
            r = float(np.hypot(*ext))
            if not any(np.hypot(x - c[0], y - c[1]) < r + rc and _overlap(mine, other) for other, c, rc in placed):
                placed.append((mine, (x, y), r))
                return x, y
        return None

    # Monitor: screen panel on a neck and a base plate, near the back edge, facing -y.
    for k in range(int(rng.integers(1, 3))):
        w, h = rng.uniform(0.45, 0.62), rng.uniform(0.3, 0.38)
        yaw = rng.normal(0, 0.15)
        pos = place(w / 2, 0.12, yaw, back=True)
        if pos is None:
            continue
        x, y = pos
        R = rot_z(yaw)
        quads += box_quads([x, y, H + 0.006], [0.22, 0.17, 0.012], R, "furniture", "monitor_base", TEXEL["furniture"])
        quads += box_quads([x, y + 0.02, H + 0.09], [0.05, 0.03, 0.16], R, "furniture", "monitor_neck", TEXEL["furniture"])
        screen = box_quads([x, y - 0.01, H + 0.1 + h / 2], [w, 0.03, h], R, "furniture", "monitor", TEXEL["furniture"],
                           bottom=True)
        screen[3] = face(screen[3].origin + screen[3].u_axis * screen[3].size_u / 2
                         + screen[3].v_axis * screen[3].size_v / 2, screen[3].normal, -UP,
                         screen[3].size_u, screen[3].size_v, "screen", "monitor_screen", TEXEL["object"])
        quads += screen
        objects.append({"kind": "monitor", "centre": [x, y, H], "size": [w, 0.03, h], "yaw": yaw})

    # Laptop: base and a lid opened to about 110 degrees.
    if rng.random() < 0.8:
        yaw = rng.normal(0, 0.3)
        pos = place(0.17, 0.13, yaw)
        if pos is not None:
            x, y = pos
            R = rot_z(yaw)
            quads += box_quads([x, y, H + 0.01], [0.33, 0.23, 0.02], R, "print", "laptop", TEXEL["object"])
            lid_R = R @ rot_x(np.radians(rng.uniform(15, 30)))
            hinge = np.array([x, y, H]) + R @ np.array([0.0, 0.115, 0.02])
            quads += box_quads(hinge + lid_R @ np.array([0.0, 0.0, 0.11]), [0.33, 0.008, 0.22], lid_R,
                               "screen", "laptop_lid", TEXEL["object"], bottom=True)
            objects.append({"kind": "laptop", "centre": [x, y, H], "yaw": yaw})

    # Keyboard, papers, then boxes and book stacks of varied size.
    for kind, n in (("keyboard", 1), ("paper", int(rng.integers(2, 5))), ("box", int(rng.integers(5, 10)))):
        for _ in range(n):
            yaw = rng.normal(0, 0.2) if kind != "box" else rng.uniform(0, np.pi)
            if kind == "keyboard":
                size = np.array([0.44, 0.14, 0.025])
            elif kind == "paper":
                size = np.array([0.21, 0.297, 0.002])[[0, 1, 2] if rng.random() < 0.5 else [1, 0, 2]]
            else:
                size = np.exp(rng.uniform(np.log([0.06, 0.06, 0.03]), np.log([0.32, 0.28, 0.3])))
            pos = place(size[0] / 2, size[1] / 2, yaw)
            if pos is None:
                continue
            x, y = pos
            if kind == "paper":
                quads.append(face([x, y, H + 0.001], UP, rot_z(yaw) @ np.array([0, -1, 0]), size[0], size[1],
                                  "print", "paper", TEXEL["object"]))
            else:
                quads += box_quads([x, y, H + size[2] / 2], size, rot_z(yaw), "print", kind, TEXEL["object"])
            objects.append({"kind": kind, "centre": [x, y, H], "size": size.tolist(), "yaw": yaw})


def _room_objects(rng: np.random.Generator, quads: list[Quad], layout: dict, room, keep_out_xy,
                  clearance: float, focus_xy: np.ndarray | None) -> None:
    """Side tables near the focus points, cabinets and shelves against the walls, crates
    (near the focus points when given) and a chair on the floor, posters and a door."""
    x0, x1, y0, y1, height = room
    objects = layout.setdefault("objects", [])
    desk = layout["desk"]
    taken: list[tuple[float, float, float]] = [(0.0, 0.0, float(np.hypot(desk["length"], desk["depth"]) / 2))]

    def try_place(half, sampler, tries=40):
        """(x, y, yaw) of a footprint with half sizes ``half`` clear of others and of the path."""
        for _ in range(tries):
            x, y, yaw = sampler()
            r = float(np.hypot(*half))
            if any(np.hypot(x - tx, y - ty) < r + tr + 0.05 for tx, ty, tr in taken):
                continue
            if not (x0 + r * 0.2 <= x <= x1 - r * 0.2 and y0 + r * 0.2 <= y <= y1 - r * 0.2):
                continue
            if not _footprint_clear((x, y), half, yaw, keep_out_xy, clearance):
                continue
            taken.append((x, y, r))
            return x, y, yaw
        return None

    def against_wall(half):
        def sample():
            wall = int(rng.integers(4))
            if wall < 2:
                x = x0 + half[1] + 0.01 if wall == 0 else x1 - half[1] - 0.01
                return x, rng.uniform(y0 + half[0], y1 - half[0]), np.pi / 2
            y = y0 + half[1] + 0.01 if wall == 2 else y1 - half[1] - 0.01
            return rng.uniform(x0 + half[0], x1 - half[0]), y, 0.0
        return sample

    def anywhere():
        return rng.uniform(x0 + 0.3, x1 - 0.3), rng.uniform(y0 + 0.3, y1 - 0.3), rng.uniform(0, np.pi)

    def near_focus():
        if focus_xy is None or len(focus_xy) == 0 or rng.random() < 0.25:
            return anywhere()
        x, y = focus_xy[int(rng.integers(len(focus_xy)))] + rng.normal(0, 0.15, 2)
        return float(x), float(y), rng.uniform(0, np.pi)

    if focus_xy is not None:  # side tables with things on them where the camera looks
        for _ in range(6):
            size = np.array([rng.uniform(0.6, 1.2), rng.uniform(0.5, 0.7), rng.uniform(0.6, 0.76)])
            pos = try_place(size[:2] / 2, near_focus)
            if pos is None:
                continue
            x, y, yaw = pos
            R = rot_z(yaw)
            quads.extend(box_quads([x, y, size[2] - 0.015], [size[0], size[1], 0.03], R, "wood", "table",
                                   TEXEL["desk"], bottom=True))
            quads.extend(box_quads([x, y, (size[2] - 0.03) / 2], [size[0] - 0.1, size[1] - 0.1, size[2] - 0.03], R,
                                   "furniture", "table_base", TEXEL["furniture"]))
            for _ in range(int(rng.integers(1, 4))):
                item = np.exp(rng.uniform(np.log([0.06, 0.06, 0.03]), np.log([0.3, 0.25, 0.3])))
                off = (rng.uniform(-0.5, 0.5, 2) * np.maximum(size[:2] - item[:2], 0.0))
                centre = np.array([x, y, size[2] + item[2] / 2]) + R @ np.array([off[0], off[1], 0.0])
                quads.extend(box_quads(centre, item, rot_z(yaw + rng.normal(0, 0.3)), "print", "table_item"))
            objects.append({"kind": "table", "centre": [x, y, 0.0], "size": size.tolist(), "yaw": yaw})

    for _ in range(int(rng.integers(3, 6))):  # cabinets, shelves
        size = np.array([rng.uniform(0.6, 1.4), rng.uniform(0.35, 0.5), rng.uniform(0.7, 2.0)])
        pos = try_place(size[:2] / 2, against_wall(size[:2] / 2))
        if pos is not None:
            quads.extend(box_quads([pos[0], pos[1], size[2] / 2], size, rot_z(pos[2]), "furniture", "cabinet",
                                   TEXEL["furniture"]))
            objects.append({"kind": "cabinet", "centre": [pos[0], pos[1], 0.0], "size": size.tolist(), "yaw": pos[2]})
    for _ in range(int(rng.integers(4, 9))):  # crates and boxes on the floor, some stacked
        size = np.exp(rng.uniform(np.log([0.25, 0.25, 0.15]), np.log([0.7, 0.6, 0.6])))
        pos = try_place(size[:2] / 2, near_focus)
        if pos is None:
            continue
        R = rot_z(pos[2])
        quads.extend(box_quads([pos[0], pos[1], size[2] / 2], size, R, "print", "crate", TEXEL["furniture"]))
        if rng.random() < 0.4:
            top = size * rng.uniform(0.4, 0.8, 3)
            quads.extend(box_quads([pos[0], pos[1], size[2] + top[2] / 2], top, rot_z(pos[2] + rng.normal(0, 0.3)),
                                   "print", "crate", TEXEL["object"]))
        objects.append({"kind": "crate", "centre": [pos[0], pos[1], 0.0], "size": size.tolist(), "yaw": pos[2]})
    chair = try_place((0.25, 0.25), anywhere)
    if chair is not None:
        x, y, yaw = chair
        R = rot_z(yaw)
        quads.extend(box_quads([x, y, 0.45], [0.46, 0.46, 0.06], R, "furniture", "chair", TEXEL["furniture"], bottom=True))
        quads.extend(box_quads(np.array([x, y, 0.75]) + R @ [0, 0.21, 0], [0.44, 0.04, 0.5], R, "furniture", "chair",
                               TEXEL["furniture"], bottom=True))
        quads.extend(box_quads([x, y, 0.21], [0.06, 0.06, 0.42], R, "furniture", "chair", TEXEL["furniture"]))
        objects.append({"kind": "chair", "centre": [x, y, 0.0], "yaw": yaw})

    # Posters and a door on the walls, 4 mm in front of them.
    walls = [([x0, 0, 0], [1, 0, 0], (y0, y1)), ([x1, 0, 0], [-1, 0, 0], (y0, y1)),
             ([0, y0, 0], [0, 1, 0], (x0, x1)), ([0, y1, 0], [0, -1, 0], (x0, x1))]
    for i, (p, n, (a0, a1)) in enumerate(walls):
        along = np.array([0.0, 1.0, 0.0]) if i < 2 else np.array([1.0, 0.0, 0.0])
        for k in range(int(rng.integers(2, 5)) + (1 if i == 0 else 0)):
            door = i == 0 and k == 0
            w, h = (0.9, 2.05) if door else (rng.uniform(0.3, 1.2), rng.uniform(0.3, 0.9))
            t = rng.uniform(a0 + w / 2 + 0.1, a1 - w / 2 - 0.1)
            zc = h / 2 if door else rng.uniform(1.0, min(2.1, height - h / 2 - 0.1))
            centre = np.array(p, np.float64) * np.abs(n) + along * t + UP * zc + 0.004 * np.asarray(n, np.float64)
            quads.append(face(centre, n, -UP, w, h, "furniture" if door else "print", "door" if door else "poster",
                              TEXEL["poster"]))


def build_scene(scene_seed: int, desk: DeskSpec | None = None, room: tuple | None = None,
                keep_out: np.ndarray | None = None, clearance: float = 0.45,
                T_world_scene: np.ndarray | None = None, focus: np.ndarray | None = None) -> Scene:
    """Build an office scene in the scene frame.

    desk: its size (default: drawn from the seed); room: (x0, x1, y0, y1, height) in metres
    (default: 2.6 m beyond the desk on every side); keep_out: (K, 3) scene-frame points
    (camera positions) that furniture must stay ``clearance`` metres away from (in plan);
    focus: (F, 2) scene-frame floor points the camera looks at, where side tables and
    crates are preferably put.
    """
    rng = np.random.default_rng([int(scene_seed), 7])
    if desk is None:
        desk = DeskSpec(float(rng.uniform(1.4, 1.8)), float(rng.uniform(0.75, 0.9)), 0.74)
    if room is None:
        room = (-desk.length / 2 - 2.6, desk.length / 2 + 2.6, -desk.depth / 2 - 2.6, desk.depth / 2 + 2.6, 2.7)
    x0, x1, y0, y1, height = (float(v) for v in room)
    room = (x0, x1, y0, y1, height)
    keep_xy = None if keep_out is None else np.asarray(keep_out, np.float64)[:, :2]
    quads = room_quads(x0, x1, y0, y1, height)
    layout: dict = {"room": {"x0": x0, "x1": x1, "y0": y0, "y1": y1, "height": height}}
    _desk(quads, layout, desk)
    _desk_objects(rng, quads, layout, desk)
    focus_xy = None if focus is None else np.asarray(focus, np.float64).reshape(-1, 2)
    _room_objects(rng, quads, layout, room, keep_xy, clearance, focus_xy)
    lights = np.array([[sx * desk.length * 0.6, sy * 1.2, height - 0.05] for sx in (-1, 1) for sy in (-1, 1)])
    lights = np.vstack([lights, [[rng.uniform(x0, x1), rng.uniform(y0, y1), height - 0.05]]])
    layout["n_quads"] = len(quads)
    layout["lights"] = lights.tolist()
    T = np.eye(4) if T_world_scene is None else np.asarray(T_world_scene, np.float64)
    layout["T_world_scene"] = T.tolist()
    log.debug("scene: %d quads, %d objects", len(quads), len(layout.get("objects", [])))
    return Scene(quads, T, lights, layout)

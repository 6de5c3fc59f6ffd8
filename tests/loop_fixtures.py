"""Synthetic keyframe maps with known ground truth, for loop-closing and relocalisation
tests and benchmarks (no images: keypoints, descriptors and BoW vectors are made directly),
and a circular camera path (TUM file) to render a small loop with the scene renderer.

The scene is a ring of points on the inside of a vertical cylinder; cameras move on a
smaller circle looking outwards, so a run of keyframes that goes round more than once
revisits its first views. Each scene point has a fixed ORB-like descriptor and pyramid
level; an observation is its projection with pixel noise of its level's sigma and its
descriptor with a few bits flipped. Its BoW word and feature-vector node are functions of
the scene point, so vocabulary matching finds the true correspondences.

The map is built as a tracker with drift would build it: keyframe k's estimate lives in a
world distorted by a similarity ``G_k`` that grows along the path as odometry drift does
(each step adds the same small error in the camera frame: scale, yaw, sideways shift); a point is created by the first keyframe seeing it, placed in that
keyframe's distorted world, and re-used by the keyframes that see it up to
``point_lifetime`` keyframes later; after that a new point is made (the map then holds
duplicates, and a revisit always creates them, as a real tracker does). Observations are
the estimated points projected with the estimated poses, plus noise, so the map is
consistent in the images; in 3D a point carries its creator's drift, so the points of a
keyframe disagree by up to ``point_lifetime`` steps of drift, which bounds how well a loop
similarity can be measured.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from orbslam_hgcn.features.keypoints import KeypointSet
from orbslam_hgcn.geometry.camera import PinholeCamera
from orbslam_hgcn.geometry.se3 import inv_S, inv_T
from orbslam_hgcn.map import Frame, KeyFrame, Map
from orbslam_hgcn.trajectory import Trajectory, write_tum
from orbslam_hgcn.vocabulary.bow import BowVector, FeatureVector

log = logging.getLogger(__name__)

SCALE_FACTORS = 1.2 ** np.arange(8)
N_WORDS = 5000
N_NODES = 97


def ring_camera() -> PinholeCamera:
    return PinholeCamera(500.0, 500.0, 320.0, 240.0, 640, 480, fps=30.0, name="ring")


@dataclass
class RingScene:
    """Ground truth: points (P, 3), descriptors (P, 32) uint8, octave (P,), camera."""

    points: np.ndarray
    desc: np.ndarray
    octave: np.ndarray
    camera: PinholeCamera

    @classmethod
    def make(cls, n_points: int = 2500, radius: float = 4.0, height: float = 1.5, seed: int = 0) -> RingScene:
        rng = np.random.default_rng(seed)
        a = rng.uniform(0, 2 * np.pi, n_points)
        r = radius * rng.uniform(0.85, 1.0, n_points)
        pts = np.stack([r * np.cos(a), r * np.sin(a), rng.uniform(-height, height, n_points)], axis=1)
        desc = rng.integers(0, 256, (n_points, 32), dtype=np.uint8)
        octave = rng.integers(0, 4, n_points).astype(np.int32)
        return cls(pts, desc, octave, ring_camera())


def ring_pose(angle: float, radius: float = 1.0) -> np.ndarray:
    """(4, 4) T_wc of a camera on the circle at ``angle`` (rad), looking outwards, y down."""
    c, s = np.cos(angle), np.sin(angle)
    z = np.array([c, s, 0.0])
    y = np.array([0.0, 0.0, -1.0])
    x = np.cross(y, z)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], axis=1)
    T[:3, 3] = radius * z
    return T


def step_error(scale_rate: float, yaw_deg_rate: float, trans_rate: float) -> np.ndarray:
    """(4, 4) similarity E: the error each step of visual odometry adds, in the camera
    frame (scale, a turn about the camera's vertical axis, a sideways shift)."""
    E = np.eye(4)
    E[:3, :3] = (1.0 + scale_rate) * Rotation.from_euler("y", yaw_deg_rate, degrees=True).as_matrix()
    E[:3, 3] = (trans_rate, 0.0, 0.0)
    return E


def drift_chain(T_wc: np.ndarray, E: np.ndarray) -> np.ndarray:
    """(K, 4, 4) similarities G_k (true world -> keyframe k's drifted world) such that the
    estimated poses ``S_k = T_cw,k G_k^-1`` have relative motions ``E T_cw,k+1 T_wc,k``
    (G_0 = I): odometry drift, one error E per step."""
    G = [np.eye(4)]
    for k in range(1, len(T_wc)):
        G.append(G[-1] @ T_wc[k] @ inv_S(E) @ inv_T(T_wc[k]))
    return np.array(G)


def observe(
    scene: RingScene, T_wc: np.ndarray, rng: np.random.Generator, noise: float = 0.5, bit_flips: int = 3, clutter: int = 50
) -> tuple[KeypointSet, np.ndarray]:
    """Keypoints of the scene points visible from T_wc, plus ``clutter`` random features.

    Returns (KeypointSet, (N,) int64 scene point of each feature, -1 for clutter)."""
    cam = scene.camera
    T_cw = inv_T(T_wc)
    X_c = scene.points @ T_cw[:3, :3].T + T_cw[:3, 3]
    z = X_c[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = np.stack([cam.fx * X_c[:, 0] / z + cam.cx, cam.fy * X_c[:, 1] / z + cam.cy], axis=1)
    vis = np.flatnonzero((z > 0.1) & (uv[:, 0] >= 8) & (uv[:, 0] < cam.width - 8) & (uv[:, 1] >= 8) & (uv[:, 1] < cam.height - 8))
    octave = np.concatenate([scene.octave[vis], rng.integers(0, 4, clutter)]).astype(np.int32)
    sigma = noise * SCALE_FACTORS[octave]
    uv_all = np.concatenate([uv[vis], rng.uniform([8, 8], [cam.width - 8, cam.height - 8], (clutter, 2))])
    uv_all = uv_all + rng.normal(0, 1, uv_all.shape) * sigma[:, None]
    desc = np.concatenate([scene.desc[vis], rng.integers(0, 256, (clutter, 32), dtype=np.uint8)])
    bits = rng.integers(0, 256, (len(desc), bit_flips))
    rows = np.repeat(np.arange(len(desc)), bit_flips)
    np.bitwise_xor.at(desc, (rows, bits.reshape(-1) // 8), (1 << (bits.reshape(-1) % 8)).astype(np.uint8))
    n = len(uv_all)
    kps = KeypointSet(
        uv_raw=uv_all.astype(np.float32), uv=uv_all.astype(np.float64), octave=octave,
        angle=rng.normal(0, 2.0, n).astype(np.float32), response=np.ones(n, np.float32), desc=desc,
        scale_factors=SCALE_FACTORS.copy(),
    )  # fmt: skip
    return kps, np.concatenate([vis, np.full(clutter, -1)]).astype(np.int64)


def bow_of(scene_ids: np.ndarray, rng: np.random.Generator) -> tuple[BowVector, FeatureVector]:
    """BoW vector (word = scene id mod N_WORDS, IDF 1) and feature vector (node = scene id
    mod N_NODES) of a frame; clutter features get random words and nodes."""
    ids = np.asarray(scene_ids)
    words = np.where(ids >= 0, ids % N_WORDS, rng.integers(0, N_WORDS, len(ids)))
    nodes = np.where(ids >= 0, ids % N_NODES, rng.integers(0, N_NODES, len(ids)))
    return BowVector.from_words(words, np.ones(N_WORDS)), FeatureVector.from_nodes(nodes)


@dataclass
class RingMap:
    """A built map: the Map, ground-truth T_wc (K, 4, 4) of its keyframes (in id order),
    the scene point of every feature of each keyframe, the scene itself, and the drift
    G (K, 4, 4) of every keyframe (true world -> its estimated world)."""

    map: Map
    T_wc_true: np.ndarray
    scene_ids: list[np.ndarray]
    scene: RingScene
    G: np.ndarray

    def keyframe_centres(self) -> tuple[np.ndarray, np.ndarray]:
        """((K, 3) estimated, (K, 3) true) centres of the good keyframes."""
        kfs = self.map.keyframes()
        return np.array([kf.center for kf in kfs]), self.T_wc_true[[kf.id for kf in kfs], :3, 3]


def build_ring_map(
    n_keyframes: int = 36,
    turns: float = 1.2,
    scale_rate: float = 0.002,
    yaw_deg_rate: float = 0.05,
    trans_rate: float = 0.003,
    point_lifetime: int = 3,
    noise: float = 0.5,
    seed: int = 0,
    scene: RingScene | None = None,
    stop: int | None = None,
    on_keyframe: Callable[[KeyFrame], object] | None = None,
    m: Map | None = None,
) -> RingMap:
    """Keyframes round the ring (``turns`` > 1 revisits the start), drifted as described in
    the module docstring (per-step error :func:`step_error`).

    The keyframes are made one at a time as a tracker and local mapper would (points and
    connections of each are up to date when it is added), and ``on_keyframe`` (e.g. a loop
    closer's ``process``) is called with each. stop: make only the first ``stop`` of the
    ``n_keyframes`` (the path is that of all of them). m: an empty map to fill (default a
    new one). Every keyframe has BoW vectors.
    """
    rng = np.random.default_rng(seed + 1)
    scene = scene or RingScene.make(seed=seed)
    m = Map() if m is None else m
    angles = np.linspace(0.0, 2 * np.pi * turns, n_keyframes)[:stop]
    T_all = np.array([ring_pose(a) for a in angles])
    G_all = drift_chain(T_all, step_error(scale_rate, yaw_deg_rate, trans_rate))
    current: dict[int, tuple[int, int]] = {}  # scene id -> (map point id, keyframe that made it)
    rm = RingMap(m, T_all, [], scene, G_all)
    cam = scene.camera
    for k, (T_wc, G) in enumerate(zip(T_all, G_all)):
        kps, ids = observe(scene, T_wc, rng, noise=noise)
        S_cw = inv_T(T_wc) @ inv_S(G)  # drifted world -> camera (a similarity of scale 1/s)
        T_cw = S_cw / np.cbrt(np.linalg.det(S_cw[:3, :3]))
        T_cw[3] = (0.0, 0.0, 0.0, 1.0)
        slots = np.flatnonzero(ids >= 0)
        pids = np.full(len(slots), -1, dtype=np.int64)  # -1: a new point
        for n, slot in enumerate(slots.tolist()):
            prev = current.get(int(ids[slot]))
            if prev is not None and k - prev[1] <= point_lifetime:
                pid = prev[0]
                while m.point(pid).bad and m.point(pid).replaced_by >= 0:  # fused meanwhile
                    pid = m.point(pid).replaced_by
                pids[n] = -1 if m.point(pid).bad or pid in pids[:n] else pid
        new = pids < 0
        X = np.empty((len(slots), 3))
        X[~new] = m.positions(pids[~new])
        X[new] = scene.points[ids[slots[new]]] @ G[:3, :3].T + G[:3, 3]
        # Observations agree with the estimates (a locally consistent map, as local BA
        # leaves it): the estimated points projected with the estimated pose, plus noise.
        X_c = X @ T_cw[:3, :3].T + T_cw[:3, 3]
        uv = np.stack([cam.fx * X_c[:, 0] / X_c[:, 2] + cam.cx, cam.fy * X_c[:, 1] / X_c[:, 2] + cam.cy], axis=1)
        uv += rng.normal(0, 1, uv.shape) * (noise * SCALE_FACTORS[kps.octave[slots]])[:, None]
        new_uv = kps.uv.copy()
        new_uv[slots] = uv
        kps = dataclasses.replace(kps, uv=new_uv, uv_raw=new_uv.astype(np.float32))
        frame = Frame(k, float(k), cam, kps, T_cw)
        frame.bow, frame.featvec = bow_of(ids, rng)
        kf = m.add_keyframe(frame)
        for n in np.flatnonzero(new).tolist():
            pids[n] = m.add_map_point(X[n], kf.id)
        m.add_observations(kf.id, pids, slots)
        for sid, pid in zip(ids[slots[new]].tolist(), pids[new].tolist()):
            current[sid] = (pid, k)
        rm.scene_ids.append(ids)
        m.update_points(pids)
        m.update_connections(kf.id)
        if on_keyframe is not None:
            on_keyframe(kf)
    return rm


def frame_at(scene: RingScene, T_wc: np.ndarray, frame_id: int, seed: int = 0) -> tuple[Frame, np.ndarray]:
    """A frame seen from T_wc with its BoW vectors (no pose), and the (N,) scene point of
    each of its features (-1 for clutter)."""
    rng = np.random.default_rng(seed)
    kps, ids = observe(scene, T_wc, rng)
    f = Frame(frame_id, float(frame_id), scene.camera, kps)
    f.bow, f.featvec = bow_of(ids, rng)
    return f, ids


def true_loop_similarity(rm: RingMap, kf_id: int, loop_kf_id: int) -> np.ndarray:
    """(4, 4) the corrected similarity pose S_cw of keyframe ``kf_id`` in the world of
    ``loop_kf_id``: loop-world points into the keyframe's camera at its own (drifted)
    scale, ``s(G_k) T_cw,k G_loop^-1``."""
    G_k, G_l = rm.G[kf_id], rm.G[loop_kf_id]
    S = inv_T(rm.T_wc_true[kf_id]) @ inv_S(G_l)
    S[:3] *= np.cbrt(np.linalg.det(G_k[:3, :3]))
    return S


def true_loop_matches(rm: RingMap, kf_id: int, loop_kf_id: int) -> np.ndarray:
    """(N,) the loop keyframe's map point seen by each feature of ``kf_id`` (by scene
    point identity), -1 elsewhere."""
    kf, lk = rm.map.keyframe(kf_id), rm.map.keyframe(loop_kf_id)
    owner = {int(rm.scene_ids[loop_kf_id][s]): int(p) for s, p in zip(*lk.observed_points())}
    ids = rm.scene_ids[kf_id]
    out = np.full(len(kf.keypoints), -1, dtype=np.int64)
    for slot in np.flatnonzero(ids >= 0).tolist():
        out[slot] = owner.get(int(ids[slot]), -1)
    return out


def duplicate_count(rm: RingMap, kf_subset: list[KeyFrame] | None = None) -> int:
    """Scene points represented by more than one good map point."""
    m = rm.map
    owners: dict[int, set[int]] = {}
    for kf in kf_subset or m.keyframes():
        ids = rm.scene_ids[kf.id]
        for slot, pid in zip(*kf.observed_points()):
            sid = int(ids[slot])
            if sid >= 0 and not m.point(int(pid)).bad:
                owners.setdefault(sid, set()).add(int(pid))
    return sum(len(v) > 1 for v in owners.values())


def circle_ground_truth(path: Path, radius: float = 1.2, turns: float = 1.3, seconds: float = 20.0,
                        height: float = 0.5) -> Path:
    """Write a TUM trajectory (100 Hz) circling the origin at ``radius`` and ``height`` m,
    looking at the origin, ``turns`` turns in ``seconds``; returns ``path``."""
    t = np.arange(0.0, seconds + 1e-9, 0.01)
    a = 2 * np.pi * turns * t / seconds
    poses = np.tile(np.eye(4), (len(t), 1, 1))
    c = np.stack([radius * np.cos(a), radius * np.sin(a), np.full_like(a, height)], axis=1)
    z = -c / np.linalg.norm(c, axis=1, keepdims=True)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    poses[:, :3, 0], poses[:, :3, 1], poses[:, :3, 2], poses[:, :3, 3] = x, np.cross(z, x), z, c
    path.parent.mkdir(parents=True, exist_ok=True)
    write_tum(path, Trajectory(1000.0 + t, poses))
    return path

"""An atlas in one file: its maps' keyframes, map points, their links and graphs, as a
versioned ``.npz``.

File format (version 2), one zip archive of numpy arrays read without pickle:

* ``_magic``: the string ``orbslam_hgcn-map``; ``_format_version``: int
  :data:`FORMAT_VERSION`; ``_meta``: JSON text (camera, map config, the maps (id and origin
  keyframe) and the active one, next keyframe id, counts, and whatever the caller adds,
  such as the vocabulary reference);
* ``kf_map``: the map of each keyframe; ``pt_owner``: the map of each point;
* keyframes (K good ones, by id): ``kf_id``, ``kf_frame_id``, ``kf_timestamp``,
  ``kf_T_cw`` (K, 4, 4), ``kf_parent`` (spanning tree), ``kf_flags`` (K, 3)
  (first_connection, not_erase, to_be_erased); their features concatenated, keyframe k
  owning rows ``kf_feat_offset[k]:kf_feat_offset[k + 1]``: ``kp_uv_raw``, ``kp_uv``,
  ``kp_octave``, ``kp_angle``, ``kp_response``, ``kp_desc`` (F, 32) uint8, ``kp_point``
  (map point id per slot, -1 none) and ``kp_node`` (feature-vector node, -1 none);
  pyramid scales ``scale_factors`` split by ``kf_scale_offset``; BoW vectors ``bow_words``
  / ``bow_weights`` split by ``kf_bow_offset``; ``kf_has_bow`` / ``kf_has_featvec``;
* graphs: ``covisibility`` (S, 3) int64 rows (a, b, shared points) with a < b, every pair
  sharing a point; ``loop_edges`` (L, 2) int64 with a < b;
* map points, every id ever created (P rows; bad points hold no observation):
  ``pt_position``, ``pt_normal``, ``pt_min_dist``, ``pt_max_dist``, ``pt_desc``,
  ``pt_found``, ``pt_visible``, ``pt_first_kf``, ``pt_ref_kf``, ``pt_bad``,
  ``pt_replaced_by``; observations in insertion order, point p owning rows
  ``obs_offset[p]:obs_offset[p + 1]`` of ``obs_kf`` / ``obs_idx``.

Culled (bad) keyframes are not written. Reading checks the header, every array's CRC, the
shapes, and that point slots, observations and covisibility weights agree; any problem is
a :class:`MapFileError` naming the file. The BoW arrays are returned as plain arrays: the
caller, who holds the vocabulary, turns them into vectors. Version 1 files (one map, no
``kf_map`` / ``pt_owner``, origin and next keyframe id in the header) are read as an atlas
of that one map.
"""

from __future__ import annotations

import dataclasses
import datetime
import json
import logging
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from orbslam_hgcn.config import MapConfig, camera_from_dict, camera_to_dict
from orbslam_hgcn.errors import OrbslamError
from orbslam_hgcn.features.keypoints import KeypointSet
from orbslam_hgcn.map.keyframe import KeyFrame
from orbslam_hgcn.map.map import Map
from orbslam_hgcn.map.mappoint import PointStore
from orbslam_hgcn.npzfile import atomic_save_npz, read_versioned_npz

log = logging.getLogger(__name__)

MAGIC = "orbslam_hgcn-map"
FORMAT_VERSION = 2
READABLE_VERSIONS = (1, 2)
_KP_FIELDS = ("uv_raw", "uv", "octave", "angle", "response", "desc")
_PT_FIELDS = ("position", "normal", "min_dist", "max_dist", "desc", "found", "visible", "first_kf", "ref_kf", "bad",
              "replaced_by")


class MapFileError(OrbslamError):
    """A map file is missing, truncated, corrupt, of another version or inconsistent."""


@dataclass
class MapFile:
    """What :func:`read_map` returns.

    map: the atlas's active map; atlas: the rebuilt Atlas (keyframes have
    ``bow``/``featvec`` None); meta: the header dict;
    bow: {kf_id: ((B,) int32 words, (B,) float32 weights)} for keyframes that had a BoW
    vector; nodes: {kf_id: (N,) int32 feature-vector node of each feature, -1 none} for
    keyframes that had a feature vector; path: the file read.
    """

    map: Map
    meta: dict[str, Any]
    bow: dict[int, tuple[np.ndarray, np.ndarray]]
    nodes: dict[int, np.ndarray]
    path: Path
    atlas: Any = None


def _offsets(lengths: list[int]) -> np.ndarray:
    return np.concatenate([[0], np.cumsum(lengths, dtype=np.int64)]).astype(np.int64)


def map_to_arrays(m: Map | Any, meta: dict[str, Any] | None = None) -> dict[str, np.ndarray]:
    """Every array of the file format (header included) for an atlas, or the atlas of map
    ``m`` (a map without one is written as an atlas of one map), read under its lock.

    meta: extra JSON-able header entries (e.g. ``{"vocabulary": {...}}``).
    """
    atlas = m if not isinstance(m, Map) else m.atlas
    maps = list(atlas.maps.values()) if atlas is not None else [m]
    maps = [mm for mm in maps if mm.n_keyframes()]  # a map just started holds nothing yet
    if not maps:
        raise MapFileError("the map has no keyframes; nothing to save")
    active = atlas.active if atlas is not None else m
    if active not in maps:
        active = max(maps, key=lambda mm: mm.n_keyframes())
    with maps[0].lock:
        kfs = [kf for mm in maps for kf in mm.keyframes()]
        kf_map = [mm.map_id for mm in maps for _ in mm.keyframes()]
        if not kfs:
            raise MapFileError("the map has no keyframes; nothing to save")
        camera = kfs[0].camera
        if any(kf.camera != camera for kf in kfs):
            raise MapFileError("the map's keyframes come from different cameras; one camera per map file")
        a: dict[str, np.ndarray] = {
            "kf_id": np.array([kf.id for kf in kfs], np.int64),
            "kf_map": np.array(kf_map, np.int64),
            "kf_frame_id": np.array([kf.frame_id for kf in kfs], np.int64),
            "kf_timestamp": np.array([kf.timestamp for kf in kfs], np.float64),
            "kf_T_cw": np.stack([kf.T_cw for kf in kfs]).astype(np.float64),
            "kf_parent": np.array([kf.parent for kf in kfs], np.int64),
            "kf_flags": np.array([(kf.first_connection, kf.not_erase, kf.to_be_erased) for kf in kfs], bool),
            "kf_feat_offset": _offsets([len(kf) for kf in kfs]),
            "kf_scale_offset": _offsets([len(kf.keypoints.scale_factors) for kf in kfs]),
            "scale_factors": np.concatenate([kf.keypoints.scale_factors for kf in kfs]).astype(np.float64),
            "kp_point": np.concatenate([kf._point_ids for kf in kfs]).astype(np.int64),
        }
        for name in _KP_FIELDS:
            a[f"kp_{name}"] = np.concatenate([getattr(kf.keypoints, name) for kf in kfs])
        # BoW vectors (any object with words/weights arrays) and feature vectors
        # ({node: feature indices}) as computed by the vocabulary.
        a["kf_has_bow"] = np.array([kf.bow is not None for kf in kfs], bool)
        bows = [kf.bow for kf in kfs if kf.bow is not None]
        a["kf_bow_offset"] = _offsets([len(kf.bow.words) if kf.bow is not None else 0 for kf in kfs])
        a["bow_words"] = np.concatenate([np.zeros(0, np.int32)] + [np.asarray(b.words, np.int32) for b in bows])
        a["bow_weights"] = np.concatenate([np.zeros(0, np.float32)] + [np.asarray(b.weights, np.float32) for b in bows])
        a["kf_has_featvec"] = np.array([kf.featvec is not None for kf in kfs], bool)
        nodes = []
        for kf in kfs:
            n = np.full(len(kf), -1, np.int32)
            for node, idx in (kf.featvec or {}).items():
                n[np.asarray(idx, np.int64)] = node
            nodes.append(n)
        a["kp_node"] = np.concatenate(nodes)
        covis = sorted((kf.id, o, w) for kf in kfs for o, w in kf.shared.items() if kf.id < o)
        a["covisibility"] = np.array(covis, np.int64).reshape(-1, 3)
        loops = sorted({(min(kf.id, o), max(kf.id, o)) for kf in kfs for o in kf.loop_edges})
        a["loop_edges"] = np.array(loops, np.int64).reshape(-1, 2)
        s = maps[0]._pts
        for name in _PT_FIELDS:
            a[f"pt_{name}"] = getattr(s, name)[: s.n].copy()
        a["pt_owner"] = s.owner[: s.n].copy()
        # Points of maps no longer in the atlas (discarded) are written as bad.
        a["pt_bad"] = a["pt_bad"] | ~np.isin(a["pt_owner"], [mm.map_id for mm in maps])
        a["obs_offset"] = _offsets([len(o) for o in s.obs])
        a["obs_kf"] = np.array([k for o in s.obs for k in o], np.int64)
        a["obs_idx"] = np.array([i for o in s.obs for i in o.values()], np.int64)
        next_kf = atlas._next_kf_id if atlas is not None else m._next_kf_id
        header = {
            "created": datetime.datetime.now(datetime.timezone.utc).replace(microsecond=0).isoformat(),
            "n_keyframes": len(kfs),
            "n_points": int(np.count_nonzero(~a["pt_bad"])),
            "maps": [{"map_id": mm.map_id, "origin_id": int(mm.origin_id)} for mm in maps],
            "active_map": int(active.map_id) if active is not None else int(maps[0].map_id),
            "next_kf_id": int(max(next_kf, max(kf.id for kf in kfs) + 1)),
            "next_map_id": int(atlas._next_map_id) if atlas is not None else 1,
            "camera": camera_to_dict(camera),
            "map_config": dataclasses.asdict(maps[0].config),
        }
    header.update(meta or {})
    a["_magic"] = np.array(MAGIC)
    a["_format_version"] = np.array(FORMAT_VERSION, np.int64)
    a["_meta"] = np.array(json.dumps(header, sort_keys=True))
    return a


def save_map(path: str | Path, m: Map | Any, meta: dict[str, Any] | None = None) -> Path:
    """Write the atlas of map ``m`` (or atlas ``m``) to ``path`` (atomically: a temporary
    file beside it, then a rename)."""
    arrays = map_to_arrays(m, meta)
    path = atomic_save_npz(path, arrays)
    log.info("wrote map (%d keyframes, %d points) to %s", len(arrays["kf_id"]), int((~arrays["pt_bad"]).sum()), path)
    return path


def read_header(path: str | Path) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """All arrays of a map file and its header dict; damage or another version is a
    MapFileError naming the file."""
    path = Path(path)
    arrays = read_versioned_npz(path, "map", MAGIC, READABLE_VERSIONS, MapFileError,
                                "build the map again with 'orbslam-hgcn run ... --save-map'")
    try:
        meta = json.loads(str(arrays["_meta"]))
        if not isinstance(meta, dict):
            raise ValueError("not a mapping")
    except (KeyError, ValueError) as exc:
        raise MapFileError(f"{path}: unreadable map header ({exc})") from None
    return arrays, meta


def read_map(path: str | Path) -> MapFile:
    """Rebuild the map stored in ``path`` (see the module text); MapFileError on any problem."""
    path = Path(path)
    arrays, meta = read_header(path)
    try:
        atlas, bow, nodes = _build(arrays, meta, path)
    except (KeyError, ValueError, IndexError, TypeError) as exc:
        raise MapFileError(f"{path}: corrupt map file ({type(exc).__name__}: {exc})") from None
    m = atlas.active
    log.info("read %d map(s) from %s; active map: %d keyframes, %d points", len(atlas), path, m.n_keyframes(),
             m.n_points())  # fmt: skip
    return MapFile(m, meta, bow, nodes, path, atlas)


def _check(cond: bool, message: str) -> None:
    if not cond:
        raise ValueError(message)


def _build(a: dict[str, np.ndarray], meta: dict[str, Any], path: Path) -> tuple[Any, dict, dict]:
    from orbslam_hgcn.map.atlas import Atlas

    camera = camera_from_dict(meta["camera"], path)
    names = {f.name for f in dataclasses.fields(MapConfig)}
    config = MapConfig(**{k: v for k, v in meta.get("map_config", {}).items() if k in names})
    ids = a["kf_id"].astype(np.int64)
    if "maps" in meta:  # version 2: an atlas
        map_specs = [(int(d["map_id"]), int(d["origin_id"])) for d in meta["maps"]]
        kf_map = a["kf_map"].astype(np.int64)
        owner = a["pt_owner"].astype(np.int64)
        active_id = int(meta["active_map"])
    else:  # version 1: one map
        map_specs = [(0, int(meta["origin_id"]))]
        kf_map = np.zeros(len(ids), np.int64)
        owner = np.zeros(len(a["pt_position"]), np.int64)
        active_id = 0
    _check(len(kf_map) == len(ids) and len(owner) == len(a["pt_position"]), "map membership arrays disagree in length")
    atlas = Atlas(config)
    atlas.maps.clear()
    maps: dict[int, Map] = {}
    for map_id, origin in map_specs:
        mm = Map(config, atlas=atlas, map_id=map_id)
        mm.origin_id = origin
        maps[map_id] = atlas.maps[map_id] = mm
    _check(active_id in maps and np.isin(kf_map, list(maps)).all(), "keyframes name a map that is not listed")
    atlas.active = maps[active_id]
    atlas._next_map_id = max(int(meta.get("next_map_id", 1)), max(maps) + 1)
    K = len(ids)
    feat_off, scale_off, bow_off = a["kf_feat_offset"], a["kf_scale_offset"], a["kf_bow_offset"]
    F = int(feat_off[-1])
    _check(K > 0 and len(np.unique(ids)) == K, "keyframe ids missing or repeated")
    for name, n in (("kf_feat_offset", K + 1), ("kf_scale_offset", K + 1), ("kf_bow_offset", K + 1)):
        _check(a[name].shape == (n,) and np.all(np.diff(a[name]) >= 0), f"'{name}' has a bad shape or order")
    _check(a["kf_T_cw"].shape == (K, 4, 4) and a["kf_flags"].shape == (K, 3), "keyframe pose or flag shape")
    for name in ("kf_frame_id", "kf_timestamp", "kf_parent", "kf_has_bow", "kf_has_featvec"):
        _check(a[name].shape == (K,), f"'{name}' has shape {a[name].shape}, expected ({K},)")
    for name in _KP_FIELDS + ("point", "node"):
        _check(len(a[f"kp_{name}"]) == F, f"'kp_{name}' holds {len(a[f'kp_{name}'])} rows, expected {F}")
    _check(a["kp_desc"].shape == (F, 32) and a["kp_desc"].dtype == np.uint8, "'kp_desc' is not (F, 32) uint8")
    _check(len(a["bow_words"]) == len(a["bow_weights"]) == int(bow_off[-1]), "BoW arrays disagree in length")
    P = len(a["pt_position"])
    for name in _PT_FIELDS:
        _check(len(a[f"pt_{name}"]) == P, f"'pt_{name}' holds {len(a[f'pt_{name}'])} rows, expected {P}")
    obs_off = a["obs_offset"]
    _check(obs_off.shape == (P + 1,) and len(a["obs_kf"]) == len(a["obs_idx"]) == int(obs_off[-1]),
           "observation arrays disagree in length")

    # Points: the store's arrays as saved, observations in their saved order.
    store = PointStore(capacity=max(P, 16))
    for name in _PT_FIELDS:
        getattr(store, name)[:P] = a[f"pt_{name}"]
    store.owner[:P] = owner
    store.n = P
    obs_kf, obs_idx = a["obs_kf"].tolist(), a["obs_idx"].tolist()
    bounds = obs_off.tolist()
    store.obs = [dict(zip(obs_kf[bounds[p]:bounds[p + 1]], obs_idx[bounds[p]:bounds[p + 1]])) for p in range(P)]
    atlas.points = store
    for mm in maps.values():
        mm._pts = store

    bow: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    nodes: dict[int, np.ndarray] = {}
    for k, kf_id in enumerate(ids.tolist()):
        f0, f1 = int(feat_off[k]), int(feat_off[k + 1])
        kps = KeypointSet(*(a[f"kp_{name}"][f0:f1] for name in _KP_FIELDS),
                          scale_factors=a["scale_factors"][int(scale_off[k]):int(scale_off[k + 1])])
        kf = KeyFrame(kf_id, int(a["kf_frame_id"][k]), float(a["kf_timestamp"][k]), camera, kps, a["kf_T_cw"][k])
        kf._point_ids[:] = a["kp_point"][f0:f1]
        kf.parent = int(a["kf_parent"][k])
        kf.first_connection, kf.not_erase, kf.to_be_erased = (bool(x) for x in a["kf_flags"][k])
        maps[int(kf_map[k])]._kfs[kf_id] = kf
        if a["kf_has_bow"][k]:
            b0, b1 = int(bow_off[k]), int(bow_off[k + 1])
            bow[kf_id] = (a["bow_words"][b0:b1].astype(np.int32), a["bow_weights"][b0:b1].astype(np.float32))
        if a["kf_has_featvec"][k]:
            nodes[kf_id] = a["kp_node"][f0:f1].astype(np.int32)
    atlas._next_kf_id = max(int(meta["next_kf_id"]), int(ids.max()) + 1)
    for mm in maps.values():
        _check(mm.origin_id in mm._kfs, f"origin keyframe {mm.origin_id} of map {mm.map_id} missing")

    # Links: slots against observations, tree, covisibility weights against a recount.
    kfs = {k: kf for mm in maps.values() for k, kf in mm._kfs.items()}
    for pid, obs in enumerate(store.obs):
        for k, idx in obs.items():
            _check(k in kfs and kfs[k]._point_ids[idx] == pid, f"point {pid} observation ({k}, {idx}) has no slot")
    n_slots = sum(int(np.count_nonzero(kf._point_ids >= 0)) for kf in kfs.values())
    _check(n_slots == len(obs_kf), f"{n_slots} linked slots but {len(obs_kf)} observations")
    for kf in kfs.values():
        if kf.parent >= 0:
            _check(kf.parent in kfs, f"keyframe {kf.id} has missing parent {kf.parent}")
            kfs[kf.parent].children.add(kf.id)
    for x, y, w in a["covisibility"].reshape(-1, 3).tolist():
        _check(x in kfs and y in kfs and w > 0, f"covisibility edge ({x}, {y}, {w}) is invalid")
        kfs[x].shared[y] = w
        kfs[y].shared[x] = w
    for kf in kfs.values():
        count: Counter[int] = Counter()
        for pid in kf._point_ids[kf._point_ids >= 0].tolist():
            count.update(o for o in store.obs[pid] if o != kf.id)
        _check(count == Counter(kf.shared), f"keyframe {kf.id}: covisibility weights disagree with the observations")
    for x, y in a["loop_edges"].reshape(-1, 2).tolist():
        _check(x in kfs and y in kfs, f"loop edge ({x}, {y}) names a missing keyframe")
        kfs[x].loop_edges.add(y)
        kfs[y].loop_edges.add(x)
    for pid, obs in enumerate(store.obs):
        for k in obs:
            _check(maps[int(owner[pid])].owns(k), f"point {pid} of map {owner[pid]} is observed by keyframe {k} "
                   "of another map")  # fmt: skip
    return atlas, bow, nodes

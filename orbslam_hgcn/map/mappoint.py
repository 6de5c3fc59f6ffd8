"""Map points: a struct-of-arrays store indexed by point id, a read-only view per point,
and the ORB-SLAM point descriptors (Mur-Artal, Montiel & Tardos, T-RO 2015, Sec. III-C):
representative descriptor, mean viewing direction, scale-invariance distance range.

Arrays (positions, normals, distance ranges, descriptors, counters, flags) are indexed by
point id, so the tracker can gather any set of points with one fancy index. Observations
are kept per point as ``{kf_id: feature index}`` in insertion order.
"""

from __future__ import annotations

import itertools
import logging
import time

import numpy as np

from orbslam_hgcn.compiled import descriptor_words, jit, popcount64
from orbslam_hgcn.match.hamming import hamming_matrix

log = logging.getLogger(__name__)


def distinctive_descriptor(desc: np.ndarray) -> np.ndarray:
    """The descriptor with the least median Hamming distance to the others.

    desc: (n, 32) uint8 descriptors of all observations of one point (n >= 1).
    Returns (32,) uint8 (ORB-SLAM MapPoint::ComputeDistinctiveDescriptors: the median of a
    row sorted ascending, self-distance included, taken at index (n - 1) // 2).
    """
    desc = np.asarray(desc, dtype=np.uint8)
    if len(desc) <= 2:
        return desc[0].copy()
    D = np.sort(hamming_matrix(desc, desc), axis=1)
    median = D[:, (len(desc) - 1) // 2]
    return desc[int(np.argmin(median))].copy()


def distinctive_descriptors(desc: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    """:func:`distinctive_descriptor` of many points at once.

    desc: (M, 32) uint8 descriptors of the observations of all points, point after point;
    sizes: (P,) int observations of each point (>= 1, summing to M). Returns (P, 32)
    uint8.
    """
    desc = np.ascontiguousarray(desc, dtype=np.uint8)
    sizes = np.asarray(sizes, dtype=np.int64)
    starts = np.cumsum(sizes) - sizes
    return desc[_distinctive_rows(descriptor_words(desc), starts, sizes)]


@jit
def _distinctive_rows(words, starts, sizes):
    """(P,) row of ``words`` ((M, 4) uint64 descriptors) holding each point's
    distinctive descriptor: the first row of the least median distance to the point's
    other rows (the median of the sorted row at index (n - 1) // 2), the first row for
    points with at most two observations."""
    pick = starts.copy()
    for p in range(len(sizes)):
        n, a = sizes[p], starts[p]
        if n <= 2:
            continue
        D = np.empty((n, n), dtype=np.int64)
        for i in range(n):
            D[i, i] = 0
            for j in range(i + 1, n):
                d = 0
                for w in range(words.shape[1]):
                    d += popcount64(words[a + i, w] ^ words[a + j, w])
                D[i, j] = d
                D[j, i] = d
        best, best_median = 0, np.int64(1) << 40
        for i in range(n):
            median = np.sort(D[i])[(n - 1) // 2]
            if median < best_median:
                best, best_median = i, median
        pick[p] = a + best
    return pick


@jit
def _normals_and_ranges(position, first_row, sizes, centers, level_scale, top_scale, kf_of, ref_kf):
    """Unit mean viewing direction, max and min distance of each point from its
    observations (rows first_row[p] .. + sizes[p] of the per-observation arrays: observing
    centre (T, 3), level scale and top level scale (T,), keyframe id (T,)). The distance
    range comes from the observation in the reference keyframe ``ref_kf`` (P,), else the
    first one. The arithmetic runs in numpy's order (each row's norm, the sum over rows),
    so the results are those of the array form."""
    P = len(sizes)
    normal = np.empty((P, 3))
    dmax = np.empty(P)
    dmin = np.empty(P)
    for p in range(P):
        a, n = first_row[p], sizes[p]
        x, y, z = position[p, 0], position[p, 1], position[p, 2]
        sx = sy = sz = 0.0
        ref = a
        for r in range(a, a + n):
            dx, dy, dz = x - centers[r, 0], y - centers[r, 1], z - centers[r, 2]
            nn = max(np.sqrt(dx * dx + dy * dy + dz * dz), 1e-12)
            sx += dx / nn
            sy += dy / nn
            sz += dz / nn
            if kf_of[r] == ref_kf[p]:
                ref = r
        nn = max(np.sqrt(sx * sx + sy * sy + sz * sz), 1e-12)
        normal[p, 0], normal[p, 1], normal[p, 2] = sx / nn, sy / nn, sz / nn
        dx, dy, dz = x - centers[ref, 0], y - centers[ref, 1], z - centers[ref, 2]
        dmax[p] = np.sqrt(dx * dx + dy * dy + dz * dz) * level_scale[ref]
        dmin[p] = dmax[p] / top_scale[ref]
    return normal, dmax, dmin


def warm_up() -> float:
    """Compile (first use after an install) or load from numba's cache the kernels of
    :func:`refresh_points`; returns the seconds it took."""
    t0 = time.perf_counter()
    words = np.arange(12, dtype=np.uint64).reshape(3, 4)
    _distinctive_rows(words, np.zeros(1, np.int64), np.array([3], np.int64))
    one = np.zeros(1, np.int64)
    _normals_and_ranges(np.ones((1, 3)), one, one + 1, np.zeros((1, 3)), np.ones(1), np.ones(1), one, one)
    return time.perf_counter() - t0


def normal_and_depth(
    position: np.ndarray,
    centers: np.ndarray,
    ref_center: np.ndarray,
    ref_octave: int,
    scale_factors: np.ndarray,
) -> tuple[np.ndarray, float, float]:
    """Mean viewing direction and scale-invariance distance range of one point.

    position: (3,) point in the world; centers: (n, 3) centres of the observing keyframes;
    ref_center: (3,) centre of the reference keyframe, ref_octave the pyramid level of the
    point's keypoint there; scale_factors: (L,) level scales.
    Returns ((3,) unit mean viewing direction (point minus centre), min_dist, max_dist), as
    ORB-SLAM UpdateNormalAndDepth: max = dist * scale[level], min = max / scale[L - 1]. The
    mean direction is normalised to unit length here, so cosine tests against it are exact.
    """
    dirs = position[None, :] - np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    dirs /= np.maximum(np.linalg.norm(dirs, axis=1, keepdims=True), 1e-12)
    normal = dirs.mean(axis=0)
    normal /= max(float(np.linalg.norm(normal)), 1e-12)
    dist = float(np.linalg.norm(position - ref_center))
    max_dist = dist * float(scale_factors[ref_octave])
    min_dist = max_dist / float(scale_factors[-1])
    return normal, min_dist, max_dist


def predict_scale(dist: np.ndarray, max_dist: np.ndarray, scale_factors: np.ndarray) -> np.ndarray:
    """Pyramid level at which points should be seen from distance ``dist``.

    dist, max_dist: (M,) float distances from the camera and each point's max distance;
    scale_factors: (L,) level scales of the observing frame.
    Returns (M,) int64 level in [0, L - 1] (ORB-SLAM MapPoint::PredictScale:
    ceil(log(max_dist / dist) / log(scale_factor))).
    """
    dist = np.asarray(dist, dtype=np.float64)
    max_dist = np.asarray(max_dist, dtype=np.float64)
    scale_factors = np.asarray(scale_factors, dtype=np.float64)
    n_levels = len(scale_factors)
    log_sf = np.log(scale_factors[1]) if n_levels > 1 else 1.0
    with np.errstate(divide="ignore", invalid="ignore"):
        level = np.ceil(np.log(max_dist / dist) / log_sf)
    level = np.nan_to_num(level, nan=0.0, posinf=n_levels - 1, neginf=0.0)
    return np.clip(level, 0, n_levels - 1).astype(np.int64)


def refresh_points(store: PointStore, kfs: dict, pids: np.ndarray, descriptors: bool = True) -> None:
    """Recompute normal, distance range and (with ``descriptors``) representative descriptor
    of the good points ``pids`` of ``store`` from their observations in ``kfs`` ({id:
    KeyFrame}); the vectorised form of :func:`normal_and_depth` and
    :func:`distinctive_descriptor` (the Map calls this under its lock).

    The observations of all points are flattened point after point, then gathered one
    observing keyframe at a time (centre, level scale, descriptor)."""
    s = store
    ids = np.asarray(pids, dtype=np.int64).reshape(-1)
    ids = ids[~s.bad[ids]]
    obs = [s.obs[p] for p in ids.tolist()]
    sizes = np.fromiter(map(len, obs), dtype=np.int64, count=len(obs))
    if not sizes.all():
        keep = sizes > 0
        ids, sizes = ids[keep], sizes[keep]
        obs = [o for o in obs if o]
    if len(ids) == 0:
        return
    total = int(sizes.sum())
    kf_of = np.fromiter(itertools.chain.from_iterable(obs), dtype=np.int64, count=total)
    feat_of = np.fromiter(itertools.chain.from_iterable(o.values() for o in obs), dtype=np.int64, count=total)
    first_row = np.cumsum(sizes) - sizes  # first observation of each point
    centers = np.empty((total, 3))
    level_scale = np.empty(total)
    top_scale = np.empty(total)
    desc = np.empty((total, 32), dtype=np.uint8)
    order = np.argsort(kf_of, kind="stable")
    kf_sorted = kf_of[order]
    bounds = np.flatnonzero(np.concatenate([[True], kf_sorted[1:] != kf_sorted[:-1], [True]]))
    for a, b in zip(bounds[:-1].tolist(), bounds[1:].tolist()):
        kf = kfs[int(kf_sorted[a])]
        sel, kp = order[a:b], kf.keypoints
        f = feat_of[sel]
        centers[sel] = kf.T_wc[:3, 3]
        level_scale[sel] = kp.scale_factors[kp.octave[f]]
        top_scale[sel] = kp.scale_factors[-1]
        if descriptors:
            desc[sel] = kp.desc[f]
    normal, dmax, dmin = _normals_and_ranges(
        s.position[ids], first_row, sizes, centers, level_scale, top_scale, kf_of, s.ref_kf[ids]
    )
    s.normal[ids], s.max_dist[ids], s.min_dist[ids] = normal, dmax, dmin
    if descriptors:
        s.desc[ids] = distinctive_descriptors(desc, sizes)


class PointStore:
    """Struct of arrays, one row per point id (ids are never reused).

    position (P, 3) float64, normal (P, 3) float64 unit mean viewing direction,
    min_dist/max_dist (P,) float64, desc (P, 32) uint8 representative descriptor,
    found/visible (P,) int64 counters, first_kf/ref_kf (P,) int64, bad (P,) bool,
    replaced_by (P,) int64 (-1: not replaced); owner (P,) int64 id of the map holding the
    point (several maps of an atlas share one store); obs: list of {kf_id: feature index}.
    """

    def __init__(self, capacity: int = 1024) -> None:
        self.n = 0
        self._alloc(capacity)
        self.obs: list[dict[int, int]] = []

    def _alloc(self, cap: int) -> None:
        def grow(name: str, shape: tuple, dtype, fill) -> None:
            new = np.full((cap, *shape), fill, dtype=dtype)
            old = getattr(self, name, None)
            if old is not None:
                new[: self.n] = old[: self.n]
            setattr(self, name, new)

        grow("position", (3,), np.float64, 0.0)
        grow("normal", (3,), np.float64, 0.0)
        grow("min_dist", (), np.float64, 0.0)
        grow("max_dist", (), np.float64, np.inf)
        grow("desc", (32,), np.uint8, 0)
        grow("found", (), np.int64, 1)
        grow("visible", (), np.int64, 1)
        grow("first_kf", (), np.int64, -1)
        grow("ref_kf", (), np.int64, -1)
        grow("bad", (), bool, False)
        grow("replaced_by", (), np.int64, -1)
        grow("owner", (), np.int64, 0)  # id of the map holding the point (see map.atlas)
        self.capacity = cap

    def new(self, positions: np.ndarray, first_kf: int, owner: int = 0) -> np.ndarray:
        """New points at (K, 3) ``positions``, made by keyframe ``first_kf``; returns their
        (K,) int64 ids, consecutive."""
        positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        k = len(positions)
        capacity = max(self.capacity, 1)
        while self.n + k > capacity:
            capacity *= 2
        if capacity != self.capacity:
            self._alloc(capacity)
        ids = np.arange(self.n, self.n + k, dtype=np.int64)
        self.n += k
        self.position[ids] = positions
        self.first_kf[ids] = first_kf
        self.ref_kf[ids] = first_kf
        self.owner[ids] = owner
        self.obs.extend({} for _ in range(k))
        return ids

    def valid(self, ids: np.ndarray) -> np.ndarray:
        """(M,) bool: ids that exist in the store."""
        ids = np.asarray(ids, dtype=np.int64)
        return (ids >= 0) & (ids < self.n)


def _ro(a: np.ndarray) -> np.ndarray:
    v = a.view()
    v.flags.writeable = False
    return v


class MapPoint:
    """Read-only view of one point of a :class:`PointStore` (changes go through the Map)."""

    __slots__ = ("_s", "id")

    def __init__(self, store: PointStore, pid: int) -> None:
        if not 0 <= pid < store.n:
            raise KeyError(f"no map point with id {pid}")
        self._s = store
        self.id = int(pid)

    def __repr__(self) -> str:
        return f"MapPoint(id={self.id}, obs={self.n_obs}, bad={self.bad})"

    @property
    def position(self) -> np.ndarray:
        """(3,) world position."""
        return _ro(self._s.position[self.id])

    @property
    def normal(self) -> np.ndarray:
        """(3,) unit mean viewing direction (from the cameras towards the point)."""
        return _ro(self._s.normal[self.id])

    @property
    def descriptor(self) -> np.ndarray:
        """(32,) uint8 representative descriptor."""
        return _ro(self._s.desc[self.id])

    @property
    def min_dist(self) -> float:
        """Nearest distance at which the point is scale-invariantly observable."""
        return float(self._s.min_dist[self.id])

    @property
    def max_dist(self) -> float:
        return float(self._s.max_dist[self.id])

    @property
    def observations(self) -> dict[int, int]:
        """Copy of {kf_id: feature index} in insertion order."""
        return dict(self._s.obs[self.id])

    @property
    def n_obs(self) -> int:
        return len(self._s.obs[self.id])

    @property
    def found(self) -> int:
        return int(self._s.found[self.id])

    @property
    def visible(self) -> int:
        return int(self._s.visible[self.id])

    @property
    def found_ratio(self) -> float:
        """found / visible (ORB-SLAM GetFoundRatio, used to cull points)."""
        return self.found / max(self.visible, 1)

    @property
    def first_kf(self) -> int:
        return int(self._s.first_kf[self.id])

    @property
    def ref_kf(self) -> int:
        return int(self._s.ref_kf[self.id])

    @property
    def bad(self) -> bool:
        return bool(self._s.bad[self.id])

    @property
    def replaced_by(self) -> int:
        """Id of the point that absorbed this one in a fuse, -1 if none."""
        return int(self._s.replaced_by[self.id])

    def predict_scale(self, dist: float, scale_factors: np.ndarray) -> int:
        """Pyramid level expected at distance ``dist`` (see :func:`predict_scale`)."""
        return int(predict_scale(np.array([dist]), np.array([self.max_dist]), scale_factors)[0])

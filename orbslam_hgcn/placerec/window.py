"""Which images a loop-closure experiment compares: sampling and the temporal exclusion window.

A video-rate sequence shows each view in dozens of consecutive frames. Compared frame by
frame, a query's best match is the frame just before it, which no loop ground truth calls a
loop, and the experiment measures nothing. The datasets of the FAB-MAP and HGCN papers hold
about one image per distinct view (City Centre and New College: an image every 1.5 m), and
a loop-closure detector compares a query only with images outside its recent past (ORB-SLAM
leaves out the keyframes covisible with the query). Both are chosen here from the data:

* **Sampling** (:func:`sample_indices`): with a ground-truth pose for every frame, an image
  is kept when the camera has moved ``SAMPLE_DIST_M`` or turned ``SAMPLE_ANGLE_DEG`` since
  the last kept one (half the 0.5 m / 30 deg that make two synthetic frames the same
  place, so that consecutive images overlap but differ); otherwise one image per
  ``SAMPLE_EVERY_S`` seconds; a folder of images without timestamps is used whole.
  ``stride`` and ``every_s`` override.
* **The exclusion window** (:func:`window_from_ground_truth`, :func:`window_from_timestamps`):
  a query ``i`` is compared with images ``j <= i - gap``. With a loop ground truth, ``gap``
  is its own smallest loop separation: the closest pair of revisits, where a revisit is a
  true pair not joined to the diagonal through other true pairs (pairs joined to it are one
  continuous visit: the frames around the query that show the same place). Without one,
  it spans ``WINDOW_S`` seconds of the timestamps.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import scipy.ndimage

from orbslam_hgcn.errors import OrbslamError

log = logging.getLogger(__name__)

SAMPLE_DIST_M = 0.25  # camera motion that makes a new image (half the synthetic loop ground truth's 0.5 m)
SAMPLE_ANGLE_DEG = 15.0  # ... or rotation of the optical axis (half its 30 deg)
SAMPLE_EVERY_S = 0.5  # without poses: one image per this many seconds (hand-held speeds: about 0.2 m)
# Without a loop ground truth: leave out the images of the last WINDOW_S seconds (views stay
# covisible for several seconds at hand-held and walking speeds).
WINDOW_S = 10.0
NEAR_IMAGES = 3  # best matches this close to the query are "the recent past", not loops
NEAR_SHARE = 0.5  # warn when more than this share of the queries match the recent past


@dataclass(frozen=True)
class Sampling:
    """The images of a sequence an experiment uses.

    indices: (n,) int64 frame indices into the whole sequence, increasing; how: in words.
    """

    indices: np.ndarray
    how: str


def _axis_angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(np.dot(a, b), -1.0, 1.0))))


def sample_by_motion(poses_wc: np.ndarray, dist: float = SAMPLE_DIST_M, angle_deg: float = SAMPLE_ANGLE_DEG) -> np.ndarray:
    """(n,) int64 frames kept from (N, 4, 4) ``T_wc`` poses: the first, then each frame whose
    camera centre lies ``dist`` from the last kept one or whose optical axis turned ``angle_deg``."""
    keep = [0]
    c, z = poses_wc[:, :3, 3], poses_wc[:, :3, 2]
    for k in range(1, len(poses_wc)):
        last = keep[-1]
        if np.linalg.norm(c[k] - c[last]) >= dist or _axis_angle_deg(z[k], z[last]) >= angle_deg:
            keep.append(k)
    return np.asarray(keep, dtype=np.int64)


def sample_by_time(timestamps: np.ndarray, every_s: float) -> np.ndarray:
    """(n,) int64 frames kept: the first, then each one ``every_s`` seconds after the last kept."""
    keep = [0]
    for k in range(1, len(timestamps)):
        if timestamps[k] - timestamps[keep[-1]] >= every_s - 1e-9:
            keep.append(k)
    return np.asarray(keep, dtype=np.int64)


def sample_indices(
    n_frames: int,
    timestamps: np.ndarray | None,
    poses_wc: np.ndarray | None,
    *,
    stride: int | None = None,
    every_s: float | None = None,
) -> Sampling:
    """The frames of a sequence to use (see the module docstring for the default).

    timestamps: (N,) seconds or None; poses_wc: (N, 4, 4) ground-truth ``T_wc`` with NaN
    where a frame has none, or None. stride / every_s: overrides (at most one).
    """
    if stride is not None and every_s is not None:
        raise OrbslamError("--stride and --every-s both choose the images; give one")
    if stride is not None:
        if stride < 1:
            raise OrbslamError(f"stride must be at least 1, found {stride}")
        return Sampling(np.arange(0, n_frames, stride, dtype=np.int64), f"every {stride}th image (--stride)"
                        if stride > 1 else "every image (--stride 1)")
    if every_s is not None:
        if not every_s > 0:
            raise OrbslamError(f"--every-s must be positive, found {every_s}")
        if timestamps is None:
            raise OrbslamError("--every-s needs timestamps, and an image folder has none; use --stride")
        return Sampling(sample_by_time(timestamps, every_s), f"one image per {every_s:g} s (--every-s)")
    if poses_wc is not None and len(poses_wc) == n_frames and np.all(np.isfinite(poses_wc[:, 0, 0])):
        return Sampling(sample_by_motion(poses_wc),
                        f"one image per {SAMPLE_DIST_M:g} m or {SAMPLE_ANGLE_DEG:g} deg of ground-truth camera motion")
    if timestamps is not None:
        return Sampling(sample_by_time(timestamps, SAMPLE_EVERY_S), f"one image per {SAMPLE_EVERY_S:g} s")
    return Sampling(np.arange(n_frames, dtype=np.int64), "every image (an image folder has no timestamps)")


@dataclass(frozen=True)
class Window:
    """A temporal exclusion: query ``i`` is compared with images ``j <= i - gap``.

    gap: in images of the sequence as used (after sampling), at least 1; seconds: the
    shortest time it spans (None without timestamps); source: how it was chosen, in words.
    """

    gap: int
    seconds: float | None
    source: str

    def describe(self) -> str:
        span = f", at least {self.seconds:.1f} s back" if self.seconds is not None else ""
        return f"{self.gap} images{span} ({self.source})"


def revisit_pairs(gt: np.ndarray) -> np.ndarray:
    """(n, n) bool: the true pairs ``(i, j)``, ``j < i``, of a loop matrix that are revisits.

    A true pair joined to the first off-diagonal (``j = i - 1``) through true pairs (8-neighbour
    connectivity in the matrix) belongs to one continuous visit of a place; every other true
    pair is a revisit. A ground truth marking loop closures only has no such band: all its
    pairs are revisits.
    """
    lower = np.tril(np.asarray(gt, dtype=bool) | np.asarray(gt, dtype=bool).T, -1)
    labels, _ = scipy.ndimage.label(lower, structure=np.ones((3, 3), dtype=bool))
    band = np.unique(np.diagonal(labels, -1))
    return lower & ~np.isin(labels, band[band > 0])


def _span_seconds(gap: int, timestamps: np.ndarray | None) -> float | None:
    """The shortest time between two images ``gap`` apart."""
    if timestamps is None or len(timestamps) <= gap:
        return None
    return float(np.min(timestamps[gap:] - timestamps[:-gap]))


def window_from_ground_truth(revisits: np.ndarray, timestamps: np.ndarray | None = None) -> Window | None:
    """The smallest loop separation of the revisit pairs (:func:`revisit_pairs` over the images
    used), or None when there is no revisit."""
    i, j = np.nonzero(revisits)
    if len(i) == 0:
        return None
    gap = int(np.min(i - j))
    return Window(gap, _span_seconds(gap, timestamps), "the ground truth's smallest loop separation")


def window_from_timestamps(timestamps: np.ndarray | None, seconds: float = WINDOW_S, source: str | None = None) -> Window:
    """The smallest gap in images such that every query's candidates lie at least ``seconds``
    back (timestamps (n,) of the images used)."""
    if timestamps is None:
        raise OrbslamError("cannot choose the exclusion window: no loop in the ground truth and no timestamps "
                           "(an image folder); pass --min-gap N")
    if not seconds > 0:
        raise OrbslamError(f"--window-s must be positive, found {seconds}")
    t = np.asarray(timestamps, dtype=np.float64)
    # for each query, the first image that is recent enough to be left out
    first_recent = np.searchsorted(t, t - seconds + 1e-9, side="right")  # 1e-9: timestamps as decimals
    gap = int(max(1, np.max(np.arange(len(t)) - first_recent + 1))) if len(t) else 1
    src = source or f"{seconds:g} s of the timestamps"
    return Window(gap, _span_seconds(gap, t), src)


def fixed_window(gap: int, timestamps: np.ndarray | None = None) -> Window:
    """A window given in images (``--min-gap``)."""
    if gap < 1:
        raise OrbslamError(f"--min-gap must be at least 1, found {gap}")
    return Window(gap, _span_seconds(gap, timestamps), "--min-gap")


def choose_window(
    revisits: np.ndarray | None,
    timestamps: np.ndarray | None,
    *,
    min_gap: int | None = None,
    window_s: float | None = None,
) -> Window:
    """The window of one sequence: ``min_gap`` (images) or ``window_s`` (seconds) when given,
    else the ground truth's smallest loop separation, else ``WINDOW_S`` of the timestamps."""
    if min_gap is not None and window_s is not None:
        raise OrbslamError("--min-gap and --window-s both set the exclusion window; give one")
    if min_gap is not None:
        return fixed_window(min_gap, timestamps)
    if window_s is not None:
        return window_from_timestamps(timestamps, window_s, f"--window-s {window_s:g}")
    found = window_from_ground_truth(revisits, timestamps) if revisits is not None else None
    if found is not None:
        return found
    return window_from_timestamps(timestamps, WINDOW_S, f"{WINDOW_S:g} s of the timestamps: the ground truth has no loop")


def hidden_revisits(revisits: np.ndarray, gap: int) -> tuple[int, int]:
    """(images whose every revisit lies inside the window, revisit pairs inside it)."""
    n = len(revisits)
    inside = revisits & ~np.tri(n, n, -gap, dtype=bool)
    outside = revisits & np.tri(n, n, -gap, dtype=bool)
    lost = inside.any(axis=1) & ~outside.any(axis=1)
    return int(lost.sum()), int(inside.sum())


def recent_past_share(best: np.ndarray, near: int = NEAR_IMAGES) -> float:
    """Share of the queries with a candidate whose best match lies within ``near`` images
    of the query (``i - best <= near``). best: (n,) int64, -1 for none."""
    i = np.arange(len(best))
    has = best >= 0
    if not has.any():
        return 0.0
    return float(np.mean((i[has] - best[has]) <= near))

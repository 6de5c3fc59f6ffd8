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
  A slow hand-held camera makes few distinct views, and few of them revisits: a figure
  from six revisiting images measures nothing. So when the loop ground truth covers every
  frame and has revisits, and that spacing leaves fewer than ``MIN_REVISITS`` images with a
  revisit outside the exclusion window or fewer than ``MIN_IMAGES`` images, the spacing
  shrinks by ``DENSIFY_STEP`` at a time (motion thresholds or seconds alike), at last to
  every frame, until both are met; the sparsest spacing that meets them is used, else the
  one with the most revisiting images, with a warning (:func:`sample_for_loops`).
  ``stride`` and ``every_s`` override.
* **The exclusion window** (:func:`window_from_ground_truth`, :func:`window_from_timestamps`):
  a query ``i`` is compared with images ``j <= i - gap``. With a loop ground truth, ``gap``
  is its own smallest loop separation: the closest pair of revisits, where a revisit is a
  true pair not joined to the diagonal through other true pairs (pairs joined to it are one
  continuous visit: the frames around the query that show the same place). Without one,
  it spans ``WINDOW_S`` seconds of the timestamps. Either is found on the images as used,
  after sampling, so a denser spacing gets a window of more images; the revisits are found
  on the ground truth of every frame before it is cut down to the images used, so the
  frames of one continuous visit never count as loops, whatever the spacing.
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
# With a loop ground truth over every frame that has revisits, the default spacing is made
# denser until at least MIN_REVISITS images revisit an earlier one (outside the window) and
# at least MIN_IMAGES are used, where the sequence allows: AUC and recall at 100% precision
# from a handful of revisits are noise.
MIN_REVISITS = 20
MIN_IMAGES = 80
DENSIFY_STEP = 2.0 ** -0.25  # each step shrinks the spacing to 84%
DENSIFY_STEPS = 24  # at most (to 1/64 of the spacing), then every frame
NEAR_IMAGES = 3  # best matches this close to the query are "the recent past", not loops
NEAR_SHARE = 0.5  # warn when more than this share of the queries match the recent past


@dataclass(frozen=True)
class Sampling:
    """The images of a sequence an experiment uses.

    indices: (n,) int64 frame indices into the whole sequence, increasing; how: in words.
    revisiting: how many of them revisit an earlier one outside the exclusion window (None
    when it was not counted: no ground truth over every frame); warning: a line saying why
    that is too few to measure with, or None.
    """

    indices: np.ndarray
    how: str
    revisiting: int | None = None
    warning: str | None = None
    min_gap: int | None = None  # a --min-gap rescaled to a denser spacing (see sample_for_loops)


def sample_by_motion(poses_wc: np.ndarray, dist: float = SAMPLE_DIST_M, angle_deg: float = SAMPLE_ANGLE_DEG) -> np.ndarray:
    """(n,) int64 frames kept from (N, 4, 4) ``T_wc`` poses: the first, then each frame whose
    camera centre lies ``dist`` from the last kept one or whose optical axis turned ``angle_deg``."""
    keep = [0]
    c, z = poses_wc[:, :3, 3].tolist(), poses_wc[:, :3, 2].tolist()
    d2, cos_max = dist * dist, float(np.cos(np.radians(angle_deg)))
    cl, zl = c[0], z[0]
    for k in range(1, len(c)):
        ck, zk = c[k], z[k]
        moved = (ck[0] - cl[0]) ** 2 + (ck[1] - cl[1]) ** 2 + (ck[2] - cl[2]) ** 2 >= d2
        if moved or zk[0] * zl[0] + zk[1] * zl[1] + zk[2] * zl[2] <= cos_max:
            keep.append(k)
            cl, zl = ck, zk
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
    if _has_poses(poses_wc, n_frames):
        return Sampling(sample_by_motion(poses_wc), _motion_how(1.0))
    if timestamps is not None:
        return Sampling(sample_by_time(timestamps, SAMPLE_EVERY_S), _time_how(1.0))
    return Sampling(np.arange(n_frames, dtype=np.int64), "every image (an image folder has no timestamps)")


def _has_poses(poses_wc: np.ndarray | None, n_frames: int) -> bool:
    return poses_wc is not None and len(poses_wc) == n_frames and bool(np.all(np.isfinite(poses_wc[:, 0, 0])))


def _motion_how(scale: float) -> str:
    return f"one image per {SAMPLE_DIST_M * scale:.3g} m or {SAMPLE_ANGLE_DEG * scale:.3g} deg of ground-truth camera motion"


def _time_how(scale: float) -> str:
    return f"one image per {SAMPLE_EVERY_S * scale:.3g} s"


def revisiting_images(revisits: np.ndarray, gap: int) -> int:
    """How many images of (n, n) ``revisits`` (over the images used) revisit an earlier one
    outside the window: a revisit pair ``(i, j)`` with ``j <= i - gap``."""
    n = len(revisits)
    return int(np.count_nonzero((np.asarray(revisits, dtype=bool) & np.tri(n, n, -max(1, gap), dtype=bool)).any(axis=1)))


def count_revisiting(
    revisits_all: np.ndarray, indices: np.ndarray, timestamps: np.ndarray | None, *,
    min_gap: int | None = None, window_s: float | None = None,
) -> int:
    """How many of the frames ``indices`` revisit an earlier one of them outside the window
    :func:`choose_window` gives these images. revisits_all: (N, N) :func:`revisit_pairs`
    of the ground truth over every frame; timestamps: (N,) or None."""
    sub = revisits_all[np.ix_(indices, indices)]
    if not sub.any():
        return 0
    t = timestamps[indices] if timestamps is not None else None
    return revisiting_images(sub, choose_window(sub, t, min_gap=min_gap, window_s=window_s).gap)


def sample_for_loops(
    n_frames: int,
    timestamps: np.ndarray | None,
    poses_wc: np.ndarray | None,
    revisits_all: np.ndarray | None,
    *,
    stride: int | None = None,
    every_s: float | None = None,
    limit: int | None = None,
    min_gap: int | None = None,
    window_s: float | None = None,
    name: str = "test",
    min_revisits: int = MIN_REVISITS,
    min_images: int = MIN_IMAGES,
) -> Sampling:
    """The frames a loop-closure experiment uses (see the module docstring).

    The spacing of :func:`sample_indices` (``stride`` / ``every_s`` when given); when they
    are not given and ``revisits_all`` ((N, N) :func:`revisit_pairs` of a ground truth over
    every frame, or None) has a revisit, the spacing is shrunk step by step (motion
    thresholds, else seconds, at last every frame) until at least ``min_revisits`` of the
    first ``limit`` images kept revisit an earlier one outside their window
    (:func:`choose_window` with ``min_gap`` / ``window_s``, found anew for each spacing) and
    at least ``min_images`` are kept. The first spacing that meets both is used, else the one
    with the most revisiting images (the sparsest of equals). ``Sampling.warning`` says so
    when fewer than ``min_revisits`` images revisit. A ``min_gap`` counts images of the
    default spacing; a denser one gets it rescaled by the ratio of the image counts
    (:func:`rescale_gap`, in ``Sampling.min_gap``), so that it leaves out as much of the
    recent past at any spacing.
    """
    base = sample_indices(n_frames, timestamps, poses_wc, stride=stride, every_s=every_s)
    if revisits_all is None or len(revisits_all) != n_frames or not revisits_all.any():
        return base

    base_n = len(base.indices[:limit])

    def gap_for(idx: np.ndarray) -> int | None:
        return rescale_gap(min_gap, base_n, len(idx[:limit])) if min_gap is not None else None

    def count(idx: np.ndarray) -> int:
        return count_revisiting(revisits_all, idx[:limit], timestamps, min_gap=gap_for(idx), window_s=window_s)

    def met(s: Sampling) -> bool:
        return s.revisiting >= min_revisits and len(s.indices[:limit]) >= min_images

    base = Sampling(base.indices, base.how, count(base.indices))
    if stride is not None or every_s is not None or met(base):
        return with_revisit_warning(base, name, min_revisits, "as given")
    by_motion = _has_poses(poses_wc, n_frames)
    if not by_motion and timestamps is None:  # an image folder: every image already
        return with_revisit_warning(base, name, min_revisits, "")
    tried = [base]
    for k in range(1, DENSIFY_STEPS + 2):
        if len(tried[-1].indices) == n_frames:
            break
        scale = DENSIFY_STEP ** k
        if k > DENSIFY_STEPS:
            idx, how = np.arange(n_frames, dtype=np.int64), "every image"
        elif by_motion:
            idx, how = sample_by_motion(poses_wc, SAMPLE_DIST_M * scale, SAMPLE_ANGLE_DEG * scale), _motion_how(scale)
        else:
            idx, how = sample_by_time(timestamps, SAMPLE_EVERY_S * scale), _time_how(scale)
        if len(idx) == len(tried[-1].indices):
            continue
        s = Sampling(idx, how, count(idx))
        tried.append(s)
        if met(s):
            break
    chosen = next((s for s in tried if met(s)), None)
    if chosen is None:
        chosen = max(tried, key=lambda s: s.revisiting)  # the first of equals: the sparsest
    if chosen is not base:
        why = []
        if base.revisiting < min_revisits:
            why.append(f"{base.revisiting} revisiting images")
        if len(base.indices[:limit]) < min_images:
            why.append(f"{len(base.indices[:limit])} images")
        first = f"{SAMPLE_DIST_M:g} m / {SAMPLE_ANGLE_DEG:g} deg" if by_motion else f"{SAMPLE_EVERY_S:g} s"
        chosen = Sampling(chosen.indices, f"{chosen.how}; denser than {first}, which kept only {' and '.join(why)}",
                          chosen.revisiting, min_gap=gap_for(chosen.indices))
    return with_revisit_warning(chosen, name, min_revisits, "which keeps every frame" if len(chosen.indices) == n_frames
                         else "the spacing with the most of them, down to every frame")


def rescale_gap(gap: int, n_from: int, n_to: int) -> int:
    """A gap of ``gap`` images out of ``n_from`` as images out of ``n_to`` (same share, rounded up)."""
    return max(1, int(np.ceil(gap * n_to / max(1, n_from) - 1e-9)))


def with_revisit_warning(s: Sampling, name: str, min_revisits: int, why: str) -> Sampling:
    """``s`` with a warning when fewer than ``min_revisits`` of its images revisit; ``why``
    says what the spacing is (or ""), after the spacing's name."""
    if s.revisiting is None or s.revisiting >= min_revisits:
        return s
    warning = (f"{name}: only {s.revisiting} images revisit an earlier one outside the exclusion window with "
               f"{s.how.split(';')[0]}{', ' + why if why else ''}: fewer than the {min_revisits} that measure "
               f"loop closure, so recall at 100% precision and AUC rest on {s.revisiting} queries; read their "
               f"95% confidence intervals")
    return Sampling(s.indices, s.how, s.revisiting, warning, s.min_gap)


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


def fixed_window(gap: int, timestamps: np.ndarray | None = None, given: int | None = None) -> Window:
    """A window given in images (``--min-gap``); ``given``: the gap as given, when ``gap`` is
    it rescaled to a denser spacing."""
    if gap < 1 or (given is not None and given < 1):
        raise OrbslamError(f"--min-gap must be at least 1, found {given if given is not None else gap}")
    src = "--min-gap" if given is None or given == gap else f"--min-gap {given}, rescaled to the denser sampling"
    return Window(gap, _span_seconds(gap, timestamps), src)


def choose_window(
    revisits: np.ndarray | None,
    timestamps: np.ndarray | None,
    *,
    min_gap: int | None = None,
    window_s: float | None = None,
    given_gap: int | None = None,
) -> Window:
    """The window of one sequence: ``min_gap`` (images) or ``window_s`` (seconds) when given,
    else the ground truth's smallest loop separation, else ``WINDOW_S`` of the timestamps.
    given_gap: the ``--min-gap`` as given when ``min_gap`` is it rescaled."""
    if min_gap is not None and window_s is not None:
        raise OrbslamError("--min-gap and --window-s both set the exclusion window; give one")
    if min_gap is not None:
        return fixed_window(min_gap, timestamps, given_gap)
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

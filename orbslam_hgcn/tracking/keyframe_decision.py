"""When the tracker makes the current frame a keyframe (ORB-SLAM2 Tracking::NeedNewKeyFrame).

Monocular rules (Mur-Artal, Montiel & Tardos, T-RO 2015, Sec. V-E, with ORB-SLAM2's
values): no keyframe within ``max_frames`` of a relocalisation once the map holds more
than ``max_frames`` keyframes; otherwise a keyframe is made when

* c1a: ``max_frames`` frames passed since the last keyframe, or
* c1b: ``min_frames`` frames and ``min_keyframe_interval_s`` seconds of camera time passed
  and local mapping is idle,

* c1c: the frame tracks fewer than ``keyframe_urgent_inliers`` points and local mapping
  is idle (the local map is running out: the camera-time interval is waived),

and c2: the frame tracks fewer than ``ref_ratio`` (0.9) of the points of the reference
keyframe that are seen by at least 3 keyframes (2 while the map has at most 2), but more
than ``keyframe_min_inliers`` (15) points. ``max_frames`` defaults to the camera fps.

The camera-time interval is not in ORB-SLAM, whose c1b makes a keyframe whenever local
mapping is idle: its keyframe rate is set by how long local mapping takes on the machine
(0.38 s per keyframe in the T-RO paper's Table I). Without it, a run whose local mapping
is always idle (sequential mode, or a fast machine) made a keyframe on nearly every frame
of forward driving (141 for 160 KITTI frames, against 19-41 for ORB-SLAM3 on the same
frames), and threaded runs mapped differently on machines of different speed. With it,
the keyframes do not depend on the machine as long as local mapping keeps up. The KITTI
camera settings set it to 0.15 s (every other frame at 10 Hz): ORB-SLAM3 at the camera's
rate on a 2-core machine keeps 80-92 keyframes of KITTI 00's first 160 frames, and 52
keyframes at 0.3 s left the map's accuracy behind it.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

from orbslam_hgcn.config import TrackingConfig

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class KeyFrameQuery:
    """What the decision looks at.

    frame_id: current frame; last_kf_frame_id: frame id of the last keyframe;
    last_reloc_frame_id: frame of the last relocalisation (-1: none); n_keyframes: in the
    map (only compared with small numbers: the tracker counts up to a bound above them);
    n_inliers: the frame's inliers after local-map tracking; ref_tracked: points of the
    reference keyframe seen by enough keyframes; mapping_idle: local mapping accepts
    keyframes; fps: camera frame rate; timestamp, last_kf_timestamp: camera times of the
    frame and of the last keyframe.
    """

    frame_id: int
    last_kf_frame_id: int
    last_reloc_frame_id: int
    n_keyframes: int
    n_inliers: int
    ref_tracked: int
    mapping_idle: bool
    fps: float
    timestamp: float = float("nan")  # of the frame, seconds
    last_kf_timestamp: float = float("nan")  # of the last keyframe (nan: none)


def min_observations(n_keyframes: int) -> int:
    """Observations a reference point needs to count in c2 (ORB-SLAM2: 3, or 2 with <= 2 keyframes)."""
    return 2 if n_keyframes <= 2 else 3


def max_frames(config: TrackingConfig, fps: float) -> int:
    return config.max_frames if config.max_frames > 0 else max(1, int(round(fps)))


def _conditions(q: KeyFrameQuery, config: TrackingConfig) -> tuple[bool, bool, bool, bool, bool]:
    """(c1a, c1b, c1c, c2, c1b's frame count and interval without its idle mapping); all
    False within the frames after a relocalisation."""
    n_max = max_frames(config, q.fps)
    if q.last_reloc_frame_id >= 0 and q.frame_id < q.last_reloc_frame_id + n_max and q.n_keyframes > n_max:
        return False, False, False, False, False
    c1a = q.frame_id >= q.last_kf_frame_id + n_max
    c1c = q.n_inliers < config.keyframe_urgent_inliers  # the local map is running out
    young = q.n_keyframes < config.min_keyframe_interval_from  # the interval applies from then on
    waited = young or not (q.timestamp - q.last_kf_timestamp < config.min_keyframe_interval_s)  # nan: no keyframe
    timed = q.frame_id >= q.last_kf_frame_id + config.min_frames and waited
    c2 = q.n_inliers < q.ref_tracked * config.ref_ratio and q.n_inliers > config.keyframe_min_inliers
    return c1a, timed and q.mapping_idle, c1c, c2, timed


def need_new_keyframe(q: KeyFrameQuery, config: TrackingConfig) -> bool:
    """True when the monocular keyframe rules ask for a keyframe."""
    c1a, c1b, c1c, c2, _ = _conditions(q, config)
    # ORB-SLAM2 interrupts a running local BA and waits when mapping is busy; the caller
    # decides again on the next frame.
    return bool((c1a or c1b or c1c) and c2 and q.mapping_idle)


def keyframe_starved(q: KeyFrameQuery, config: TrackingConfig, on_interval: bool = False) -> bool:
    """True when the rules ask for a keyframe by c1a (``max_frames`` frames, a second of
    camera time, since the last one) or c1c (the frame tracks fewer than
    ``keyframe_urgent_inliers`` points) and c2, and only a busy local mapping stops it.
    With ``on_interval`` also by c1b's frame count and camera-time interval: every
    keyframe that an idle mapping would have taken is due."""
    c1a, _, c1c, c2, timed = _conditions(q, config)
    return bool((c1a or c1c or (on_interval and timed)) and c2 and not q.mapping_idle)

"""Dataset readers: TUM RGB-D, EuRoC, KITTI odometry, image folders and video files.

Each reader is a :class:`Sequence` of :class:`FrameRecord` (index, timestamp in seconds,
image, ground-truth ``T_wc`` or None); :func:`open_sequence` opens one by kind or detects it.
"""

from .base import FrameRecord, Sequence
from .factory import KINDS, detect_kind, open_sequence

__all__ = ["KINDS", "FrameRecord", "Sequence", "detect_kind", "open_sequence"]

"""The map model: frames, keyframes, map points, covisibility graph and spanning tree;
the keyframe database over their BoW vectors is :mod:`.database` (imported on its own)."""

from orbslam_hgcn.map.frame import Frame
from orbslam_hgcn.map.graph import MapSnapshot, check_invariants, essential_graph, snapshot
from orbslam_hgcn.map.keyframe import KeyFrame
from orbslam_hgcn.map.map import Map, PointArrays
from orbslam_hgcn.map.mappoint import MapPoint, predict_scale

__all__ = [
    "Frame",
    "KeyFrame",
    "Map",
    "MapPoint",
    "MapSnapshot",
    "PointArrays",
    "check_invariants",
    "essential_graph",
    "predict_scale",
    "snapshot",
]

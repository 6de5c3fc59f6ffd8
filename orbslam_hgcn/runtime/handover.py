"""The mapping hand-over policy of :class:`~orbslam_hgcn.runtime.system.System`: how the
tracker hands its keyframes to local mapping and how long it waits for mapping after a
frame (``threads.mapping_sync``, ``threads.sync_mapping_s``, ``threads.keyframe_wait_s``).

:class:`HandoverPolicy` holds these methods of System, which inherits them: whether local
mapping takes a keyframe now (``_mapping_idle``, the tracker's ``mapping_idle``), the
hand-over of a keyframe (``_on_keyframe``), and the waits after a frame's pose is out:
``_pipeline_mapping`` (mapping_sync "points"), ``_map_due_keyframe`` ("due") and
``_map_starved_frame`` (a keyframe was due but mapping was busy), the last two making the
due keyframe after the wait (``_keyframe_after_wait``).
"""

from __future__ import annotations

import time

from orbslam_hgcn.map import KeyFrame
from orbslam_hgcn.runtime.locks import first
from orbslam_hgcn.runtime.stages import SequentialStages, ThreadedStages
from orbslam_hgcn.tracking.tracker import TrackResult


class HandoverPolicy:
    """How :class:`~orbslam_hgcn.runtime.system.System` hands keyframes to local mapping and
    waits for it (a mixin of System: it uses the system's ``configs``, ``tracker``, ``map``,
    ``stages``, ``timings``, ``_resume_by`` and ``_hold_points``, set by System.run and
    System.process)."""

    def _mapping_idle(self) -> bool:
        # With mapping_sync "due" a keyframe waits for mapping to finish the previous one,
        # local BA included: cut short by every keyframe that found it running, BA was
        # aborted on 64 of 66 keyframes of a loaded KITTI run (keyframe ATE 138 cm, 39 cm
        # with the BAs finished).
        if self.tracker.starved_on_interval:
            return self.stages.mapping_done()
        # With mapping_sync "points" a mapping held after a keyframe's new points
        # takes the next keyframe once released, as an idle one (the keyframes made do not
        # depend on how far it got).
        if self._hold_points and self.stages.holding:
            return True
        return self.stages.mapping_idle()

    def _map_due_keyframe(self, result: TrackResult, stages: SequentialStages | ThreadedStages) -> None:
        """threads.mapping_sync "due": a keyframe is due on this frame and local mapping is
        still busy with the previous one: wait for mapping to take one (within
        threads.sync_mapping_s, and with drop_late until the next frame's resume time)
        and make it from this frame. Timed as mapping_sync."""
        t0 = time.perf_counter()
        limit = min(self.configs.threads.sync_mapping_s, self._resume_by - t0)
        if limit > 0 and stages.wait_for_mapping(limit, done=True):
            # The frame was tracked without the points mapping made meanwhile; the keyframe
            # made from it observes them as one made after the mapping would.
            self._keyframe_after_wait(result, retrack=True)
        self.timings["mapping_sync"].append(1000.0 * (time.perf_counter() - t0))

    def _pipeline_mapping(self, result: TrackResult, stages: ThreadedStages, submitted: int) -> None:
        """threads.mapping_sync "points", after the frame's pose is out: local mapping holds
        after the new points (triangulated and fused) of the keyframes handed over before
        this frame (the first ``submitted``); release them (local BA and culling now run).
        If this frame made a keyframe, wait until its new points are made and fused
        (mapping finishes the released keyframes first), so that the next frame is tracked
        against them; else wait until mapping has finished the released keyframes, so that
        the next frame sees their local BA. Each wait is bounded by threads.sync_mapping_s (and
        with drop_late by the next frame's resume time) and timed as mapping_sync. Mapping
        thus works while the frames arrive, and when it keeps up, every frame is tracked
        against the same map whatever the machine's load."""
        released = stages.release_points(submitted)
        if not (result.new_keyframes or released):
            return
        t0 = time.perf_counter()
        limit = min(self.configs.threads.sync_mapping_s, self._resume_by - t0)
        if limit > 0:
            if result.new_keyframes:
                stages.wait_for_points(limit)
            else:
                stages.wait_for_mapping(limit, done=True)
        self.timings["mapping_sync"].append(1000.0 * (time.perf_counter() - t0))

    def _keyframe_after_wait(self, result: TrackResult, retrack: bool = False) -> KeyFrame | None:
        """Make the keyframe that was due on ``result``'s frame now that mapping takes it
        (``retrack``: after searching the local map again), and hand it over; None when
        the rules no longer ask for it."""
        with self.stages.handover():
            with first(self.tracker.map.lock):
                kf = self.tracker.keyframe_now(result.frame, result.n_inliers, retrack)
            if kf is not None:
                result.new_keyframes.append(kf)
                self._on_keyframe(kf)
        return kf

    def _map_starved_frame(self, result: TrackResult, stages: SequentialStages | ThreadedStages) -> None:
        """A keyframe was due on this frame but local mapping was busy (result.keyframe_starved):
        wait for mapping to take one, make it from this frame, and wait for mapping to
        triangulate its points, all within threads.keyframe_wait_s, so that the next frame
        finds a local map. The frames that arrive meanwhile wait (with threads.drop_late,
        a paced run drops those beyond its frame queue)."""
        t0 = time.perf_counter()
        deadline = t0 + self.configs.threads.keyframe_wait_s
        if stages.wait_for_mapping(self.configs.threads.keyframe_wait_s):
            if self._keyframe_after_wait(result) is not None:
                stages.wait_for_mapping(max(0.0, deadline - time.perf_counter()))
        self.timings["keyframe_wait"].append(1000.0 * (time.perf_counter() - t0))

    def _on_keyframe(self, kf: KeyFrame) -> None:
        if not self.configs.system.local_mapping:
            self.map.update_points(kf.observed_points()[1])
            self.map.update_connections(kf.id)
            return
        self.stages.submit(kf)

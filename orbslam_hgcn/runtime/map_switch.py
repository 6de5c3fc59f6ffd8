"""Map switching of :class:`~orbslam_hgcn.runtime.system.System`: the stages follow the
tracker to another map of the atlas (after a reset, a new map, or relocalisation into
another map: :meth:`MapSwitching.use_map`), and a loaded map and its atlas replace the
system's own before the first frame (:meth:`MapSwitching.install_map`, used by
``--load-map`` and ``Slam(load_map=...)``).
:class:`MapSwitching` holds these methods of System, which inherits them.
"""

from __future__ import annotations

import logging

from orbslam_hgcn.config import camera_to_dict
from orbslam_hgcn.errors import VocabularyError
from orbslam_hgcn.map import Map
from orbslam_hgcn.map.atlas import Atlas
from orbslam_hgcn.runtime.locks import TrackingFirstLock
from orbslam_hgcn.map.io import MapFileError
from orbslam_hgcn.tracking.tracker import TrackingState, TrackResult

log = logging.getLogger(__name__)


class MapSwitching:
    """How :class:`~orbslam_hgcn.runtime.system.System` moves its stages to another map (a
    mixin of System: it uses the system's atlas, tracker, stage runner, mapper, loop closer,
    relocaliser, keyframe database and events)."""

    def use_map(self, m: Map) -> None:
        """Make ``m`` (already the tracker's map) the map of every stage: the stages first
        finish the keyframes of the previous map, then the local mapper, loop closer and
        relocaliser are reset onto ``m``."""
        if self._stages is not None:
            self._stages.sync()
        if not self.sequential:
            self._share_map()
        self.map = m
        self.mapper.reset(m)
        if self.loop_closer is not None and hasattr(self.loop_closer, "reset"):
            self.loop_closer.reset(m, keep_database=True)
        if self.relocalizer is not None and hasattr(self.relocalizer, "reset"):
            self.relocalizer.reset(m)

    def install_atlas(self, atlas: Atlas, m: Map) -> None:
        """Use ``atlas`` (a loaded one) instead of the system's own, ``m`` its active map;
        before the first frame (then :meth:`use_map`)."""
        if self.sequential is False and isinstance(self.atlas.lock, TrackingFirstLock):
            atlas.lock = TrackingFirstLock()
        atlas.set_active(m)
        atlas.merge_hooks = [self.tracker.rescale_records]
        self.atlas = atlas
        self.tracker.atlas = atlas

    def install_map(self, m: Map, localization: bool = True) -> None:
        """Make ``m`` (and its atlas, when it has one: a map read from a file) the map of the
        system, before its first frame.

        Replaces the system's atlas and the tracker's map (a new tracker generation, state
        LOST so the next frame is relocalised, against any map of the atlas), hands it to the
        other stages (:meth:`use_map`), and rebuilds the keyframe database from every
        keyframe's BoW vector. ``localization``: the tracker then never makes keyframes,
        starts a map nor resets one.
        """
        if self.database is None or self.relocalizer is None:
            raise VocabularyError("tracking against a saved map needs a vocabulary (relocalisation)")
        atlas = m.atlas
        every = [kf for mm in atlas.maps.values() for kf in mm.keyframes()] if atlas is not None else m.keyframes()
        missing = [kf.id for kf in every if kf.bow is None]
        if missing:
            raise MapFileError(f"keyframes {missing[:5]} of the loaded map have no BoW vector; cannot relocalise")
        kf_camera = m.keyframes()[0].camera
        if (kf_camera.width, kf_camera.height) != (self.camera.width, self.camera.height):
            raise MapFileError(f"the map's camera is {kf_camera.width}x{kf_camera.height}, the sequence's "
                               f"{self.camera.width}x{self.camera.height}")  # fmt: skip
        if camera_to_dict(kf_camera) != camera_to_dict(self.camera):
            log.warning("the map's camera %s differs from the sequence's %s", kf_camera, self.camera)
        if atlas is not None:
            self.install_atlas(atlas, m)
        self.tracker.reset(m)
        self.tracker.state = TrackingState.LOST
        self.tracker.localization = bool(localization)
        self.use_map(m)
        self.database.clear()
        for kf in every:
            self.database.add(kf.id, kf.bow)
        log.info("installed a map of %d keyframes and %d points%s", m.n_keyframes(), m.n_points(),
                 " (localisation only)" if localization else "")  # fmt: skip

    def _map_changed(self, frame_id: int, timestamp: float, result: TrackResult) -> None:
        """The tracker discarded its map, started a new one or relocalised into another:
        the stages follow it to the active map (the keyframe database keeps every map's
        keyframes, less those of a discarded map)."""
        if result.reset:
            self.n_resets += 1
        self.use_map(self.tracker.map)
        if self.database is not None:
            for k in self.database.keyframes():
                if self.atlas.map_of(k) is None:
                    self.database.erase(k)
        event = "reset" if result.reset else "new_map" if result.new_map else "map_switched"
        self.events.append({"frame": frame_id, "t": timestamp, "event": event, "map": self.map.map_id,
                            **({"why": result.why} if result.why else {})})

"""Keyframe words from the map's own tracks: the word of a feature's causal track mean.

A descriptor seen alone predicts its 3D point's word poorly; averaged with the other
observations of the same point it does much better (``bench/bench_hgcn_labels.py --parts
ceiling``: 74.6-75.0% against 93.2% on tracks of the training imagery). SLAM holds those
tracks: a keyframe's features matched to map points have observations in earlier
keyframes. When a keyframe enters the keyframe database, each of its features that has a
track gets the word of the mean, in the vocabulary's PCA space, of the track's
descriptors observed in keyframes up to this one (causal: never a later keyframe); a
feature without a track keeps its own word. For an HGCN vocabulary the mean goes through
the network as a lone descriptor would.

Frames described alone keep lone words: a lost frame being relocalised, the tracker's
reference matching and every FeatureVector (BoW matching pairs features, not tracks).

The running sum of each map point's reduced descriptors is cached with the keyframes it
holds, so a keyframe adds only the observations that are new since the point was last
seen: the arithmetic does not grow with the track's length (reading the point's
observation list still does, as the map's own descriptor refresh does).

Works on ids and arrays (observations, descriptors), never on the map.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from orbslam_hgcn.vocabulary.bow import BowVector


class TrackWordsBase:
    """What the keyframe words from map-point tracks share: per-point state kept between
    keyframes in dicts keyed by point id (``caches``; the first holds every cached point),
    and the keyframe's BoW vector from the points that :meth:`track_points` gives its
    tracked features.

    vocabulary: has ``project(desc) -> (N, d)``, ``words_of_points(x) -> (N,) int32`` and
    ``bow_from_words(words)``.
    """

    def __init__(self, vocabulary, *caches: dict) -> None:
        self.vocabulary = vocabulary
        self._caches = caches

    def __len__(self) -> int:
        return len(self._caches[0])

    def points(self) -> list[int]:
        """Ids of the points with cached state."""
        return list(self._caches[0])

    def forget(self, pids: Sequence[int]) -> None:
        """Drop the cached state of points (bad or replaced ones)."""
        for p in pids:
            for cache in self._caches:
                cache.pop(int(p), None)

    def track_points(
        self,
        kf_id: int,
        x: np.ndarray,
        desc: np.ndarray,
        idx: np.ndarray,
        pids: np.ndarray,
        observations: Sequence[dict[int, int]],
        descriptors_of: Callable[[int], np.ndarray],
    ) -> tuple[np.ndarray, np.ndarray]:
        """((K,) indices into idx of the features whose words come from their tracks, (K, d)
        float32 the PCA-space points whose words they get); arguments as for
        :meth:`keyframe_bow`, x given."""
        raise NotImplementedError

    def keyframe_bow(
        self,
        kf_id: int,
        desc: np.ndarray,
        lone_words: np.ndarray,
        idx: np.ndarray,
        pids: np.ndarray,
        observations: Sequence[dict[int, int]],
        descriptors_of: Callable[[int], np.ndarray],
        x: np.ndarray | None = None,
    ) -> tuple[BowVector, np.ndarray]:
        """The keyframe's BoW vector from track words, and its (N,) int32 words.

        desc: (N, B) the keyframe's descriptors; lone_words: (N,) their own words (kept by
        features without a track); x: their reduced descriptors when already at hand. idx:
        (M,) its features linked to map points pids (M,), whose observations ({kf id:
        feature index}) are ``observations``. descriptors_of: kf id -> that keyframe's
        (N', B) descriptors.
        """
        v = self.vocabulary
        if x is None:
            x = v.project(desc)
        idx = np.asarray(idx)
        rows, points = self.track_points(kf_id, x, desc, idx, np.asarray(pids), observations, descriptors_of)
        words = np.array(lone_words, dtype=np.int32, copy=True)
        if len(rows):
            words[idx[rows]] = v.words_of_points(points)
        return v.bow_from_words(words), words


class TrackWords(TrackWordsBase):
    """Causal track-mean words over a flat (PCA-space) vocabulary (``kmeans`` or ``hgcn``).

    vocabulary: has ``project(desc) -> (N, d)`` and ``words_of_points(x) -> (N,) int32``.
    """

    def __init__(self, vocabulary) -> None:
        if not hasattr(vocabulary, "words_of_points"):
            raise ValueError(f"track words need a flat vocabulary (kmeans or hgcn), not {vocabulary.kind!r}")
        self._sum: dict[int, np.ndarray] = {}  # point id -> (d,) float64 sum of reduced descriptors
        self._seen: dict[int, set[int]] = {}  # point id -> keyframes already summed
        super().__init__(vocabulary, self._sum, self._seen)

    def means(
        self,
        kf_id: int,
        x: np.ndarray,
        idx: np.ndarray,
        pids: np.ndarray,
        observations: Sequence[dict[int, int]],
        descriptors_of: Callable[[int], np.ndarray],
    ) -> tuple[np.ndarray, np.ndarray]:
        """Causal track means of keyframe ``kf_id``'s tracked features.

        x: (N, d) reduced descriptors of the keyframe. idx: (M,) its features linked to map
        points pids (M,), whose observations ({kf id: feature index}) are ``observations``.
        descriptors_of: kf id -> that keyframe's (N', B) descriptors. Observations of
        keyframes after ``kf_id`` are ignored, and so is every point that the keyframe's
        own feature is not an observation of (a stale link).
        Returns ((K,) indices into idx of the features with a track of at least two
        observations, (K, d) float32 their means).
        """
        kf_id = int(kf_id)
        new_pt: list[int] = []
        new_kf: list[int] = []
        new_ix: list[int] = []
        keep = np.zeros(len(idx), bool)
        for k, (pid, obs) in enumerate(zip(pids.tolist(), observations)):
            if obs.get(kf_id) != int(idx[k]):
                continue
            seen = self._seen.setdefault(pid, set())
            n_causal = 0
            for j, i in obs.items():
                if j > kf_id:
                    continue
                n_causal += 1
                if j not in seen:
                    seen.add(j)
                    new_pt.append(pid)
                    new_kf.append(j)
                    new_ix.append(i)
            keep[k] = n_causal >= 2
        if new_pt:
            self._add(kf_id, x, np.array(new_pt), np.array(new_kf), np.array(new_ix), descriptors_of)
        rows = np.flatnonzero(keep)
        means = np.empty((len(rows), x.shape[1]), np.float32)
        for r, k in enumerate(rows.tolist()):
            pid = int(pids[k])
            means[r] = self._sum[pid] / len(self._seen[pid])
        return rows, means

    def _add(self, kf_id: int, x: np.ndarray, pts: np.ndarray, kfs: np.ndarray, ixs: np.ndarray,
             descriptors_of: Callable[[int], np.ndarray]) -> None:
        """Add the reduced descriptors of observations (pts, kfs, ixs) to the sums."""
        vals = np.empty((len(pts), x.shape[1]), np.float32)
        own = kfs == kf_id
        vals[own] = x[ixs[own]]
        other = np.flatnonzero(~own)
        if len(other):
            order = other[np.argsort(kfs[other], kind="stable")]
            kf_sorted = kfs[order]
            starts = np.flatnonzero(np.r_[True, kf_sorted[1:] != kf_sorted[:-1]])
            bounds = np.r_[starts, len(order)]
            desc = np.concatenate([descriptors_of(int(kf_sorted[s]))[ixs[order[s:e]]]
                                   for s, e in zip(bounds[:-1], bounds[1:])])
            vals[order] = self.vocabulary.project(desc)
        for pid, v in zip(pts.tolist(), vals):
            s = self._sum.get(pid)
            if s is None:
                self._sum[pid] = v.astype(np.float64)
            else:
                s += v

    def track_points(self, kf_id, x, desc, idx, pids, observations, descriptors_of):
        """The causal track means of the tracked features (:meth:`means`)."""
        return self.means(kf_id, x, idx, pids, observations, descriptors_of)

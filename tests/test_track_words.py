"""Track words: a keyframe's BoW from the causal means of its features' tracks, or from the
graph network over each feature's causal track mates. The words are those of the directly
computed means (network outputs), later keyframes never change them, and a lone frame
relocalises against a map whose keyframes carry track words (end to end)."""

import dataclasses

import numpy as np
import pytest
import vocab_fixtures as vf

from orbslam_hgcn.config import LocalMappingConfig
from orbslam_hgcn.errors import ConfigError
from orbslam_hgcn.geometry.camera import PinholeCamera
from orbslam_hgcn.datasets import open_sequence
from orbslam_hgcn.app.mapfile import load_map, save_system_map
from orbslam_hgcn.app.run import trajectory_ate
from orbslam_hgcn.runtime.system import Configs, System
from orbslam_hgcn.vocabulary import load_vocabulary
from orbslam_hgcn.vocabulary.track_network import TrackNetworkWords
from orbslam_hgcn.vocabulary.track_words import TrackWords


def _tracks(rng, n_kf=4, n_feat=300, n_points=120):
    """Descriptors of n_kf keyframes, and point observations {kf: feature} (every point seen
    in 2..n_kf keyframes, each time by a noisy copy of its own descriptor)."""
    base = rng.integers(0, 256, (n_points, 32), dtype=np.uint8)
    desc = [rng.integers(0, 256, (n_feat, 32), dtype=np.uint8) for _ in range(n_kf)]
    obs = []
    for p in range(n_points):
        kfs = np.sort(rng.choice(n_kf, rng.integers(2, n_kf + 1), replace=False))
        o = {}
        for k in kfs.tolist():
            i = int(rng.integers(0, n_feat))
            while any(oo.get(k) == i for oo in obs + [o]):
                i = int(rng.integers(0, n_feat))
            flip = rng.random((32, 8)) < 0.08
            desc[k][i] = base[p] ^ np.packbits(flip, axis=1)[:, 0]
            o[k] = i
        obs.append(o)
    return desc, obs


def _keyframe_args(desc, obs, kf, vocab):
    pids = np.array([p for p, o in enumerate(obs) if kf in o], np.int64)
    idx = np.array([obs[p][kf] for p in pids], np.int64)
    return (kf, desc[kf], vocab.transform_words(desc[kf]), idx, pids, [obs[p] for p in pids], desc.__getitem__)


def _check_causal_words(make, vocab, desc, obs, direct):
    """Feed the keyframes in order to a cache ``make(vocab)`` and check every keyframe's
    words against the direct computation ``direct(kf, feature, observations)`` (the word of
    the feature's causal track; None: its lone word) and against a fresh cache that sees the
    later keyframes' observations already linked (as a threaded run may: they are never
    used). Returns the cache."""
    tw = make(vocab)
    got = {kf: tw.keyframe_bow(*_keyframe_args(desc, obs, kf, vocab))[1] for kf in range(len(desc))}
    n_changed = 0
    for kf in range(len(desc)):
        args = _keyframe_args(desc, obs, kf, vocab)
        words = args[2].copy()
        for i, o in zip(args[3], args[5]):
            w = direct(kf, i, o)
            if w is not None:
                words[i] = w
        assert np.array_equal(got[kf], words), kf
        n_changed += int(np.sum(words != args[2]))
        assert np.array_equal(make(vocab).keyframe_bow(*args)[1], got[kf])
    assert n_changed > 20  # the tracks do change words (the test can tell)
    # The first keyframe's tracks hold only itself: its words are its lone words.
    assert np.array_equal(got[0], vocab.transform_words(desc[0]))
    return tw


@pytest.mark.parametrize("which", ["kmeans", "hgcn"])
def test_track_words_are_the_words_of_causal_means_and_never_change(which):
    vocab = vf.small_kmeans_vocab() if which == "kmeans" else vf.small_hgcn_vocab()
    desc, obs = _tracks(np.random.default_rng(3))

    def direct(kf, i, o):
        # The mean of the reduced descriptors over keyframes <= kf.
        causal = [vocab.project(desc[j][[f]])[0] for j, f in o.items() if j <= kf]
        if len(causal) >= 2:
            return vocab.words_of_points(np.mean(causal, 0, keepdims=True).astype(np.float32))[0]
        return None

    _check_causal_words(TrackWords, vocab, desc, obs, direct)


def test_track_words_need_a_flat_vocabulary():
    with pytest.raises(ValueError, match="flat vocabulary"):
        TrackWords(load_vocabulary("orb"))


@pytest.fixture(scope="module", params=[("hgcn", "mean"), ("hgcn_graph", "network")], ids=["means", "network"])
def track_mapped(request, synth_replay_100, tmp_path_factory):
    """The replay's first 60 frames mapped with keyframe words from track means (HGCN
    vocabulary) or from the track network, and the saved map."""
    name, by = request.param
    seq = open_sequence("tum", synth_replay_100)
    vocab = load_vocabulary(name)
    configs = Configs(local_mapping=dataclasses.replace(LocalMappingConfig(), track_words=True, track_words_by=by))
    system = System(seq.camera, configs, vocabulary=vocab, sequential=True)
    system.run(seq, 60, progress=False)
    path = save_system_map(tmp_path_factory.mktemp("map") / "map.npz", system, "hgcn")
    return seq, vocab, system, path


def test_lone_frame_relocalises_against_track_words(track_mapped):
    seq, vocab, mapping, path = track_mapped
    kfs = [kf for kf in mapping.map.keyframes() if not kf.bad]
    assert len(kfs) >= 4
    # The database holds track words: most keyframes' BoW vectors differ from their lone ones.
    differ = [not np.array_equal(kf.bow.words, vocab.bow(kf.keypoints.desc).words) for kf in kfs]
    assert sum(differ) >= len(kfs) - 1  # the first keyframe has no earlier track mates
    assert mapping.mapper.timings["track_words"]
    m = load_map(path, vocab).map
    system = System(seq.camera, vocabulary=vocab, sequential=True)
    system.install_map(m, localization=True)
    for i in range(30, 40):
        system.process(seq[i].image, seq[i].timestamp, seq[i].index)
    stats = system.stats()
    # The first frame after the load is lost by construction and described alone.
    assert stats["relocalization"]["successes"] >= 1 and stats["relocalization"]["history"][0][0] == 30
    assert stats["frames"]["tracked"] == 10
    # Its pose agrees with the mapping run's pose of the same frame, within three times the
    # per-frame error of that run against the ground truth (RMSE after Sim(3) alignment,
    # taken to map units by the alignment's scale): the relocalised pose is as good as a
    # tracked one.
    loc = system.camera_trajectory()
    ref = mapping.camera_trajectory()
    j = ref.nearest(loc.timestamps[0], 1e-4)
    assert j is not None
    ate = trajectory_ate(seq.ground_truth, ref)
    assert np.linalg.norm(loc.positions[0] - ref.positions[j]) < 3.0 * ate["rmse_m"] / ate["scale"]


# --- the graph network over causal track mates (local_mapping.track_words_by: network) ---


def test_track_network_words_are_the_networks_words_of_causal_mates_and_never_change():
    vocab = load_vocabulary("hgcn_graph")
    net = vocab.track_network
    n_kf = net.window + 4  # tracks longer than the window: the cache keeps only the recent mates
    desc, obs = _tracks(np.random.default_rng(4), n_kf=n_kf)

    def direct(kf, i, o):
        # The network on the feature and its window most recent observations in earlier keyframes.
        older = sorted((j for j in o if j < kf), reverse=True)[: net.window]
        if not older:
            return None
        mates = np.zeros((1, net.window, vocab.pca.dim), np.float32)
        mask = np.zeros((1, net.window), bool)
        ham = np.zeros((1, net.window))
        for r, j in enumerate(older):
            mates[0, r] = vocab.project(desc[j][[o[j]]])[0]
            mask[0, r] = True
            ham[0, r] = np.unpackbits(desc[kf][i] ^ desc[j][o[j]]).sum()
        return vocab.words_of_points(net.embed(vocab.project(desc[kf][[i]]), mates, mask, ham))[0]

    tw = _check_causal_words(TrackNetworkWords, vocab, desc, obs, direct)
    assert max(len(tw._obs[p]) for p in tw.points()) <= net.window + 1


def test_track_network_words_need_a_vocabulary_with_a_network():
    with pytest.raises(ValueError, match="track network"):
        TrackNetworkWords(load_vocabulary("kmeans"))
    with pytest.raises(ConfigError, match="track_words_by"):
        LocalMappingConfig(track_words_by="median")
    configs = Configs(local_mapping=LocalMappingConfig(track_words=True, track_words_by="network"))
    with pytest.raises(ConfigError, match="hgcn_graph"):
        System(PinholeCamera(500, 500, 320, 240, 640, 480), configs, vocabulary=load_vocabulary("kmeans"), sequential=True)

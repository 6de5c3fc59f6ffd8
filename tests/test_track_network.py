"""The graph network over causal feature tracks on planted tracks: where a lone descriptor
is ambiguous, the trained network names its track's class and the untrained one (the
identity) does not; attention down-weights planted bad mates where the plain mean cannot;
the numpy run-time form equals the torch model."""

import dataclasses

import numpy as np
import pytest
import torch

from orbslam_hgcn.vocabulary.track_network import HAM_SCALE, POPCOUNT, TrackNetwork
from orbslam_hgcn.vocabulary.training.track_net import (
    TorchTrackNet,
    TrackNetConfig,
    track_nodes,
    train_track_network,
)

CFG = TrackNetConfig(window=8, epochs=40, min_epochs=10, patience=10, batch=512, holdout=0.15)


def planted_tracks(rng, centres, tracks_per_class=60, track_len=12, outliers=0):
    """Tracks of noisy views of planted class centres (rows in causal order). With
    ``outliers``, that many members of every track (not the first) are views of another
    class and carry unrelated binary descriptors, the good members noisy copies of the
    track's own. Returns (x (M, d), desc (M, 32), track (M,), truth per track (T,), good (M,))."""
    n_classes, d = centres.shape
    n_tracks = n_classes * tracks_per_class
    truth = np.repeat(np.arange(n_classes), tracks_per_class)
    track = np.repeat(np.arange(n_tracks), track_len)
    cls = truth[track].copy()
    good = np.ones(len(track), bool)
    if outliers:
        pos = np.tile(np.arange(track_len), n_tracks)
        for t in range(n_tracks):
            bad = t * track_len + rng.choice(np.arange(1, track_len), outliers, replace=False)
            good[bad] = False
            cls[bad] = (truth[t] + rng.integers(1, n_classes, outliers)) % n_classes
        assert not np.any(~good & (pos == 0))
    x = (centres[cls] + rng.normal(size=(len(track), d))).astype(np.float32)
    base = rng.integers(0, 256, (n_tracks, 32), dtype=np.uint8)
    flips = np.packbits(rng.random((len(track), 32, 8)) < 0.06, axis=2)[..., 0]
    desc = np.where(good[:, None], base[track] ^ flips, rng.integers(0, 256, (len(track), 32), dtype=np.uint8))
    return x, desc.astype(np.uint8), track, truth, good


def _nearest(x, centres):
    return np.argmin(((x[:, None, :] - centres[None]) ** 2).sum(-1), axis=1)


def _accuracy(net: TrackNetwork, x, desc, track, truth, centres, good=None):
    """Word accuracy of the network on every good centre with a full window of mates."""
    nodes = track_nodes(track, desc, net.window, truth, good)
    full = nodes.available == net.window
    mask = nodes.mates[full] >= 0
    y = net.embed(x[nodes.centre[full]], x[np.maximum(nodes.mates[full], 0)], mask, nodes.ham[full])
    return float(np.mean(_nearest(y, centres) == nodes.target[full]))


@pytest.fixture(scope="module")
def planted():
    rng = np.random.default_rng(0)
    centres = rng.normal(size=(6, 20)) * 0.3
    train = planted_tracks(rng, centres)
    test = planted_tracks(rng, centres)
    return centres, train, test


def test_trained_track_network_names_the_track_where_the_identity_cannot(planted):
    centres, (x, desc, track, truth, _), test = planted
    # The problem: a lone descriptor's nearest class centre is mostly wrong.
    assert np.mean(_nearest(test[0], centres) == test[3][test[2]]) <= 0.6
    net, stats = train_track_network(x, track, centres, CFG, desc=desc, track_target=truth, device="cpu")
    assert stats["best_epoch"] >= 1 and stats["epochs"] >= CFG.min_epochs
    assert _accuracy(net, *test[:4], centres) >= 0.9
    # The untrained network (gate 0) is the identity: lone words, the same test fails.
    identity = dataclasses.replace(net, gate=np.zeros_like(net.gate))
    x_t = test[0]
    nodes = track_nodes(test[2], test[1], net.window, test[3])
    y = identity.embed(x_t[nodes.centre], x_t[np.maximum(nodes.mates, 0)], nodes.mates >= 0, nodes.ham)
    np.testing.assert_allclose(y, x_t[nodes.centre], atol=1e-5)
    assert _accuracy(identity, *test[:4], centres) <= 0.6


def test_attention_down_weights_planted_bad_mates():
    rng = np.random.default_rng(1)
    # Far enough apart that the good mates' mean names the class (97%) and the bad ones
    # spoil the plain mean (86%, 4 of 12 track members from other classes).
    centres = rng.normal(size=(6, 20)) * 0.5
    x, desc, track, truth, good = planted_tracks(rng, centres, outliers=4)
    test = planted_tracks(rng, centres, outliers=4)
    att, _ = train_track_network(x, track, centres, CFG, desc=desc, track_target=truth, centre_ok=good,
                                 device="cpu")
    mean, _ = train_track_network(x, track, centres, dataclasses.replace(CFG, aggregation="mean"), desc=desc,
                                  track_target=truth, centre_ok=good, device="cpu")
    acc_att = _accuracy(att, *test[:4], centres, test[4])
    acc_mean = _accuracy(mean, *test[:4], centres, test[4])
    assert acc_att >= 0.9 and acc_att >= acc_mean + 0.05, (acc_att, acc_mean)
    # The attention weights: bad mates get less than good ones.
    nodes = track_nodes(test[2], test[1], att.window, test[3], test[4])
    full = nodes.available == att.window
    u = test[0][nodes.centre[full]] / att.input_scale
    um = test[0][np.maximum(nodes.mates[full], 0)] / att.input_scale
    d = att.dim
    logit = (np.abs(u[:, None] - um) @ att.att[:d] + (u[:, None] * um) @ att.att[d: 2 * d]
             + nodes.ham[full] / HAM_SCALE * att.att[2 * d])
    bad = ~test[4][nodes.mates[full]]
    assert logit[bad].mean() < logit[~bad].mean() - 1.0


def test_numpy_network_equals_the_torch_model():
    rng = np.random.default_rng(2)
    d, w, n = 20, 6, 300
    model = TorchTrackNet(d, dataclasses.replace(TrackNetConfig(), window=w), input_scale=3.0).double()
    with torch.no_grad():
        for p in (model.weight, model.bias, model.gate, model.att, model.att_bias, model.att_self):
            p.add_(torch.from_numpy(rng.normal(scale=0.3, size=tuple(p.shape))))
    x = rng.normal(size=(n, d)) * 1.5
    mates = x[:, None, :] + rng.normal(size=(n, w, d))
    mask = np.arange(w)[None, :] < rng.integers(0, w + 1, n)[:, None]
    ham = rng.integers(0, 256, (n, w)).astype(np.float64)
    with torch.no_grad():
        ref = model(*(torch.from_numpy(a) for a in (x / 3.0, mates / 3.0, mask, ham))).numpy() * 3.0
    net = model.to_numpy()
    got = net.embed(x, mates, mask, ham)
    np.testing.assert_allclose(got, ref, atol=1e-5)
    assert np.array_equal(got[~mask.any(1)], x[~mask.any(1)].astype(np.float32))
    assert np.abs(got - x)[mask.any(1)].max() > 0.1  # the network moves tracked centres
    # Saved arrays load back to the same network.
    again = TrackNetwork.from_arrays(net.arrays())
    np.testing.assert_array_equal(again.embed(x, mates, mask, ham), got)
    assert POPCOUNT[255] == 8


@pytest.mark.parametrize("name, arm, aggregation", [("hgcn_graph", "C-att", "attention"),
                                                    ("hgcn_graph_mean", "C", "mean")])
def test_shipped_track_network_files(name, arm, aggregation, tmp_path):
    from orbslam_hgcn.vocabulary import load_vocabulary

    vocab = load_vocabulary(name)
    meta = vocab.metadata
    assert meta.kind == "hgcn" and meta.params["arm"] == arm and meta.params["aggregation"] == aggregation
    assert vocab.track_network.aggregation == aggregation
    assert meta.stats["best_epoch"] >= 1
    assert meta.stats["validation_accuracy"] > meta.stats["validation_accuracy_untrained"]
    # Lone descriptors keep the k-means vocabulary's words.
    kmeans = load_vocabulary("kmeans")
    desc = np.random.default_rng(0).integers(0, 256, (500, 32), dtype=np.uint8)
    assert np.array_equal(vocab.transform_words(desc), kmeans.transform_words(desc))
    # The network survives a save and load.
    again = load_vocabulary(vocab.save(tmp_path / "v.npz"))
    assert again.track_network.arrays().keys() == vocab.track_network.arrays().keys()
    for k, a in vocab.track_network.arrays().items():
        np.testing.assert_array_equal(again.track_network.arrays()[k], a)

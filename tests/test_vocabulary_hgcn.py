"""The HGCN vocabulary's parts: PCA, kNN graph, propagation blocks, label seeding, the
HGCN on planted clusters, and the trained vocabulary's quantiser."""

import dataclasses
from math import comb

import numpy as np
import pytest
import scipy.sparse as sp
import vocab_fixtures as vf

from orbslam_hgcn.config import HgcnTrainConfig
from orbslam_hgcn.vocabulary.graph import (
    build_graph,
    descriptor_features,
    fit_pca,
    knn,
    normalised_adjacency,
    symmetric_adjacency,
    two_hop_blocks,
)
from orbslam_hgcn.vocabulary.training.hgcn import train_hgcn
from orbslam_hgcn.vocabulary.hgcn_vocab import seed_labels


def adjusted_rand_index(a: np.ndarray, b: np.ndarray) -> float:
    """Hubert & Arabie's adjusted Rand index of two labellings."""
    _, a = np.unique(a, return_inverse=True)
    _, b = np.unique(b, return_inverse=True)
    table = np.zeros((a.max() + 1, b.max() + 1), np.int64)
    np.add.at(table, (a, b), 1)
    pairs = sum(comb(int(v), 2) for v in table.ravel())
    rows = sum(comb(int(v), 2) for v in table.sum(1))
    cols = sum(comb(int(v), 2) for v in table.sum(0))
    expected = rows * cols / comb(len(a), 2)
    return (pairs - expected) / (0.5 * (rows + cols) - expected)


def test_pca_lookup_table_equals_unpacked_projection():
    rng = np.random.default_rng(0)
    desc = rng.integers(0, 256, (500, 32), dtype=np.uint8)
    pca = fit_pca(desc, 20)
    f = descriptor_features(desc)
    np.testing.assert_allclose(pca.transform(desc), (f - pca.mean) @ pca.components, atol=1e-4)
    np.testing.assert_allclose(pca.components.T @ pca.components, np.eye(20), atol=1e-5)
    # The first component carries the most variance of the data.
    var = ((f - pca.mean) @ pca.components).var(0)
    assert np.all(np.diff(var) <= 1e-3)


def test_knn_graph_is_symmetric_with_requested_degree():
    rng = np.random.default_rng(1)
    x = rng.normal(size=(300, 20)).astype(np.float32)
    x[10] = x[11]  # exact duplicates must not confuse self-exclusion
    k = 9
    nbr = knn(x, k)
    d = ((x[:, None] - x[None]) ** 2).sum(-1)
    np.fill_diagonal(d, np.inf)
    brute = np.argsort(d, axis=1)[:, :k]
    agree = np.mean([len(set(a) & set(b)) / k for a, b in zip(nbr, brute)])
    assert agree > 0.99 and not np.any(nbr == np.arange(300)[:, None])
    a = symmetric_adjacency(nbr)
    assert (a != a.T).nnz == 0 and a.diagonal().sum() == 0
    assert np.asarray(a.sum(1)).min() >= k and set(np.unique(a.data)) == {1.0}
    for i in range(300):
        assert set(nbr[i]) <= set(a.indices[a.indptr[i] : a.indptr[i + 1]])
    an = normalised_adjacency(a).toarray()
    dense = a.toarray() + np.eye(300)
    deg = dense.sum(1)
    np.testing.assert_allclose(an, dense / np.sqrt(deg[:, None] * deg[None, :]), rtol=1e-5)
    np.testing.assert_allclose(an, an.T)
    # The approximate (IVF) path still gives every node at least k neighbours.
    big = rng.normal(size=(2000, 20)).astype(np.float32)
    assert np.asarray(symmetric_adjacency(knn(big, k, exact_max=100)).sum(1)).min() >= k


def test_two_hop_blocks_compute_two_layers_exactly():
    rng = np.random.default_rng(2)
    x = rng.normal(size=(400, 5)).astype(np.float32)
    adj = build_graph(x, 4)
    feats = rng.normal(size=(400, 3))
    seeds = np.sort(rng.choice(400, 25, replace=False))
    hop2, (r1, c1, v1), hop1, (r2, c2, v2) = two_hop_blocks(adj, seeds)
    b1 = sp.csr_matrix((v1, (r1, c1)), shape=(len(hop1), len(hop2)))
    b2 = sp.csr_matrix((v2, (r2, c2)), shape=(len(seeds), len(hop1)))
    exact = (adj @ (adj @ feats))[seeds]
    np.testing.assert_allclose(b2 @ (b1 @ feats[hop2]), exact, rtol=1e-5, atol=1e-6)
    # With 3 sampled layer-1 neighbours: fewer inputs, the same aggregation on average.
    mean = np.zeros_like(exact)
    for _ in range(300):
        h2, (r1, c1, v1), h1, (r2, c2, v2) = two_hop_blocks(adj, seeds, 3, rng)
        assert len(h2) <= len(hop2) and np.array_equal(h1, hop1)
        b1 = sp.csr_matrix((v1, (r1, c1)), shape=(len(h1), len(h2)))
        mean += sp.csr_matrix((v2, (r2, c2)), shape=(len(seeds), len(h1))) @ (b1 @ feats[h2]) / 300
    assert np.abs(mean - exact).max() < 0.1 * np.abs(exact).max()


def test_seed_labels_fraction_and_shared_track_labels():
    rng = np.random.default_rng(3)
    x = rng.normal(size=(1000, 4)).astype(np.float32)
    cfg = HgcnTrainConfig(n_words=20, label_fraction=0.1, kmeans_iters=5)
    labels, centres = seed_labels(x, cfg, None, np.random.default_rng(0))
    assert (labels >= 0).sum() == 100 and centres.shape == (20, 4)
    tracks = np.arange(1000) // 5  # 200 tracks of 5 descriptors
    labels_t, _ = seed_labels(x, cfg, tracks, np.random.default_rng(0))
    seeded = np.unique(tracks[labels >= 0])
    members = np.isin(tracks, seeded)
    assert np.all(labels_t[members] >= 0) and np.all(labels_t[~members] == -1)
    for t in seeded:
        assert len(np.unique(labels_t[tracks == t])) == 1


def planted(rng, n_clusters=6, per=80, spread=1.2):
    centres = rng.normal(size=(n_clusters, 20)) * spread
    truth = np.repeat(np.arange(n_clusters), per)
    return centres, truth, (centres[truth] + rng.normal(size=(len(truth), 20))).astype(np.float32)


def planted_tracks(rng, n_classes=6, tracks_per_class=40, track_len=12, spread=0.35):
    """Planted classes seen through tracks: every track holds track_len noisy views of one
    class centre, so that a lone view is ambiguous and a track's mean is not. Returns
    (truth (N,), track (N,), x (N, 20), the normalised graph of the tracks' cliques)."""
    centres = rng.normal(size=(n_classes, 20)) * spread
    track = np.repeat(np.arange(n_classes * tracks_per_class), track_len)
    truth = np.repeat(np.arange(n_classes), tracks_per_class)[track]
    x = (centres[truth] + rng.normal(size=(len(truth), 20))).astype(np.float32)
    same = track[:, None] == track[None, :]
    np.fill_diagonal(same, False)
    return truth, track, x, normalised_adjacency(sp.csr_matrix(same.astype(np.float32)))


def _nearest_row(x: np.ndarray, centres: np.ndarray) -> np.ndarray:
    return np.argmin(((x[:, None, :] - centres[None]) ** 2).sum(-1), axis=1)


def test_hgcn_uses_the_track_graph_where_a_lone_descriptor_is_ambiguous():
    """A do-nothing network (the untrained layers: identity self path, zero neighbour path)
    must fail here, the trained one must not."""
    rng = np.random.default_rng(0)
    truth, track, x, adj = planted_tracks(rng)
    seeded = rng.random(len(truth)) < 0.1
    labels = np.where(seeded, truth, -1)
    seed_centres = np.stack([x[seeded & (truth == k)].mean(0) for k in range(6)])
    # The problem: a lone descriptor's nearest seed centre is mostly wrong, its track's mean
    # nearly never.
    assert np.mean(_nearest_row(x, seed_centres) == truth) <= 0.6
    means = np.stack([x[track == t].mean(0) for t in range(track.max() + 1)])[track]
    assert np.mean(_nearest_row(means, seed_centres) == truth) >= 0.97
    cfg = HgcnTrainConfig(n_words=6, hidden_dim=16, epochs=40, holdout=0.1, lr=0.1, patience=100)
    model, pred, stats = train_hgcn(x, adj, labels, seed_centres, cfg, groups=track, progress=False)
    assert np.mean(pred[~seeded] == truth[~seeded]) >= 0.9
    assert stats["hgcn_best_epoch"] > 0 and all(c > 0 for c in stats["curvatures"])
    # The untrained network: one epoch that cannot move the layers (learning rates 0).
    _, identity_pred, _ = train_hgcn(x, adj, labels, seed_centres, dataclasses.replace(cfg, epochs=1, lr=0.0, scale_lr=0.0),
                                     groups=track, progress=False)
    assert np.mean(identity_pred[~seeded] == truth[~seeded]) < 0.7
    # The numpy copy of the layers gives the torch model's embeddings.
    import torch

    net = model.to_numpy(model.input_scale)
    with torch.no_grad():
        iso = model.embed_isolated(torch.from_numpy(x / model.input_scale)).numpy()
    np.testing.assert_allclose(net.embed_isolated(x), iso, atol=2e-5)


@pytest.mark.parametrize("activation", ["relu", "leaky_relu", "elu", "tanh"])
@pytest.mark.parametrize("residual", [True, False])
def test_compiled_lone_node_layers_equal_the_numpy_graph_form(activation, residual):
    """The compiled kernel of the run-time embedding gives what the numpy layers give a
    node without neighbours, also where the projections onto the ball clip."""
    from orbslam_hgcn.vocabulary.ball import BallNetwork

    rng = np.random.default_rng(3)
    ws = [rng.normal(size=(16, 20)) * 0.4, rng.normal(size=(16, 16)) * 0.4]
    bs = [rng.normal(size=16) * 0.2 for _ in ws]
    sws = [rng.normal(size=w.shape) * 0.4 for w in ws] if residual else []
    sbs = [rng.normal(size=16) * 0.2 for _ in ws] if residual else []
    net = BallNetwork(ws, bs, sws, sbs, np.array([0.3, 1.2, 0.5]), activation, 2.0)
    x = (rng.normal(size=(500, 20)) * rng.choice([0.1, 1.0, 30.0], size=(500, 1))).astype(np.float32)
    np.testing.assert_allclose(net.embed_isolated(x), net.embed_graph(x, None), atol=1e-6)
    assert net.embed_isolated(x[:0]).shape == (0, 16)


def test_prototype_search_is_the_exact_hyperbolic_nearest():
    """The exhaustive L2 search over the lifted prototypes finds the prototype nearest in
    the ball's distance, with prototypes from the centre to near the boundary (where the
    Euclidean nearest is often not the hyperbolic one). (The run-time search over the same
    lifted points is compared with this one in test_vocabulary_probe.py.)"""
    from orbslam_hgcn.vocabulary.ball import PrototypeSearch

    rng = np.random.default_rng(4)
    c = 0.7
    dirs = rng.normal(size=(3000, 20))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    protos = dirs * (rng.uniform(0.0, 0.97, size=(3000, 1)) / np.sqrt(c))
    h = (protos[rng.integers(0, 3000, 2000)] + rng.normal(size=(2000, 20)) * 0.15)
    h *= np.minimum(1.0, 0.97 / np.sqrt(c) / np.linalg.norm(h, axis=1, keepdims=True))
    p2 = (protos ** 2).sum(1)
    d = np.arccosh(1 + 2 * c * ((h[:, None] - protos[None]) ** 2).sum(-1)
                   / ((1 - c * (h ** 2).sum(1))[:, None] * (1 - c * p2)[None]))
    truth = d.argmin(1)
    got = PrototypeSearch(protos.astype(np.float32), c).search(h.astype(np.float32), exact=True)
    euclid = ((h[:, None] - protos[None]) ** 2).sum(-1).argmin(1)
    assert np.mean(euclid != truth) > 0.05  # the metric matters here
    wrong = got != truth
    # Float32 near-ties aside: a different answer is (almost) as near as the true one.
    assert wrong.mean() < 0.005
    assert np.all(d[np.flatnonzero(wrong), got[wrong]] - d[np.flatnonzero(wrong), truth[wrong]] < 1e-3)


def test_runtime_assignment_reproduces_the_network_labels_on_planted_clusters():
    """The run-time word (the trained layers applied to one descriptor alone, then the nearest
    prototype) is the word the network gives the descriptor inside the training graph, for
    training descriptors and for new ones (labelled inside a graph over both)."""
    from orbslam_hgcn.vocabulary.hgcn_vocab import train_hgcn_vocabulary

    rng = np.random.default_rng(1)
    centres, truth, x = planted(rng, 12, 150, 2.0)
    lift = rng.normal(size=(20, 64))
    desc = (x @ lift).astype(np.float32)  # float descriptors, 64-D
    cfg = HgcnTrainConfig(n_words=12, pca_dim=20, hidden_dim=16, epochs=10, n_coarse=3, label_fraction=0.2)
    vocab = train_hgcn_vocabulary(desc, np.arange(len(desc)) // 30, cfg, progress=False)
    stats = vocab.metadata.stats
    assert vocab.assignment == "network" and stats["runtime_word_agreement"] >= 0.9
    xp = vocab.project(desc)
    graph = vocab.graph_words(xp, build_graph(xp, 9))
    assert np.mean(vocab.words_of_points(xp) == graph) >= 0.9
    # New descriptors of the same clusters.
    new = ((centres[truth[::5]] + rng.normal(size=(len(truth[::5]), 20))) @ lift).astype(np.float32)
    both = np.concatenate([desc, new])
    bp = vocab.project(both)
    in_graph = vocab.graph_words(bp, build_graph(bp, 9))[len(desc):]
    alone = vocab.transform_words(new)
    assert np.mean(alone == in_graph) >= 0.9


def test_trained_hgcn_vocabulary_quantiser():
    vocab = vf.small_hgcn_vocab()
    cfg = vf.SMALL_HGCN
    assert vocab.n_words == cfg.n_words and vocab.centroids.shape == (cfg.n_words, cfg.pca_dim)
    assert np.all(np.isfinite(vocab.centroids)) and np.all(vocab.idf >= 0)
    desc = vf.descriptors("euroc", 0)
    x = vocab.project(desc)
    # Network assignment: the nearest prototype (hyperbolic distance) of the lone-node
    # embedding; the search is exact.
    assert vocab.assignment == "network"
    h = vocab.embed(x).astype(np.float64)
    c = float(vocab.network.curvatures[-1])
    p = vocab.prototypes.astype(np.float64)
    d = np.arccosh(1 + 2 * c * ((h[:, None] - p[None]) ** 2).sum(-1)
                   / ((1 - c * (h ** 2).sum(-1))[:, None] * (1 - c * (p ** 2).sum(-1))[None]))
    words = vocab.transform_words(desc)
    assert np.mean(words == d.argmin(1)) > 0.99  # float32 ties aside
    np.testing.assert_array_equal(vocab.word_nodes(words, 4), vocab.word_coarse[words])
    assert vocab.word_coarse.max() < cfg.n_coarse
    # Centroid assignment: the nearest class-mean centroid in PCA space.
    vocab.assignment = "centroid"
    try:
        brute = ((x[:, None] - vocab.centroids[None]) ** 2).sum(-1).argmin(1)
        np.testing.assert_array_equal(vocab.transform_words(desc), brute)
    finally:
        vocab.assignment = "network"
    meta = vocab.metadata
    assert meta.n_descriptors == len(vf.training_set()[0]) and meta.n_images == 10
    assert meta.params["pca_dim"] == 20 and meta.params["knn"] == 9
    assert dataclasses.asdict(cfg)["label_fraction"] == meta.params["label_fraction"]
    for key in ("labelled_accuracy", "validation_accuracy", "heldout_accuracy", "runtime_word_agreement"):
        assert 0.0 <= meta.stats[key] <= 1.0
    assert meta.stats["runtime_word_agreement"] >= 0.9


def test_tracks_from_consecutive_real_frames():
    from orbslam_hgcn.vocabulary.training.tracks import build_tracks, match_pair

    kps = [vf.keypoints("tum", i) for i in range(4, 8)]  # 33 ms apart: nearly the same view
    a, b = match_pair(kps[0].desc, kps[1].desc, kps[0].uv_raw, kps[1].uv_raw)
    assert len(a) > 300 and len(np.unique(a)) == len(a) and len(np.unique(b)) == len(b)
    assert np.median(np.linalg.norm(kps[0].uv_raw[a] - kps[1].uv_raw[b], axis=1)) < 3.0
    # Different places (TUM vs EuRoC) give (almost) no verified match.
    e = vf.keypoints("euroc", 0)
    assert len(match_pair(kps[0].desc, e.desc, kps[0].uv_raw, e.uv_raw)[0]) < 20
    # Tracks over the four frames, plus one frame of another sequence (never linked).
    desc = [k.desc for k in kps] + [e.desc]
    uv = [k.uv_raw for k in kps] + [e.uv_raw]
    track = build_tracks(desc, uv, np.array([0, 0, 0, 0, 1]), progress=False)
    image = np.repeat(np.arange(5), [len(d) for d in desc])
    assert np.all(track[image == 4] == -1)
    linked = track >= 0
    assert linked[image < 4].mean() > 0.5
    pairs = np.unique(np.stack([track[linked], image[linked]], 1), axis=0)
    assert len(pairs) == linked.sum()  # one descriptor per image in every track


def test_tracks_of_float_descriptors():
    """SIFT (float) descriptors are matched by Euclidean distance under the same rules."""
    import cv2

    from orbslam_hgcn.vocabulary.training.tracks import match_pair

    sift = cv2.SIFT_create(nfeatures=800)

    def describe(path):
        kps, desc = sift.detectAndCompute(cv2.imread(str(path), cv2.IMREAD_GRAYSCALE), None)
        return desc.astype(np.float32), np.array([k.pt for k in kps], np.float32)

    tum = sorted(vf.tum_rgb().glob("*.png"))
    (d1, uv1), (d2, uv2) = describe(tum[4]), describe(tum[5])
    a, b = match_pair(d1, d2, uv1, uv2)
    assert len(a) > 150 and len(np.unique(a)) == len(a)
    assert np.median(np.linalg.norm(uv1[a] - uv2[b], axis=1)) < 3.0
    de, uve = describe(sorted(vf.euroc_rgb().glob("*.png"))[0])
    assert len(match_pair(d1, de, uv1, uve)[0]) < 20


def test_hgcn_vocabulary_on_float_descriptors(tmp_path):
    from orbslam_hgcn.vocabulary import load_vocabulary
    from orbslam_hgcn.vocabulary.hgcn_vocab import train_hgcn_vocabulary

    # SIFT-like 128-D float descriptors around 10 centres, 30 "images"; 40 words: no word
    # may mix two centres' descriptors (k-means seeds start from random points, so fewer
    # words than centres could merge some).
    rng = np.random.default_rng(4)
    centres = rng.normal(0, 5, (10, 128)).astype(np.float32)
    truth = rng.integers(0, 10, 3000)
    desc = centres[truth] + rng.normal(0, 0.3, (3000, 128)).astype(np.float32)
    cfg = HgcnTrainConfig(n_words=40, hidden_dim=8, epochs=4, n_coarse=4, label_fraction=0.2)
    vocab = train_hgcn_vocabulary(desc, np.arange(3000) // 100, cfg, progress=False)
    assert vocab.descriptor_type == "float" and vocab.metadata.descriptor_dim == 128
    words = vocab.transform_words(desc)
    purity = sum(np.bincount(truth[words == w]).max() for w in np.unique(words)) / len(words)
    assert purity == 1.0 and len(np.unique(words)) > 30
    vocab.save(tmp_path / "sift.npz")
    back = load_vocabulary(tmp_path / "sift.npz")
    np.testing.assert_array_equal(back.transform_words(desc[:100]), words[:100])
    with pytest.raises(ValueError):
        vocab.transform_words(desc.astype(np.uint8))

"""Vocabulary files: round trips, damaged files, the CLI and interrupted training."""

import zipfile

import numpy as np
import pytest
import vocab_fixtures as vf

from orbslam_hgcn import cli
from orbslam_hgcn.errors import VocabularyError
from orbslam_hgcn.vocabulary import load_vocabulary
from orbslam_hgcn.vocabulary.training import train as train_mod
from orbslam_hgcn.npzfile import atomic_save_npz
from orbslam_hgcn.vocabulary.base import FORMAT_VERSION
from orbslam_hgcn.vocabulary.flat import KMeansVocabulary
from orbslam_hgcn.vocabulary.hgcn_vocab import HGCNVocabulary
from orbslam_hgcn.vocabulary.orb_tree import TreeVocabulary


KINDS = {"orb": vf.small_orb_vocab, "hgcn": vf.small_hgcn_vocab, "kmeans": vf.small_kmeans_vocab}


@pytest.fixture(params=list(KINDS))
def saved(request, tmp_path):
    vocab = KINDS[request.param]()
    path = tmp_path / f"{request.param}.npz"
    vocab.save(path)
    return vocab, path


def test_round_trip_gives_identical_output(saved):
    vocab, path = saved
    back = load_vocabulary(path)
    assert type(back) is type(vocab) and back.kind == vocab.kind
    assert back.metadata == vocab.metadata
    for desc in (vf.descriptors("tum", 0), vf.descriptors("euroc", 0)):
        np.testing.assert_array_equal(back.transform_words(desc), vocab.transform_words(desc))
        (b1, f1), (b2, f2) = vocab.transform(desc), back.transform(desc)
        assert b1 == b2 and len(b1) > 0
        assert f1.keys() == f2.keys() and all(np.array_equal(f1[k], f2[k]) for k in f1)
    assert load_vocabulary(path, expected_kind=vocab.kind).n_words == vocab.n_words


def _expect_error(path, match=None, **kw):
    with pytest.raises(VocabularyError, match=match) as err:
        load_vocabulary(path, **kw)
    assert str(path) in str(err.value)


def test_damaged_files_raise_vocabulary_errors(saved, tmp_path):
    vocab, path = saved
    data = path.read_bytes()
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(data[: len(data) // 2])
    _expect_error(truncated, "truncated or corrupt")
    corrupt = tmp_path / "corrupt.npz"
    flipped = bytearray(data)
    for i in range(len(data) // 3, len(data) // 3 + 64):
        flipped[i] ^= 0xFF
    corrupt.write_bytes(bytes(flipped))
    _expect_error(corrupt)
    empty = tmp_path / "empty.npz"
    empty.write_bytes(b"")
    _expect_error(empty, "empty")
    _expect_error(tmp_path / "missing.npz", "not found")
    other = "hgcn" if vocab.kind == "orb" else "orb"
    _expect_error(path, f"is a '{vocab.kind}' vocabulary, expected '{other}'", expected_kind=other)
    for cls in (HGCNVocabulary, TreeVocabulary, KMeansVocabulary):
        if cls.kind != vocab.kind:
            with pytest.raises(VocabularyError):
                load_vocabulary(path, expected_kind=cls.kind)


def _rewrite(path, out, **changes):
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    for key, val in changes.items():
        if val is None:
            arrays.pop(key)
        else:
            arrays[key] = val
    atomic_save_npz(out, arrays)
    return out


def test_header_and_content_checks(saved, tmp_path):
    vocab, path = saved
    _expect_error(_rewrite(path, tmp_path / "v.npz", _format_version=np.array(FORMAT_VERSION + 1)),
                  f"version {FORMAT_VERSION + 1} is not supported")
    _expect_error(_rewrite(path, tmp_path / "m.npz", _magic=np.array("something else")), "not an orbslam_hgcn")
    _expect_error(_rewrite(path, tmp_path / "k.npz", _kind=np.array("sift")), "unknown vocabulary kind")
    _expect_error(_rewrite(path, tmp_path / "i.npz", idf=np.zeros(0, np.float32)), "empty or corrupt")
    key = "centres" if vocab.kind == "orb" else "centroids"
    _expect_error(_rewrite(path, tmp_path / "c.npz", **{key: None}), "corrupt vocabulary")
    plain = tmp_path / "plain.npz"
    np.savez(plain, a=np.arange(3))
    _expect_error(plain, "not an orbslam_hgcn")


def test_interrupted_save_leaves_no_file(tmp_path, monkeypatch):
    vocab = vf.small_orb_vocab()
    target = tmp_path / "v.npz"

    def boom(fh, **arrays):
        fh.write(b"partial")
        raise KeyboardInterrupt

    monkeypatch.setattr(np, "savez_compressed", boom)
    with pytest.raises(KeyboardInterrupt):
        vocab.save(target)
    assert list(tmp_path.iterdir()) == []


def test_cli_train_info_and_interrupt(tmp_path, monkeypatch, capsys):
    out = tmp_path / "voc.npz"
    images = str(vf.tum_rgb())
    assert cli.main(["vocab", "train", "--kind", "orb", "--images", images, "--max-images", "3",
                     "--levels", "2", "--out", str(out)]) == 0
    assert out.is_file() and not (tmp_path / "voc.npz.descriptors.npz").exists()
    assert cli.main(["vocab", "info", str(out)]) == 0
    text = capsys.readouterr().out
    assert "kind:            orb" in text and "training images: 3" in text and images in text
    km = tmp_path / "km.npz"
    assert cli.main(["vocab", "train", "--kind", "kmeans", "--images", images, "--max-images", "4",
                     "--words", "64", "--out", str(km)]) == 0
    back = load_vocabulary(km)
    assert back.kind == "kmeans" and back.n_words == 64
    assert cli.main(["vocab", "info", str(km)]) == 0
    text = capsys.readouterr().out
    assert "kind:            kmeans" in text and "search_exactness: 1.0" in text and "kmeans_seconds" in text
    # Ctrl-C during training: exit 130, no vocabulary, the descriptor cache kept for resuming.
    out2 = tmp_path / "voc2.npz"

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(train_mod, "train_vocabulary", interrupted)
    assert cli.main(["vocab", "train", "--kind", "orb", "--images", images, "--max-images", "3",
                     "--out", str(out2)]) == 130
    assert not out2.exists() and (tmp_path / "voc2.npz.descriptors.npz").is_file()
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []
    # Errors are one line and exit 2.
    assert cli.main(["vocab", "info", str(tmp_path / "nope.npz")]) == 2
    assert "vocabulary file not found" in capsys.readouterr().err


def test_zip_member_crc_is_checked(tmp_path):
    vocab = vf.small_orb_vocab()
    path = tmp_path / "v.npz"
    vocab.save(path)
    with zipfile.ZipFile(path) as z:
        info = z.getinfo("centres.npy")
        offset = info.header_offset + 30 + len(info.filename) + len(info.extra) + info.compress_size // 2
    data = bytearray(path.read_bytes())
    data[offset] ^= 0x55
    path.write_bytes(bytes(data))
    _expect_error(path)


@pytest.mark.parametrize("name", ["orb", "hgcn", "kmeans", "orb10k"])
def test_shipped_vocabularies(name):
    from orbslam_hgcn.vocabulary.loading import SHIPPED

    path = SHIPPED[name]
    assert path.is_file() and path.stat().st_size < 50e6
    vocab = load_vocabulary(name)
    meta = vocab.metadata
    kind = "orb" if name == "orb10k" else name
    assert vocab.kind == kind and meta.n_words == vocab.n_words >= 4000
    # Trained on the real photographs less the held-out ones, which the metadata names.
    assert meta.trained_on.startswith("2153 real photographs of shared/data/real_photos")
    assert "held out: camvid from #560, icdar2015 from #400" in meta.trained_on
    assert meta.n_images == 2153 and meta.n_descriptors >= 2_000_000
    assert meta.stats["role"]
    bow, fv = vocab.transform(vf.descriptors("tum", 0))
    assert len(bow) > 100 and fv.n_features() > 500
    if name == "hgcn":  # words by its network, as its training measured
        assert vocab.network is not None and vocab.assignment == "network"
        assert meta.stats["runtime_word_agreement"] >= 0.9


def test_shipped_hgcn_and_kmeans_are_the_same_size():
    """The ablation pair: the k-means vocabulary is the HGCN vocabulary's seed k-means at its
    word count, and the ORB tree of about that size is there to compare with."""
    hgcn, km, tree = (load_vocabulary(n) for n in ("hgcn", "kmeans", "orb10k"))
    assert km.n_words == hgcn.n_words and km.pca.dim == hgcn.pca.dim
    assert tree.metadata.params["levels"] == 4 and 5000 <= tree.n_words <= 10_000
    for meta in (km.metadata, tree.metadata):  # the same training recipe
        assert meta.trained_on == hgcn.metadata.trained_on and meta.n_images == hgcn.metadata.n_images
        assert meta.n_descriptors == hgcn.metadata.n_descriptors


def test_inverted_file_search_of_large_flat_vocabularies(monkeypatch):
    """Above FLAT_MAX_WORDS words the search goes through an inverted file: probing every
    list gives the exact nearest word, probing one list mostly does."""
    from orbslam_hgcn.vocabulary import flat

    monkeypatch.setattr(flat, "FLAT_MAX_WORDS", 32)
    desc, img = vf.training_set()
    vocab = flat.train_kmeans_vocabulary(desc, img, vf.SMALL_HGCN, progress=False)
    assert len(vocab.ivf_centroids) == int(4 * np.sqrt(vf.SMALL_HGCN.n_words))
    q = vf.descriptors("tum", 0)
    x = vocab.project(q)
    brute = ((x[:, None, :] - vocab.centroids[None]) ** 2).sum(-1).argmin(1)
    vocab.nprobe = len(vocab.ivf_centroids)
    np.testing.assert_array_equal(vocab.transform_words(q), brute)
    vocab.nprobe = 1
    one = vocab.transform_words(q)
    assert 0.3 < np.mean(one == brute) < 1.0


def test_version1_hgcn_file_reads_by_centroid(tmp_path):
    """A format-1 HGCN file (no network) loads, finds words by nearest class-mean centroid,
    and cannot be switched to the network."""
    vocab = vf.small_hgcn_vocab()
    path = tmp_path / "v2.npz"
    vocab.save(path)
    with np.load(path) as z:
        drop = [k for k in z.files if k.startswith("net_") or k in ("prototypes", "assignment")]
    assert "prototypes" in drop and "net_w0" in drop
    v1 = _rewrite(path, tmp_path / "v1.npz", _format_version=np.array(1), **{k: None for k in drop})
    back = load_vocabulary(v1)
    assert back.network is None and back.assignment == "centroid"
    desc = vf.descriptors("tum", 0)
    x = back.project(desc)
    brute = ((x[:, None, :] - back.centroids[None]) ** 2).sum(-1).argmin(1)
    np.testing.assert_array_equal(back.transform_words(desc), brute)  # exact search below 16384 words
    with pytest.raises(ValueError, match="no network"):
        back.assignment = "network"


def test_config_validation(tmp_path):
    from orbslam_hgcn.config import HgcnTrainConfig, VocabularyConfig
    from orbslam_hgcn.errors import ConfigError

    with pytest.raises(ConfigError, match="vocabulary.kind"):
        VocabularyConfig(kind="sift")
    with pytest.raises(ConfigError, match="label_fraction"):
        HgcnTrainConfig(label_fraction=0.0)
    bad = tmp_path / "train.yaml"
    bad.write_text("hgcn:\n  n_wrods: 100\n")
    assert cli.main(["vocab", "train", "--kind", "hgcn", "--images", str(vf.tum_rgb()), "--out",
                     str(tmp_path / "x.npz"), "--config", str(bad)]) == 2


def test_image_sources(tmp_path):
    import shutil

    from orbslam_hgcn.errors import DatasetError
    from orbslam_hgcn.vocabulary.training.train import open_image_source, select_images

    nested = tmp_path / "a" / "b"
    nested.mkdir(parents=True)
    frames = sorted(vf.tum_rgb().glob("*.png"))[:3]
    shutil.copy(frames[0], tmp_path / "a" / "x.png")
    shutil.copy(frames[1], nested / "y.png")
    src = open_image_source(tmp_path)  # a plain folder: images found recursively
    assert src.n == 2 and src.load(1).ndim == 2 and src.load(1).dtype == np.uint8
    tum = open_image_source(vf.tum_rgb().parent)  # a TUM sequence through the dataset reader
    assert tum.n == len(list(vf.tum_rgb().glob("*.png"))) and "(tum)" in tum.name
    # 21 images, 5 evenly spread: items 0, 5, 10, 15, 20.
    assert select_images([src, tum], 5) == [(0, 0), (1, 3), (1, 8), (1, 13), (1, 18)]
    (tmp_path / "notes.txt").write_text("x")
    for bad in (tmp_path / "missing", tmp_path / "notes.txt"):
        with pytest.raises(DatasetError, match=str(bad)):
            open_image_source(bad)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(DatasetError, match="no images found"):
        open_image_source(empty)


def test_shipped_flat_vocabularies_name_their_arm_and_the_run_default_is_the_winner():
    """The shipped k-means and HGCN files name their arm of the keyframe-word ablation; the
    k-means file says it is run's default and which ablation chose it; ``run`` without --vocab
    opens the arm-A0 file, the one no other arm beat."""
    from orbslam_hgcn.app.run import DEFAULT_VOCAB, open_vocabulary

    arms = {name: load_vocabulary(name).metadata for name in ("kmeans", "hgcn")}
    assert arms["kmeans"].params["arm"] == "A0" and arms["hgcn"].params["arm"] == "A1"
    assert "default vocabulary of run" in arms["kmeans"].stats["role"]
    assert "bench_track_words.py" in arms["kmeans"].stats["role"] and "(A0)" in arms["kmeans"].stats["role"]
    assert "arm A1" in arms["hgcn"].stats["role"]
    default = open_vocabulary(None, loop_closing=True)
    assert DEFAULT_VOCAB == "kmeans" and default.metadata.params["arm"] == "A0"

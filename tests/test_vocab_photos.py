"""Vocabularies from real photographs: the photo folder's sources and held-out part, the
memory check `vocab train` makes before it starts, and what the shipped files say they
were trained on."""

import subprocess
import sys

import cv2
import numpy as np
import pytest

from orbslam_hgcn.errors import DatasetError, OrbslamError
from orbslam_hgcn.vocabulary import load_vocabulary
from orbslam_hgcn.vocabulary.loading import SHIPPED
from orbslam_hgcn.vocabulary.training import photos
from orbslam_hgcn.vocabulary.training.train import train_from_images, training_memory_bytes


def _photo_folder(tmp_path, counts):
    rng = np.random.default_rng(0)
    folder = tmp_path / "photos"
    folder.mkdir()
    for source, n in counts.items():
        for i in range(n):
            img = (rng.random((60, 80)) * 255).astype(np.uint8)
            assert cv2.imwrite(str(folder / f"{source}_{i:04d}.jpg"), img)
    (folder / "README.md").write_text("attribution\n")
    return folder


def test_photo_sources_split_by_prefix_and_hold_out_the_tail_of_the_video_sources(tmp_path):
    first_held = photos.HOLDOUT["camvid"]
    folder = _photo_folder(tmp_path, {"camvid": first_held + 3, "urban_scenes": 4, "imagenet_sample": 2})
    train = photos.photo_files(folder, "train")
    held = photos.photo_files(folder, "heldout")
    every = photos.photo_files(folder, "all")
    assert sorted(train) == ["camvid", "imagenet_sample", "urban_scenes"]
    assert len(train["camvid"]) == first_held and len(held["camvid"]) == 3 and list(held) == ["camvid"]
    assert train["camvid"][-1].name == f"camvid_{first_held - 1:04d}.jpg"
    assert held["camvid"][0].name == f"camvid_{first_held:04d}.jpg"
    assert not {f for v in train.values() for f in v} & {f for v in held.values() for f in v}
    assert sum(len(v) for v in every.values()) == first_held + 3 + 4 + 2
    sources = photos.photo_sources(folder, "train")
    assert [s.name for s in sources] == ["real_photos/camvid", "real_photos/imagenet_sample", "real_photos/urban_scenes"]
    assert sources[2].load(0).shape == (60, 80)
    line = photos.describe(folder, "train")
    assert f"{first_held + 6} real photographs" in line and "held out: camvid from #560" in line
    with pytest.raises(DatasetError):
        photos.photo_files(tmp_path / "missing")
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "notes.txt").write_text("no photo here\n")
    with pytest.raises(DatasetError, match="no photos"):
        photos.photo_files(empty)


def test_vocab_train_checks_memory_before_it_extracts_anything(tmp_path, monkeypatch):
    folder = _photo_folder(tmp_path, {"urban_scenes": 3})
    need = training_memory_bytes("hgcn", 3, 1000)
    assert need > training_memory_bytes("orb", 3, 1000) > training_memory_bytes("orb", 2, 1000)
    monkeypatch.setenv("ORBSLAM_HGCN_MEMORY_LIMIT_MB", str(need / 2**20 / 2))
    out = tmp_path / "v.npz"
    with pytest.raises(OrbslamError, match="--max-images"):
        train_from_images("hgcn", [folder], out, progress=False)
    assert not out.exists() and not (tmp_path / "v.npz.descriptors.npz").exists()
    # The command line: status 2, one message, no traceback.
    proc = subprocess.run([sys.executable, "-m", "orbslam_hgcn", "vocab", "train", "--kind", "orb", "--images",
                           str(folder), "--out", str(out)], capture_output=True, text=True, timeout=300,
                          env={**__import__("os").environ, "ORBSLAM_HGCN_MEMORY_LIMIT_MB": "1"})
    assert proc.returncode == 2, proc.stderr
    assert "needs about" in proc.stderr and "Traceback" not in proc.stderr


@pytest.mark.parametrize("name", ["orb", "orb10k", "kmeans", "hgcn", "hgcn_graph", "hgcn_graph_mean"])
def test_every_shipped_vocabulary_was_trained_on_real_photographs_only(name):
    vocab = load_vocabulary(SHIPPED[name])
    said = vocab.metadata.trained_on
    assert "real photographs of shared/data/real_photos" in said, said
    assert "synthetic" not in said and "render" not in said.replace("no render", "")
    assert "KITTI" not in said and "TUM" not in said and "EuRoC" not in said
    assert vocab.metadata.n_images >= 2000
    if name == "orb":  # ORB-SLAM's ORBvoc shape: k = 10, L = 6, most of a million words
        assert vocab.metadata.params["k"] == 10 and vocab.levels == 6
        assert vocab.n_words > 500_000

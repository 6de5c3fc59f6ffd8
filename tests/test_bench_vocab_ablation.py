"""The vocabulary ablation bench's causal track-mean words on hand-made inputs with known
answers: the window, causality and lone descriptors."""

import numpy as np
import pytest
from conftest import load_bench


@pytest.fixture(scope="module")
def va():
    return load_bench("bench_vocab_ablation")


class LineVocab:
    """Words of a 1-D PCA space: the descriptor's first value, word = its rounded value."""

    def project(self, desc):
        return np.asarray(desc, np.float64)[:, :1]

    def words_of_points(self, x):
        return np.rint(np.asarray(x)[:, 0]).astype(np.int32)


def test_track_mean_words_window_causality_and_lone_descriptors(va):
    # Four images of two descriptors; track 7 runs through all four (values 0, 2, 4, 9), track
    # 8 is in images 2 and 3 only; each image's second descriptor in images 0, 1 has no track.
    desc = [np.array([[0.0], [5.0]]), np.array([[2.0], [6.0]]), np.array([[4.0], [10.0]]),
            np.array([[9.0], [12.0]])]
    tracks = np.array([7, -1, 7, -1, 7, 8, 7, 8])
    v = LineVocab()
    lone = [v.words_of_points(v.project(d)) for d in desc]
    words = va.causal_track_mean_words(v, desc, lone, tracks, window=3)
    assert words[0].tolist() == [0, 5]  # a track's first member has no mate yet: its own word
    assert words[1].tolist() == [1, 6]  # mean of 0 and 2; the untracked one keeps its word
    assert words[2].tolist() == [2, 10]  # mean of 0, 2, 4; track 8 starts here
    assert words[3].tolist() == [5, 11]  # window 3: 2, 4, 9 (not 0) -> 5; track 8: 10, 12 -> 11
    # Causality: an image's words do not change when later images are added.
    short = va.causal_track_mean_words(v, desc[:2], lone[:2], tracks[:4], window=3)
    assert [w.tolist() for w in short] == [w.tolist() for w in words[:2]]
    # Window 1: every descriptor alone, the lone words.
    alone = va.causal_track_mean_words(v, desc, lone, tracks, window=1)
    assert [w.tolist() for w in alone] == [[0, 5], [2, 6], [4, 10], [9, 12]]
    assert [w.tolist() for w in lone] == [[0, 5], [2, 6], [4, 10], [9, 12]]  # the lone words are not changed


def test_paired_mean_interval_and_wins(va):
    # Differences 0.01, 0.02, 0.03 (1, 2, 3 points): mean +2.0, every resample inside [1, 3].
    txt = va.paired([0.01, 0.02, 0.03])
    mean, rest = txt.split(" [")
    lo, hi = (float(x) for x in rest.split("]")[0].split(", "))
    assert mean == "mean +2.0" and 1.0 <= lo < 2.0 < hi <= 3.0 and txt.endswith("3/0")
    assert va.paired([0.0, -0.05, 0.05]).endswith("1/1")

"""DBoW2 text vocabularies (ORB-SLAM's ORBvoc.txt): export, import, the words they give
(checked against a plain re-implementation of DBoW2's descent), malformed files and the CLI."""

import json

import numpy as np
import pytest
import vocab_fixtures as vf

from orbslam_hgcn.cli import main
from orbslam_hgcn.errors import VocabularyError
from orbslam_hgcn.vocabulary import dbow2, load_vocabulary
from orbslam_hgcn.vocabulary.loading import DEFAULT_FILES
from orbslam_hgcn.vocabulary.orb_tree import TreeVocabulary


# --- a plain DBoW2 reader and descent (TemplatedVocabulary::loadFromTextFile, transform) ---


def reference_words(text: str, desc: np.ndarray) -> tuple[np.ndarray, int]:
    """Words of ``desc`` as DBoW2 finds them, read straight off the text: node n is line
    n + 1, children in line order, leaves numbered in line order; descend to the child of
    smallest Hamming distance, keeping the first on a tie. Also returns how many ties the
    descent met."""
    lines = text.rstrip().split("\n")[1:]
    children: dict[int, list[int]] = {0: []}
    code, word = {}, {}
    for n, line in enumerate(lines, start=1):
        f = line.split()
        children.setdefault(int(f[0]), []).append(n)
        children.setdefault(n, [])
        code[n] = int.from_bytes(bytes(int(x) for x in f[2:34]), "little")
        if f[1] == "1":
            word[n] = len(word)
    out, ties = [], 0
    for row in desc:
        q = int.from_bytes(row.tobytes(), "little")
        node = 0
        while children[node]:
            dists = [(q ^ code[c]).bit_count() for c in children[node]]
            best = min(dists)
            ties += dists.count(best) > 1
            node = children[node][dists.index(best)]  # the first child at the smallest distance
        out.append(word[node])
    return np.array(out), ties


def random_desc(n: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (n, 32), dtype=np.uint8)


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """The shipped ORB tree, exported with the CLI and read back."""
    orig = load_vocabulary("orb")
    path = tmp_path_factory.mktemp("dbow2") / "ORBvoc.txt"
    assert main(["vocab", "export", "orb", "--format", "dbow2", "--out", str(path)]) == 0
    return orig, path, load_vocabulary(path)


# --- export / import round trip -------------------------------------------------------------


def test_round_trip_gives_the_same_words_weights_and_scores(exported):
    orig, path, back = exported
    assert isinstance(back, TreeVocabulary) and back.n_words == orig.n_words > 500_000
    np.testing.assert_array_equal(back.idf, orig.idf)  # bit for bit
    np.testing.assert_array_equal(back.parent, orig.parent)
    np.testing.assert_array_equal(back.centres[1:], orig.centres[1:])
    assert back.levels == orig.levels == 6 and back.metadata.params["k"] == 10
    frames = [vf.descriptors("tum", i) for i in (0, 1, 5, 12)]
    for desc in frames + [random_desc(3000)]:
        assert len(desc) > 500
        np.testing.assert_array_equal(back.transform_words(desc), orig.transform_words(desc))
    vecs = []
    for desc in frames:
        (b1, f1), (b2, f2) = orig.transform(desc), back.transform(desc)
        assert b1 == b2 and len(b1) > 100
        assert f1.keys() == f2.keys() and all(np.array_equal(f1[n], f2[n]) for n in f1)
        vecs.append((b1, b2))
    for (a1, a2) in vecs:
        for (c1, c2) in vecs:
            assert orig.score(a1, c1) == back.score(a2, c2)
    assert 0 < orig.score(vecs[0][0], vecs[1][0]) < 1


def test_exported_text_is_what_orbslam_reads(exported):
    orig, path, _ = exported
    text = path.read_text()
    lines = text.split("\n")
    assert lines[0] == "10 6  0 0"  # k L scoring(L1 = 0) weighting(TF-IDF = 0), as saveToTextFile writes it
    assert not text.endswith("\n")  # ORB-SLAM's reader would make a trailing empty line a node
    assert len(lines) == len(orig.parent)
    fields = [line.split() for line in lines[1:]]
    assert {len(f) for f in fields} == {35}
    leaf = np.array([f[1] == "1" for f in fields])
    np.testing.assert_array_equal(np.flatnonzero(leaf) + 1, orig.word_node)
    weights = np.array([float(f[34]) for f in fields])
    assert np.all(weights[~leaf] == 0)
    np.testing.assert_array_equal(weights[leaf].astype(np.float32), orig.idf)


def test_descent_matches_dbow2(exported):
    _, path, back = exported
    text = path.read_text()
    desc = np.concatenate([vf.descriptors("tum", 3)[:600], random_desc(600, seed=1)])
    want, ties = reference_words(text, desc)
    assert ties > 50  # the first-child rule on ties is exercised
    np.testing.assert_array_equal(back.transform_words(desc), want)


def test_detected_by_content_and_kind_checked(exported, tmp_path):
    _, path, back = exported
    other = tmp_path / "vocab.dbow"  # no .txt suffix: told by its first line
    other.write_bytes(path.read_bytes())
    assert dbow2.is_dbow2_text(other) and not dbow2.is_dbow2_text(DEFAULT_FILES["orb"])
    assert load_vocabulary(other).n_words == back.n_words
    assert load_vocabulary(path, expected_kind="orb").n_words == back.n_words
    with pytest.raises(VocabularyError, match="expected 'hgcn'"):
        load_vocabulary(path, expected_kind="hgcn")


# --- a tiny hand-written file -----------------------------------------------------------------

Z, F = [0] * 32, [255] * 32
A, B = Z, F
A0, A1 = [15] + Z[1:], [0, 15] + Z[2:]
B0, B1 = [240] + F[1:], [255, 240] + F[2:]


def node_line(parent, leaf, desc, weight):
    return " ".join(str(v) for v in [parent, leaf, *desc]) + f"  {weight}"


# k=2, L=2. Node 1 (A) and node 2 (B) under the root; their children interleave in the file,
# so the leaves (words, in line order) are node 3 -> w0, 4 -> w1, 5 -> w2, 6 -> w3.
TINY_LINES = [
    "2 2  0 0",
    node_line(0, 0, A, 0),  # line 2: node 1
    node_line(0, 0, B, 0),  # line 3: node 2
    node_line(1, 1, A0, 1.5),  # line 4: node 3, word 0
    node_line(2, 1, B0, 0.5),  # line 5: node 4, word 1
    node_line(1, 1, A1, 2),  # line 6: node 5, word 2
    node_line(2, 1, B1, 0),  # line 7: node 6, word 3 (stopped: weight 0)
]
TINY = "\n".join(TINY_LINES) + "\n"


def queries() -> np.ndarray:
    q = np.zeros((6, 32), np.uint8)
    q[1, 1] = 15  # A, then A1 (distance 0 against 8)
    q[2] = 255  # B, then B0 and B1 tie at 4: the first (B0)
    q[3] = 255
    q[3, 1] = 240  # B, then B1
    q[4, :16] = 255  # 128 bits: A and B tie, so A; then A0 and A1 tie at 124: A0
    q[5, :16] = 255
    q[5, 16] = 1  # 129 bits: B; B0 and B1 tie at 131: B0
    return q  # q[0] = zeros: A, then A0 and A1 tie at 4: A0


def test_tiny_file_words_by_hand(tmp_path):
    path = tmp_path / "tiny.txt"
    path.write_text(TINY)
    vocab = load_vocabulary(path)
    assert vocab.n_words == 4 and vocab.levels == 2
    np.testing.assert_array_equal(vocab.idf, [1.5, 0.5, 2.0, 0.0])
    q = queries()
    np.testing.assert_array_equal(vocab.transform_words(q), [0, 2, 1, 3, 0, 1])
    np.testing.assert_array_equal(reference_words(TINY, q)[0], [0, 2, 1, 3, 0, 1])
    bow, fv = vocab.transform(q[:4], levels_up=1)  # words 0, 2, 1, 3; word 3 weighs 0
    assert bow.to_dict() == pytest.approx({0: 1.5 / 4, 1: 0.5 / 4, 2: 2.0 / 4})
    assert {n: v.tolist() for n, v in fv.items()} == {1: [0, 1], 2: [2]}  # nodes at depth L - 1 = 1
    a, b = vocab.bow(q[[0, 1]]), vocab.bow(q[[0, 2]])  # {w0: 1.5, w2: 2} and {w0: 1.5, w1: 0.5}
    assert vocab.score(a, b) == pytest.approx(1.5 / 3.5)


def test_tiny_file_layout_variants(tmp_path):
    """CRLF line ends, tabs, extra spaces and trailing blank lines read the same; a leaf
    above the last level (DBoW2 stops splitting small clusters) is a word of its own."""
    path = tmp_path / "crlf.txt"
    path.write_bytes(("\r\n".join(line.replace(" ", "\t  ", 3) for line in TINY_LINES) + "\r\n\r\n\n").encode())
    np.testing.assert_array_equal(load_vocabulary(path).transform_words(queries()), [0, 2, 1, 3, 0, 1])
    shallow = "\n".join([
        "2 2 0 0",
        node_line(0, 0, A, 0),  # node 1
        node_line(0, 1, B, 0.5),  # node 2: a leaf at depth 1, word 0
        node_line(1, 1, A0, 1.5),  # node 3, word 1
        node_line(1, 1, A1, 2.0),  # node 4, word 2
    ])
    path = tmp_path / "shallow.txt"
    path.write_text(shallow)
    vocab = load_vocabulary(path)
    q = queries()[[0, 1, 2]]
    np.testing.assert_array_equal(vocab.transform_words(q), [1, 2, 0])
    np.testing.assert_array_equal(reference_words(shallow, q)[0], [1, 2, 0])
    np.testing.assert_array_equal(vocab.word_nodes(np.arange(3), 1), [2, 1, 1])


def test_write_then_read_tiny_file(tmp_path):
    src = tmp_path / "tiny.txt"
    src.write_text(TINY)
    vocab = load_vocabulary(src)
    out = dbow2.write_dbow2_text(vocab, tmp_path / "out.txt", progress=False)
    lines = out.read_text().split("\n")
    assert lines[0] == "2 2  0 0" and lines[3].split()[-1] == "1.5" and lines[2].split()[-1] == "0"
    assert [line.split() for line in lines] == [line.split() for line in TINY_LINES]


# --- malformed files --------------------------------------------------------------------------


def _replace(line_no, old, new):
    def edit(lines):
        lines[line_no - 1] = lines[line_no - 1].replace(old, new, 1) if old else new
        return "\n".join(lines) + "\n"
    return edit


def _field(line_no, index, value):
    def edit(lines):
        f = lines[line_no - 1].split()
        f[index] = value
        lines[line_no - 1] = " ".join(f)
        return "\n".join(lines) + "\n"
    return edit


MALFORMED = {
    "empty file": (lambda lines: "", 1, "empty file"),
    "blank file": (lambda lines: "\n \n", 1, "empty file"),
    "header only": (lambda lines: lines[0] + "\n", 2, "no nodes"),
    "header with 3 fields": (_replace(1, None, "2 2 0"), 1, "bad header"),
    "header not numbers": (_replace(1, None, "k L scoring weighting"), 1, "bad header"),
    "binary file": (lambda lines: "PK\x03\x04\x00garbage\n" + "\n".join(lines[1:]), 1, "bad header"),
    "scoring code out of range": (_replace(1, None, "2 2 9 0"), 1, "scoring = 9"),
    "k out of range": (_replace(1, None, "25 2 0 0"), 1, "k = 25"),
    "a field missing": (_field(5, 34, ""), 5, "found 34"),
    "an extra field": (_replace(3, None, TINY_LINES[2] + " 7"), 3, "found 36"),
    "byte 256": (_field(6, 9, "256"), 6, "d7 .* is 256, outside 0..255"),
    "byte -1": (_field(4, 2, "-1"), 4, "d0 .* is -1"),
    "byte not a number": (_field(4, 3, "x7"), 4, "d1.*not an integer"),
    "byte with a fraction": (_field(4, 3, "7.5"), 4, "not an integer"),
    "huge byte": (_field(4, 3, "99999999999"), 4, "outside 0..255"),
    "parent beyond the node": (_field(3, 0, "5"), 3, "parent id 5 is out of range"),
    "parent is the node": (_field(4, 0, "3"), 4, "parent id 3 is out of range"),
    "negative parent": (_field(2, 0, "-1"), 2, "parent id -1"),
    "is_leaf 2": (_field(4, 1, "2"), 4, "is_leaf is 2"),
    "weight not a number": (_field(5, 34, "abc"), 5, "weight.*not a number"),
    "weight nan": (_field(5, 34, "nan"), 5, "weight"),
    "negative weight": (_field(5, 34, "-0.5"), 5, "weight '-0.5' is not a finite number >= 0"),
    "inner node with a weight": (_field(3, 34, "0.7"), 3, "inner node .* has weight '0.7'"),
    "blank line inside": (lambda lines: "\n".join(lines[:3] + [""] + lines[3:]) + "\n", 4, "blank line"),
    "truncated mid-line": (lambda lines: TINY[: TINY.index(lines[6]) + 30], 7, "found [0-9]+; is the file truncated"),
    "truncated at a line end": (lambda lines: "\n".join(lines[:4]) + "\n", 3, "node 2 is an inner node .* without "
                                "children; is the file truncated"),
    "no leaves": (lambda lines: "\n".join(lines[:3]) + "\n", 3, "no leaves"),
    "leaf with children": (_field(2, 1, "1"), 2, "node 1 is flagged as a leaf .* node 3 \\(line 4\\)"),
}


@pytest.mark.parametrize("block_bytes", [8 << 20, 60], ids=["one block", "many blocks"])
@pytest.mark.parametrize("case", list(MALFORMED))
def test_malformed_file_names_the_line(case, block_bytes, tmp_path, monkeypatch):
    monkeypatch.setattr(dbow2, "_BLOCK_BYTES", block_bytes)  # small blocks: line numbers across blocks
    edit, line, match = MALFORMED[case]
    path = tmp_path / "bad.txt"
    path.write_text(edit(list(TINY_LINES)))
    with pytest.raises(VocabularyError, match=match) as err:
        load_vocabulary(path)
    assert str(err.value).startswith(f"{path}:{line}: "), str(err.value)


def test_errors_deep_in_a_long_file_name_their_line(tmp_path, monkeypatch):
    monkeypatch.setattr(dbow2, "_BLOCK_BYTES", 4096)
    lines = ["10 2 0 0"] + [node_line(0, 0, Z, 0) for _ in range(10)]
    lines += [node_line(1 + i // 100, 1, random_desc(1, i)[0], 1.0) for i in range(1000)]
    good = "\n".join(lines)
    path = tmp_path / "long.txt"
    path.write_text(good)
    assert load_vocabulary(path).n_words == 1000
    for line_no, value, match in ((700, "x", "not an integer"), (901, "300", "outside 0..255")):
        bad = list(lines)
        f = bad[line_no - 1].split()
        f[5] = value
        bad[line_no - 1] = " ".join(f)
        path.write_text("\n".join(bad))
        with pytest.raises(VocabularyError, match=match) as err:
            load_vocabulary(path)
        assert str(err.value).startswith(f"{path}:{line_no}: ")


def test_export_refuses_what_dbow2_cannot_hold(tmp_path):
    hgcn = tmp_path / "h.txt"
    with pytest.raises(VocabularyError, match="only an ORB vocabulary tree"):
        dbow2.write_dbow2_text(load_vocabulary("hgcn"), hgcn, progress=False)
    src = tmp_path / "tiny.txt"
    src.write_text(TINY)
    vocab = load_vocabulary(src)
    vocab.metadata.params["k"] = 30
    with pytest.raises(VocabularyError, match="k <= 20"):
        dbow2.write_dbow2_text(vocab, tmp_path / "k30.txt", progress=False)
    assert not hgcn.exists() and not (tmp_path / "k30.txt").exists()


# --- the command line -------------------------------------------------------------------------


@pytest.fixture(scope="module")
def synth40(tmp_path_factory):
    """40 frames of the real fr3 camera path replayed in a synthetic room (initialises at
    about frame 22)."""
    from orbslam_hgcn.synth.sequence import SynthOptions, render_sequence

    out = tmp_path_factory.mktemp("synth40")
    return render_sequence(out, SynthOptions(trajectory="replay", gt=str(vf.REPLAY_GT), frames=40), progress=False)


def test_cli_run_with_exported_vocabulary(exported, synth40, tmp_path, capsys):
    """A sequential run with the exported file equals the run with the .npz it came from
    (local mapping pairs features for triangulation by the vocabulary's feature vectors)."""
    _, path, _ = exported
    results = {}
    for name, vocab in (("npz", "orb"), ("txt", str(path))):
        out = tmp_path / name
        rc = main(["run", str(synth40), "--dataset", "tum", "--out", str(out), "--vocab", vocab, "--sequential",
                   "--no-progress"])
        assert rc == 0, capsys.readouterr().err
        stats = json.loads((out / "stats.json").read_text())
        results[name] = (stats, (out / "KeyFrameTrajectory.txt").read_text())
    (s_npz, kf_npz), (s_txt, kf_txt) = results["npz"], results["txt"]
    assert dbow2.TRAINED_ON in s_txt["vocabulary"] and dbow2.TRAINED_ON not in s_npz["vocabulary"]
    assert s_txt["keyframes"] >= 3 and s_txt["map_points"] > 100
    assert (s_txt["keyframes"], s_txt["map_points"]) == (s_npz["keyframes"], s_npz["map_points"])
    assert kf_txt == kf_npz and len([ln for ln in kf_txt.splitlines() if ln[:1].isdigit()]) == s_txt["keyframes"]


@pytest.mark.parametrize("command", ["export", "run", "info"])
def test_cli_malformed_file_one_line_exit_2(command, tmp_path, capsys):
    bad = tmp_path / "bad.txt"
    bad.write_text(_field(6, 9, "256")(list(TINY_LINES)))
    args = {
        "export": ["vocab", "export", str(bad), "--out", str(tmp_path / "o.txt")],
        "info": ["vocab", "info", str(bad)],
        "run": ["run", str(vf.tum_rgb().parent), "--out", str(tmp_path / "o"), "--vocab", str(bad), "--no-progress"],
    }[command]
    rc = main(args)
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2
    assert len(err) == 1 and f"{bad}:6: " in err[0] and "outside 0..255" in err[0], err


def test_cli_export_of_hgcn_is_refused(tmp_path, capsys):
    rc = main(["vocab", "export", "hgcn", "--out", str(tmp_path / "h.txt")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "only an ORB vocabulary tree" in err[0]

"""DBoW2 text vocabularies (ORB-SLAM's ``ORBvoc.txt``): reading them as an ORB tree, and
writing an ORB tree in that format.

The format is the one of ``TemplatedVocabulary::saveToTextFile`` / ``loadFromTextFile`` in
the DBoW2 copy that ORB-SLAM2 and ORB-SLAM3 ship (DBoW2: Galvez-Lopez & Tardos, "Bags of
binary words for fast place recognition in image sequences", T-RO 2012):

* line 1: ``k L scoring weighting`` (ints; ORB-SLAM reads 0 <= k <= 20, 1 <= L <= 10,
  scoring 0..5 and weighting 0..3, numbered as in :data:`SCORING` and :data:`WEIGHTING`);
* line n + 1, for every node n = 1..N but the root (node 0), in node-id order:
  ``parent is_leaf d0 d1 ... d31 weight``: the parent's node id (below n), 1 for a leaf
  (a word) and 0 for an inner node, the node's ORB descriptor as 32 decimal bytes
  (``FORB::toString``), and the word's IDF weight (0 for inner nodes).

The leaves, in the order their lines appear, are words 0..W-1; a node's children are the
nodes naming it as parent, in line order. A descriptor's word is found as DBoW2's
``transform`` finds it: from the root, step to the child at the smallest Hamming distance
(the first such child on a tie) until a leaf. :class:`TreeVocabulary` keeps exactly that
layout (node ids, children in id order, leaves in id order as words, ``np.argmin`` taking the
first minimum), so a file read here quantises as ORB-SLAM does.

Reading is vectorised (``np.loadtxt`` over blocks of lines, checks over whole arrays): an
``ORBvoc.txt``-sized file (1.1 M nodes, 146 MB) reads in a few seconds. Any malformed line
is a :class:`VocabularyError` naming the file and the line.
"""

from __future__ import annotations

import io
import logging
import math
import os
import re
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from orbslam_hgcn.errors import VocabularyError, where
from orbslam_hgcn.vocabulary.base import VocabularyMetadata
from orbslam_hgcn.vocabulary.orb_tree import TreeVocabulary

log = logging.getLogger(__name__)

# DBoW2's enums (BowVector.h): ScoringType and WeightingType, in their numeric order.
SCORING = ("L1", "L2", "chi-square", "KL", "Bhattacharyya", "dot-product")
WEIGHTING = ("tf-idf", "tf", "idf", "binary")
DESC_BYTES = 32  # FORB::L: bytes of an ORB descriptor
N_FIELDS = DESC_BYTES + 3  # parent, is_leaf, 32 bytes, weight
MAX_K, MAX_L = 20, 10  # the largest k and L ORB-SLAM's loadFromTextFile accepts
TRAINED_ON = "DBoW2 text vocabulary"

_ROW = np.dtype([("ints", "<i4", (N_FIELDS - 1,)), ("weight", "<f8")])
_BLOCK_BYTES = 8 << 20  # bytes parsed per np.loadtxt call (bounds temporary memory)
_PROGRESS_BYTES = 32 << 20  # files this large show a progress bar
_HEADER = re.compile(rb"\s*[+-]?\d+\s+[+-]?\d+\s+[+-]?\d+\s+[+-]?\d+\s*")
_INT = re.compile(rb"[+-]?\d+")
_FLOAT = re.compile(rb"[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?")
_ZIP_MAGIC = b"PK\x03\x04"


def is_dbow2_text(path: str | Path) -> bool:
    """Whether ``path`` is to be read as a DBoW2 text vocabulary: a ``.txt`` name, or a file
    whose first line is four integers (``k L scoring weighting``)."""
    path = Path(path)
    if path.suffix.lower() == ".txt":
        return True
    if not path.is_file():
        return False
    with open(path, "rb") as fh:
        head = fh.read(256)
    if head.startswith(_ZIP_MAGIC):
        return False
    return bool(_HEADER.fullmatch(head.split(b"\n", 1)[0]))


# --- reading ------------------------------------------------------------------------------


def read_dbow2_text(path: str | Path, progress: bool = True) -> TreeVocabulary:
    """Read a DBoW2 text vocabulary (e.g. ORB-SLAM's ``ORBvoc.txt``) as a TreeVocabulary.

    progress: show a progress bar for large files. Word ids, IDF weights and the descent of
    a descriptor follow DBoW2 (see the module docstring). Malformed input (bad header, a
    line with the wrong number of fields, a byte outside 0..255, a parent id that is not an
    earlier node, an inner node with a weight, a leaf with children, an inner node without
    any, a truncated or empty file, a tree without leaves) raises a VocabularyError naming
    the file and line.
    """
    path = Path(path)
    t0 = time.perf_counter()
    if not path.is_file():
        raise VocabularyError(f"{path}: vocabulary file not found")
    raw = path.read_bytes()
    if not raw or raw.isspace():
        raise VocabularyError(f"{where(path, 1)}: empty file; a DBoW2 vocabulary starts with 'k L scoring weighting'")
    nl = raw.find(b"\n")
    start = len(raw) if nl < 0 else nl + 1  # the node lines are raw[start:end]
    k, levels, scoring, weighting = _parse_header(raw[:start], path)
    end = len(raw)
    while end > start and raw[end - 1 : end].isspace():  # trailing blank lines are tolerated (ORB-SLAM
        end -= 1  # would read one more, garbage, node)
    if end == start:
        raise VocabularyError(f"{where(path, 2)}: no nodes after the header; the file is truncated")
    ints, weight = _parse_body(raw, start, end, path, progress and len(raw) >= _PROGRESS_BYTES)
    _check_values(ints, weight, raw, start, end, path)
    parent = np.concatenate([[-1], ints[:, 0]]).astype(np.int32)
    leaf = ints[:, 1] == 1
    _check_tree(parent, leaf, path)
    centres = np.zeros((len(parent), DESC_BYTES), np.uint8)  # the root has no descriptor
    centres[1:] = ints[:, 2:]
    idf = weight[leaf].astype(np.float32)
    if scoring != 0 or weighting not in (0, 1):
        log.warning("%s: DBoW2 scoring %s with %s weighting; this system weights TF-IDF and scores L1, so its "
                    "scores will differ from DBoW2's with these settings", path, SCORING[scoring], WEIGHTING[weighting])
    meta = VocabularyMetadata(
        kind="orb",
        n_words=int(len(idf)),
        descriptor_type="binary",
        descriptor_dim=DESC_BYTES,
        trained_on=TRAINED_ON,
        params={"k": k, "levels": levels, "scoring": SCORING[scoring], "weighting": WEIGHTING[weighting],
                "format": "dbow2-text"},
        stats={"nodes": int(len(parent))},
    )
    vocab = TreeVocabulary(parent, centres, idf, meta)
    log.info("read the DBoW2 vocabulary %s (k=%d, L=%d, %d nodes, %d words) in %.1f s", path, k, levels,
             len(parent), vocab.n_words, time.perf_counter() - t0)
    return vocab


def _parse_header(header: bytes, path: Path) -> tuple[int, int, int, int]:
    """k, L, scoring, weighting of line 1, checked as ORB-SLAM's loadFromTextFile checks them."""
    fields = header.split()
    if len(fields) != 4 or not all(_INT.fullmatch(f) for f in fields):
        shown = header[:60].decode("ascii", "replace").strip()
        raise VocabularyError(f"{where(path, 1)}: bad header {shown!r}; a DBoW2 text vocabulary starts with "
                              "four integers 'k L scoring weighting'")
    k, levels, scoring, weighting = (int(f) for f in fields)
    for name, value, lo, hi in (("k", k, 0, MAX_K), ("L", levels, 1, MAX_L), ("scoring", scoring, 0, len(SCORING) - 1),
                                ("weighting", weighting, 0, len(WEIGHTING) - 1)):
        if not lo <= value <= hi:
            raise VocabularyError(f"{where(path, 1)}: bad header: {name} = {value} is outside {lo}..{hi}")
    return k, levels, scoring, weighting


def _parse_body(raw: bytes, start: int, end: int, path: Path, progress: bool) -> tuple[np.ndarray, np.ndarray]:
    """(N, 34) int32 fields (parent, is_leaf, 32 bytes) and (N,) float64 weights of the N
    node lines ``raw[start:end]``, parsed block by block; a block that does not parse is
    searched line by line."""
    ints, weights = [], []
    first_line = 2  # file line number of the block's first line
    bar = tqdm(total=end - start, desc="reading DBoW2 vocabulary", unit="B", unit_scale=True, disable=not progress)
    while start < end:
        stop = raw.find(b"\n", min(start + _BLOCK_BYTES, end), end)
        stop = end if stop < 0 else stop + 1
        block = raw[start:stop]
        n_lines = block.count(b"\n") + (not block.endswith(b"\n"))
        try:
            rows = np.loadtxt(io.BytesIO(block), dtype=_ROW, comments=None, ndmin=1)
        except ValueError as exc:
            _raise_first_bad_line(block, first_line, path, str(exc))
        if len(rows) != n_lines:  # np.loadtxt skips blank lines; a node line may not be blank
            _raise_first_bad_line(block, first_line, path, "a blank line")
        ints.append(rows["ints"])
        weights.append(rows["weight"])
        first_line += n_lines
        bar.update(stop - start)
        start = stop
    bar.close()
    return np.concatenate(ints), np.concatenate(weights)


def _check_values(ints: np.ndarray, weight: np.ndarray, raw: bytes, start: int, end: int, path: Path) -> None:
    """Each line's fields in range (see :func:`_line_problem`), checked over whole arrays."""
    node = np.arange(1, len(ints) + 1)
    pid, leaf = ints[:, 0], ints[:, 1]
    bad = (pid < 0) | (pid >= node) | ((leaf != 0) & (leaf != 1))
    bad |= np.any(ints[:, 2:] & ~0xFF, axis=1)  # a byte outside 0..255
    bad |= ~np.isfinite(weight) | (weight < 0) | ((leaf == 0) & (weight != 0))
    if bad.any():
        row = int(np.argmax(bad))
        _raise_line(_nth_line(raw[start:end], row), row + 1, path)


def _check_tree(parent: np.ndarray, leaf: np.ndarray, path: Path) -> None:
    """Leaves flagged exactly where nodes have no children, and at least one leaf."""
    n = len(parent) - 1
    if not leaf.any():
        raise VocabularyError(f"{where(path, n + 1)}: the tree has no leaves (is_leaf, field 2, is 0 on every "
                              "line), so no words")
    has_children = np.bincount(parent[1:], minlength=n + 1)[1:] > 0
    wrong = leaf == has_children
    if wrong.any():
        node = int(np.argmax(wrong)) + 1
        if leaf[node - 1]:
            child = int(np.argmax(parent == node))
            msg = f"node {node} is flagged as a leaf (a word) but node {child} (line {child + 1}) names it as parent"
        else:
            msg = f"node {node} is an inner node (is_leaf 0) without children; is the file truncated?"
        raise VocabularyError(f"{where(path, node + 1)}: {msg}")


def _line_problem(line: bytes, node: int) -> str | None:
    """What is wrong with the line of node ``node`` (1-based), or None."""
    fields = line.split()
    if len(fields) != N_FIELDS:
        empty = " (a blank line)" if not fields else ""
        return (f"expected {N_FIELDS} fields 'parent is_leaf d0 .. d31 weight', found {len(fields)}{empty}; "
                "is the file truncated?")
    for i, f in enumerate(fields[:-1]):
        if not _INT.fullmatch(f):
            return f"field {i + 1} ({_field_name(i)}) is {_shown(f)}, not an integer"
    if not _FLOAT.fullmatch(fields[-1]):
        return f"field {N_FIELDS} (weight) is {_shown(fields[-1])}, not a number"
    pid, leaf = int(fields[0]), int(fields[1])
    if not 0 <= pid < node:
        return f"parent id {pid} is out of range: node {node} needs an earlier node 0..{node - 1} as parent"
    if leaf not in (0, 1):
        return f"is_leaf is {leaf}, not 0 or 1"
    for i, f in enumerate(fields[2:-1]):
        if not 0 <= int(f) <= 255:
            return f"descriptor byte d{i} (field {i + 3}) is {int(f)}, outside 0..255"
    weight = float(fields[-1])
    if not math.isfinite(weight) or weight < 0:
        return f"weight {_shown(fields[-1])} is not a finite number >= 0"
    if leaf == 0 and weight != 0:
        return f"an inner node (is_leaf 0) has weight {_shown(fields[-1])}; only leaves (words) carry weights"
    return None


def _field_name(i: int) -> str:
    return "parent" if i == 0 else "is_leaf" if i == 1 else f"descriptor byte d{i - 2}"


def _shown(field: bytes) -> str:
    return repr(field[:24].decode("ascii", "replace"))


def _raise_line(line: bytes, node: int, path: Path) -> None:
    problem = _line_problem(line, node) or "malformed line"
    raise VocabularyError(f"{where(path, node + 1)}: {problem}")


def _raise_first_bad_line(block: bytes, first_line: int, path: Path, detail: str) -> None:
    """Raise for the first malformed line of a block that np.loadtxt refused (``detail``)."""
    for i, line in enumerate(block.split(b"\n")[: block.count(b"\n") + (not block.endswith(b"\n"))]):
        node = first_line + i - 1
        problem = _line_problem(line, node)
        if problem:
            raise VocabularyError(f"{where(path, first_line + i)}: {problem}")
    raise VocabularyError(f"{where(path, first_line)}: malformed block of lines ({detail})")


def _nth_line(body: bytes, row: int) -> bytes:
    """Line ``row`` (0-based) of the node lines."""
    ends = np.flatnonzero(np.frombuffer(body, np.uint8) == ord("\n"))
    start = 0 if row == 0 else int(ends[row - 1]) + 1
    stop = int(ends[row]) if row < len(ends) else len(body)
    return body[start:stop]


# --- writing ------------------------------------------------------------------------------


def write_dbow2_text(vocab: TreeVocabulary, path: str | Path, progress: bool = True) -> Path:
    """Write an ORB tree as a DBoW2 text vocabulary that ORB-SLAM2/3 load (``ORBvoc.txt``).

    Nodes keep their ids (so words keep theirs); weights are the IDF weights, written so
    that reading them back as doubles and rounding to float32 gives them exactly. The header
    codes scoring and weighting as DBoW2 numbers them (L1 = 0, TF-IDF = 0, as the ORB tree
    scores and weights). The last line has no newline: ORB-SLAM's reader loops until
    end-of-file and would read a final empty line as one more (garbage) node. Written to a
    temporary file and renamed into place.
    """
    path = Path(path)
    t0 = time.perf_counter()
    if not isinstance(vocab, TreeVocabulary):
        raise VocabularyError(f"{path}: only an ORB vocabulary tree can be written in the DBoW2 format, "
                              f"not a {vocab.kind!r} vocabulary")
    if vocab.descriptor_type != "binary" or vocab.metadata.descriptor_dim != DESC_BYTES:
        raise VocabularyError(f"{path}: the DBoW2 ORB format holds {DESC_BYTES}-byte binary descriptors; this tree "
                              f"has {vocab.descriptor_type} descriptors of {vocab.metadata.descriptor_dim}")
    parent = vocab.parent
    m = len(parent)
    if m < 2 or parent[0] != -1 or not np.all((parent[1:] >= 0) & (parent[1:] < np.arange(1, m))):
        raise VocabularyError(f"{path}: the tree's nodes are not numbered parents first (root 0), as DBoW2 needs")
    params = vocab.metadata.params
    k, levels = int(params.get("k", vocab.children.shape[1])), int(vocab.levels)
    if not (0 <= k <= MAX_K and 1 <= levels <= MAX_L):
        raise VocabularyError(f"{path}: k = {k}, L = {levels}: ORB-SLAM reads DBoW2 trees with k <= {MAX_K} and "
                              f"1 <= L <= {MAX_L} only")
    scoring = SCORING.index(params["scoring"]) if params.get("scoring") in SCORING else 0
    weighting = WEIGHTING.index(params["weighting"]) if params.get("weighting") in WEIGHTING else 0
    is_leaf = vocab.node_word >= 0
    weight_text = np.full(m, b"0", dtype="S24")
    weight_text[vocab.word_node] = _float32_text(vocab.idf)

    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    step = 1 << 16
    try:
        with open(tmp, "wb") as fh:
            fh.write(f"{k} {levels}  {scoring} {weighting}\n".encode())
            for s in tqdm(range(1, m, step), desc="writing DBoW2 vocabulary", unit="block",
                          disable=not progress or m < 20 * step):
                e = min(m, s + step)
                text = _lines(parent[s:e], is_leaf[s:e], vocab.centres[s:e], weight_text[s:e])
                fh.write(text[:-1] if e == m else text)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    log.info("wrote the DBoW2 vocabulary %s (%d nodes, %d words) in %.1f s", path, m, vocab.n_words,
             time.perf_counter() - t0)
    return path


# Byte value -> its decimal text and a space, padded with NULs to 4 characters.
_BYTE_TEXT = np.zeros((256, 4), np.uint8)
for _v in range(256):
    _t = f"{_v} ".encode()
    _BYTE_TEXT[_v, : len(_t)] = np.frombuffer(_t, np.uint8)
del _v, _t


def _float32_text(values: np.ndarray) -> np.ndarray:
    """Text of float32 values that reads back (as a double, then rounded to float32) to the
    same value: whole numbers as integers (``0``, ``2``, as C++ streams write them), others in
    their shortest form, or the double's 17 digits where that would not read back."""
    values = np.asarray(values, np.float32)
    text = values.astype("S24")
    whole = (values == np.floor(values)) & (np.abs(values) < 1e15)
    text[whole] = values[whole].astype(np.int64).astype("S24")
    off = text.astype(np.float64).astype(np.float32) != values
    if off.any():
        text[off] = values[off].astype(np.float64).astype("S24")
    return text


def _lines(parent: np.ndarray, is_leaf: np.ndarray, centres: np.ndarray, weight_text: np.ndarray) -> bytes:
    """The text of a block of node lines, built as one NUL-padded byte table and then
    squeezed (every field is padded with NULs, which are then dropped)."""
    n = len(parent)

    def column(text: np.ndarray, sep: bytes) -> np.ndarray:
        width = text.dtype.itemsize
        out = np.zeros((n, width + 1), np.uint8)
        out[:, :width] = np.frombuffer(text.tobytes(), np.uint8).reshape(n, width)
        out[:, width] = ord(sep)
        return out

    table = np.concatenate([
        column(parent.astype("S11"), b" "),
        column(np.where(is_leaf, b"1", b"0").astype("S1"), b" "),
        _BYTE_TEXT[centres].reshape(n, 4 * DESC_BYTES),
        column(weight_text, b"\n"),
    ], axis=1).ravel()
    return table[table != 0].tobytes()

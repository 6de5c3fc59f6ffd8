"""Hamming distances of ORB descriptors and the selection steps shared by the matchers.

Thresholds and the rotation-consistency check follow ORB-SLAM's ORBmatcher (Mur-Artal,
Montiel & Tardos, T-RO 2015): TH_HIGH = 100 and TH_LOW = 50 bits, a 30-bin histogram of
orientation differences of which only the three largest bins survive.
"""

from __future__ import annotations

import logging

import numpy as np

from orbslam_hgcn.compiled import descriptor_words

log = logging.getLogger(__name__)

TH_HIGH = 100  # loose descriptor distance (tracking by projection)
TH_LOW = 50  # strict descriptor distance (initialisation, BoW, triangulation, fusion)
HISTO_LENGTH = 30  # bins of the rotation-consistency histogram

_CHUNK = 65536  # rows of A times rows of B per step of hamming_matrix (bounds its temporaries)


def hamming_pairs(desc_a: np.ndarray, desc_b: np.ndarray) -> np.ndarray:
    """(K,) int32 Hamming distances between row-aligned descriptors.

    desc_a, desc_b: (K, B) uint8 packed bits (B = 32 for ORB).
    """
    if len(desc_a) == 0:
        return np.zeros(0, dtype=np.int32)
    return np.bitwise_count(descriptor_words(desc_a) ^ descriptor_words(desc_b)).sum(axis=1, dtype=np.int32)


def hamming_matrix(desc_a: np.ndarray, desc_b: np.ndarray) -> np.ndarray:
    """(A, B) int32 Hamming distances between all rows of desc_a (A, L) and desc_b (B, L)
    uint8 packed bits: popcounts of the XOR of their 64-bit words, a block of rows of A at
    a time."""
    a64, b64 = descriptor_words(desc_a), descriptor_words(desc_b)
    out = np.empty((len(a64), len(b64)), np.int32)
    step = max(1, _CHUNK // max(len(b64), 1))
    for s in range(0, len(a64), step):
        out[s : s + step] = np.bitwise_count(a64[s : s + step, None, :] ^ b64[None]).sum(-1, dtype=np.int32)
    return out


def best_two_per_group(group: np.ndarray, dist: np.ndarray, n_groups: int) -> tuple[np.ndarray, ...]:
    """Best and second-best candidate of each group.

    group: (K,) int group (query) of each candidate; dist: (K,) its distance.
    Returns (best_pos, best_dist, second_pos, second_dist), each (n_groups,): positions
    index the candidate arrays (-1 where absent), distances are int64 with a large value
    (1 << 30) where absent. Ties keep the earliest candidate.
    """
    big = 1 << 30
    best_pos = np.full(n_groups, -1, dtype=np.int64)
    second_pos = np.full(n_groups, -1, dtype=np.int64)
    best = np.full(n_groups, big, dtype=np.int64)
    second = np.full(n_groups, big, dtype=np.int64)
    if len(group) == 0:
        return best_pos, best, second_pos, second
    group = np.asarray(group, dtype=np.int64)
    dist = np.asarray(dist, dtype=np.int64)
    order = np.lexsort((np.arange(len(group)), dist, group))
    g = group[order]
    idx = np.flatnonzero(np.concatenate([[True], g[1:] != g[:-1]]))
    best_pos[g[idx]] = order[idx]
    best[g[idx]] = dist[order[idx]]
    nxt = idx + 1
    has2 = nxt < len(order)
    has2[has2] &= g[nxt[has2]] == g[idx[has2]]
    second_pos[g[idx[has2]]] = order[nxt[has2]]
    second[g[idx[has2]]] = dist[order[nxt[has2]]]
    return best_pos, best, second_pos, second


def resolve_conflicts(query_to_target: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Keep, for each target matched by several queries, only the closest query.

    query_to_target: (M,) int target index or -1; dist: (M,) distance of each match.
    Returns the (M,) assignment with the losing queries set to -1 (ties: lowest query).
    """
    out = query_to_target.copy()
    q = np.flatnonzero(out >= 0)
    if len(q) == 0:
        return out
    order = q[np.lexsort((q, dist[q], out[q]))]
    t = out[order]
    dup = np.concatenate([[False], t[1:] == t[:-1]])
    out[order[dup]] = -1
    return out


def rotation_consistency(angle_diff_deg: np.ndarray, n_bins: int = HISTO_LENGTH) -> np.ndarray:
    """(K,) bool: matches whose orientation change falls in one of the 3 largest bins.

    angle_diff_deg: (K,) keypoint angle in the first image minus the angle in the second.
    ORB-SLAM's ComputeThreeMaxima: the second and third bins are kept only when they hold
    at least a tenth of the largest bin. (ORB-SLAM's code scales by 1/30 instead of
    30/360, so its bins are 30 degrees wide; here there are n_bins bins of 360/n_bins.)
    """
    k = len(angle_diff_deg)
    if k == 0:
        return np.zeros(0, dtype=bool)
    rot = np.mod(np.asarray(angle_diff_deg, dtype=np.float64), 360.0)
    # Bins centred on multiples of 360 / n_bins, so that "no rotation" is one bin.
    b = np.mod(np.round(rot * (n_bins / 360.0)).astype(np.int64), n_bins)
    counts = np.bincount(b, minlength=n_bins)
    top = np.argsort(-counts, kind="stable")[:3]
    keep_bin = np.zeros(n_bins, dtype=bool)
    keep_bin[top[0]] = True
    for j in top[1:]:
        if counts[j] >= 0.1 * counts[top[0]]:
            keep_bin[j] = True
    return keep_bin[b]


def apply_rotation_check(match: np.ndarray, angle_q: np.ndarray, angle_t: np.ndarray) -> np.ndarray:
    """Set to -1 the matches failing :func:`rotation_consistency`.

    match: (M,) target index per query or -1; angle_q: (M,) query keypoint angles in
    degrees; angle_t: (N,) target keypoint angles. Returns the filtered (M,) copy.
    """
    out = match.copy()
    q = np.flatnonzero(out >= 0)
    if len(q):
        ok = rotation_consistency(angle_q[q] - angle_t[out[q]])
        out[q[~ok]] = -1
    return out

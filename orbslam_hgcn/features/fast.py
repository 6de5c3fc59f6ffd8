"""FAST-9 corners with ORB-SLAM's per-cell thresholds, as compiled loops.

The segment test of Rosten & Drummond ("Machine learning for high-speed corner detection",
ECCV 2006): a pixel is a corner when 9 contiguous pixels of the 16-pixel circle of radius 3
around it are all brighter than its intensity plus a threshold, or all darker than it
minus the threshold. Its score is the largest threshold at which it is still a corner,
minus one (the score ``cv2.FAST`` gives with non-maximum suppression), and a corner is
kept when its score is above that of each of its 8 neighbours.

ORB-SLAM (Mur-Artal et al. 2015) searches each cell of a level at a high threshold and,
where a cell has no corner, again at a low one. :func:`detect_level` does both for one
level in one call and gives the same corners, in the same order, as ``cv2.FAST`` run on
the windows :class:`~orbslam_hgcn.features.orb.ORBExtractor` hands it:

- FAST on a window tests the pixels 3 or more inside the window's border, and its
  non-maximum suppression takes pixels outside the tested area as score 0;
- the level is one window (inside the edge threshold less 3), searched at the high
  threshold; each cell without a corner is then a window of its own (the cell plus 3 px,
  kept inside the level's window), searched at the low threshold, and only the corners
  inside the cell are kept.

A pixel's score depends only on its 7x7 neighbourhood, so a corner found in a cell's
window has the score it would have on the whole level; only the suppression differs at
window borders, and it follows the windows here as well. The quick test and the scores
run on the vector units (see :func:`detect_level`), no ``cv2.KeyPoint`` object is made,
and no Python loop runs over the cells.
"""

from __future__ import annotations

import numpy as np

from orbslam_hgcn.compiled import jit

MARGIN = 3  # the circle's radius: no corner within 3 px of its window's border

# The 16-pixel Bresenham circle of radius 3, (dx, dy) in order around it.
CIRCLE = np.array(
    [(0, 3), (1, 3), (2, 2), (3, 1), (3, 0), (3, -1), (2, -2), (1, -3),
     (0, -3), (-1, -3), (-2, -2), (-3, -1), (-3, 0), (-3, 1), (-2, 2), (-1, 3)],
    dtype=np.int64,
)  # fmt: skip


_BATCH = 1024  # candidates scored together


@jit
def detect_level(img, lo, hi_threshold, lo_threshold, cells, first_cell, boxes, o):  # pragma: no cover - compiled
    """ORB-SLAM's FAST corners of one (H, W) uint8 level image (C-contiguous).

    The window rows/cols [lo, H - lo) x [lo, W - lo) is searched at ``hi_threshold``; then
    each cell that holds none of the kept corners is searched at ``lo_threshold`` as if on
    its own window (the cell plus 3 px). ``cells``: (H, W) int32 cell of each pixel, -1
    outside; ``boxes``: (C, 4) int64 x0, x1, y0, y1 (ends exclusive) of the level's cells,
    numbered from ``first_cell``; ``o``: (16,) int64 flat offsets of the circle in this
    image (:func:`circle_offsets`). Returns (x, y, score, cell), each (N,): the
    high-threshold corners row by row, then those of each searched cell, cell by cell and
    row by row within a cell.

    A cell's own window tests exactly the cell's pixels (those 3 px inside the level's
    window), and its suppression sees only them: so the low-threshold pass runs over the
    rows of the searched cells (neighbouring ones in a grid row together) and suppresses
    a corner only by a neighbour of its own cell. It is one function with no compiled
    callees: numba re-optimises a callee inside each caller, and a layered version took
    half a minute to compile.
    """
    h, w = img.shape
    lo = max(lo, 0)  # every read and write below stays inside the image
    ta, tb, tc, td = lo + MARGIN, h - lo - MARGIN, lo + MARGIN, w - lo - MARGIN  # the tested area
    flat = img.ravel()
    cell_flat = cells.ravel()
    scores = np.zeros(h * w, np.uint8)  # the pass's scores; 0 elsewhere
    corners = np.empty(h * w, np.int64)  # the pass's corners (flat indices), row by row
    idx = np.empty(_BATCH + w, np.int64)  # candidates waiting to be scored
    cand = np.empty(w, np.bool_)
    D = np.empty((16, _BATCH + w), np.int16)
    M = np.empty((16, _BATCH + w), np.int16)
    N = np.empty((16, _BATCH + w), np.int16)
    best = np.empty((2, _BATCH + w), np.int16)
    out_i = np.empty(h * w, np.int64)  # a pixel is kept at most once
    out_s = np.empty(h * w, np.uint8)
    n_out = 0
    n_hi = 0
    n_cells = len(boxes)
    searched = np.zeros(n_cells, np.bool_)  # cells searched at the low threshold
    # (row, first col, end col) to test: a row of the level in the first pass, at most a
    # row of each searched cell in the second.
    n_rows = h
    for c in range(n_cells):
        n_rows += max(boxes[c, 3] - boxes[c, 2], 0)
    seg = np.empty((n_rows, 3), np.int64)
    for pass_ in range(2):
        if ta >= tb or tc >= td:
            break
        n_seg = 0
        if pass_ == 0:
            t = hi_threshold
            for y in range(ta, tb):
                seg[n_seg, 0], seg[n_seg, 1], seg[n_seg, 2] = y, tc, td
                n_seg += 1
        else:
            t = lo_threshold
            searched[:] = True
            for k in range(n_out):
                c = cell_flat[out_i[k]] - first_cell
                if 0 <= c < n_cells:
                    searched[c] = False
            n_hi = n_out
            # Runs of searched cells side by side in a grid row, clipped to the tested area.
            c = 0
            while c < n_cells:
                if not searched[c]:
                    c += 1
                    continue
                x0, x1, y0, y1 = boxes[c, 0], boxes[c, 1], boxes[c, 2], boxes[c, 3]
                c += 1
                while (
                    c < n_cells and searched[c] and boxes[c, 0] == x1 and boxes[c, 2] == y0 and boxes[c, 3] == y1
                ):  # fmt: skip
                    x1 = boxes[c, 1]
                    c += 1
                x0, x1 = max(x0, tc), min(x1, td)
                if x0 < x1:
                    for y in range(max(y0, ta), min(y1, tb)):
                        seg[n_seg, 0], seg[n_seg, 1], seg[n_seg, 2] = y, x0, x1
                        n_seg += 1
        t16 = np.int16(t)
        n_idx = 0
        n_corners = 0
        # 1. Scores of the tested pixels (of searched cells in the second pass), a row
        #    segment at a time; the extra last step only scores what is left.
        for q in range(n_seg + 1):
            if q < n_seg:
                start, stop = seg[q, 0] * w + seg[q, 1], seg[q, 0] * w + seg[q, 2]
                scores[start:stop] = 0
                # The quick test: for each of the 8 opposite pairs (k, k + 8) of the
                # circle, one of the two is darker than the centre minus t (all pairs) or
                # one is brighter than the centre plus t (all pairs); a corner's arc of 9
                # holds one pixel of each pair. One view per circle pixel indexed from 0,
                # bounds clamped to 0..255 so that the comparisons stay in uint8, no
                # branches: the loop runs on the vector units.
                p0 = flat[start + o[0] : stop + o[0]]
                p1 = flat[start + o[1] : stop + o[1]]
                p2 = flat[start + o[2] : stop + o[2]]
                p3 = flat[start + o[3] : stop + o[3]]
                p4 = flat[start + o[4] : stop + o[4]]
                p5 = flat[start + o[5] : stop + o[5]]
                p6 = flat[start + o[6] : stop + o[6]]
                p7 = flat[start + o[7] : stop + o[7]]
                p8 = flat[start + o[8] : stop + o[8]]
                p9 = flat[start + o[9] : stop + o[9]]
                p10 = flat[start + o[10] : stop + o[10]]
                p11 = flat[start + o[11] : stop + o[11]]
                p12 = flat[start + o[12] : stop + o[12]]
                p13 = flat[start + o[13] : stop + o[13]]
                p14 = flat[start + o[14] : stop + o[14]]
                p15 = flat[start + o[15] : stop + o[15]]
                centre = flat[start:stop]
                for j in range(stop - start):
                    v = np.int16(centre[j])
                    lo_v = np.uint8(max(v - t16, 0))
                    hi_v = np.uint8(min(v + t16, 255))
                    a, b = p0[j], p8[j]
                    dark = (a < lo_v) | (b < lo_v)
                    bright = (a > hi_v) | (b > hi_v)
                    a, b = p1[j], p9[j]
                    dark &= (a < lo_v) | (b < lo_v)
                    bright &= (a > hi_v) | (b > hi_v)
                    a, b = p2[j], p10[j]
                    dark &= (a < lo_v) | (b < lo_v)
                    bright &= (a > hi_v) | (b > hi_v)
                    a, b = p3[j], p11[j]
                    dark &= (a < lo_v) | (b < lo_v)
                    bright &= (a > hi_v) | (b > hi_v)
                    a, b = p4[j], p12[j]
                    dark &= (a < lo_v) | (b < lo_v)
                    bright &= (a > hi_v) | (b > hi_v)
                    a, b = p5[j], p13[j]
                    dark &= (a < lo_v) | (b < lo_v)
                    bright &= (a > hi_v) | (b > hi_v)
                    a, b = p6[j], p14[j]
                    dark &= (a < lo_v) | (b < lo_v)
                    bright &= (a > hi_v) | (b > hi_v)
                    a, b = p7[j], p15[j]
                    dark &= (a < lo_v) | (b < lo_v)
                    bright &= (a > hi_v) | (b > hi_v)
                    cand[j] = dark | bright
                for j in range(stop - start):
                    if cand[j]:
                        idx[n_idx] = start + j
                        n_idx += 1
            if n_idx == 0 or (q < n_seg and n_idx < _BATCH):
                continue
            # The candidates' scores. With d_k = centre - circle pixel k, a pixel passes
            # the segment test at t when an arc of 9 has all d > t (a darker ring) or all
            # -d > t (a brighter one). With A the largest over the 16 arcs of the arc's
            # smallest d, and B the same for -d, its score max(A, B) - 1 is the largest
            # threshold it passes (cv2.FAST's score) and is below any it fails.
            for j in range(n_idx):
                i = idx[j]
                v = np.int16(flat[i])
                for k in range(16):
                    D[k, j] = v - np.int16(flat[np.uint64(i + o[k])])  # unsigned: no wraparound check
            for sign in range(2):
                if sign == 1:
                    for k in range(16):
                        for j in range(n_idx):
                            D[k, j] = -D[k, j]
                # The smallest over an arc of 9 from arcs of 2, 4 and 8: loops over the
                # candidates, on the vector units.
                for k in range(16):
                    k1 = (k + 1) & 15
                    for j in range(n_idx):
                        M[k, j] = min(D[k, j], D[k1, j])
                for k in range(16):
                    k2 = (k + 2) & 15
                    for j in range(n_idx):
                        N[k, j] = min(M[k, j], M[k2, j])
                for k in range(16):
                    k4 = (k + 4) & 15
                    for j in range(n_idx):
                        M[k, j] = min(N[k, j], N[k4, j])
                for j in range(n_idx):
                    best[sign, j] = -256
                for k in range(16):
                    k8 = (k + 8) & 15
                    for j in range(n_idx):
                        best[sign, j] = max(best[sign, j], min(M[k, j], D[k8, j]))
            for j in range(n_idx):
                s = max(best[0, j], best[1, j]) - 1
                if s >= t:
                    scores[idx[j]] = s
                    corners[n_corners] = idx[j]
                    n_corners += 1
            n_idx = 0
        # 2. Non-maximum suppression: a corner is kept when its score is above each
        #    neighbour's (0 outside the tested area, which is never written); in the
        #    second pass only neighbours of its own cell count.
        for k in range(n_corners):
            i = corners[k]
            s = scores[i]
            if pass_ == 0:
                keep = (
                    s > scores[i - w - 1] and s > scores[i - w] and s > scores[i - w + 1] and s > scores[i - 1]
                    and s > scores[i + 1] and s > scores[i + w - 1] and s > scores[i + w] and s > scores[i + w + 1]
                )  # fmt: skip
            else:
                c = cell_flat[i]
                keep = True
                for nb in (i - w - 1, i - w, i - w + 1, i - 1, i + 1, i + w - 1, i + w, i + w + 1):
                    if cell_flat[nb] == c and scores[nb] >= s:
                        keep = False
            if keep:
                out_i[n_out] = i
                out_s[n_out] = s
                n_out += 1
    # The second pass's corners cell by cell (a stable counting sort keeps rows in order).
    n_lo = n_out - n_hi
    if n_lo > 0:
        count = np.zeros(n_cells + 1, np.int64)
        for k in range(n_hi, n_out):
            count[cell_flat[out_i[k]] - first_cell + 1] += 1
        for c in range(n_cells):
            count[c + 1] += count[c]
        lo_i = out_i[n_hi:n_out].copy()
        lo_s = out_s[n_hi:n_out].copy()
        for k in range(n_lo):
            c = cell_flat[lo_i[k]] - first_cell
            out_i[n_hi + count[c]] = lo_i[k]
            out_s[n_hi + count[c]] = lo_s[k]
            count[c] += 1
    x = np.empty(n_out, np.int64)
    y = np.empty(n_out, np.int64)
    cell_of = np.empty(n_out, np.int32)
    for k in range(n_out):
        y[k], x[k] = out_i[k] // w, out_i[k] % w
        cell_of[k] = cell_flat[out_i[k]]
    return x, y, out_s[:n_out].astype(np.float32), cell_of


def circle_offsets(width: int) -> np.ndarray:
    """(16,) int64 flat offsets of :data:`CIRCLE` in a C-contiguous image of that width."""
    return CIRCLE[:, 1] * width + CIRCLE[:, 0]

"""Descriptor graph of the HGCN vocabulary: PCA features, faiss kNN graph, GCN normalisation.

Following the paper ("Semi-supervised Vector-Quantization in Visual SLAM using HGCN"): the
256 bits of every ORB descriptor are unpacked into a 256-D 0/1 vector and reduced to 20
dimensions by PCA; the graph links each descriptor to its k = 9 nearest neighbours in that
space (faiss), is made symmetric, and is normalised as in Kipf & Welling's GCN (ICLR 2017):
``A_hat = D^-1/2 (A + I) D^-1/2``.

faiss is imported where it is used, here and in :mod:`.ball` and :mod:`.flat`: a run with a
binary vocabulary never loads it (about 50 ms of its start-up).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from orbslam_hgcn.compiled import jit

# scipy.sparse is imported by the functions that build graphs (training and the HGCN
# vocabulary's new points), not with the module: 70 ms of every run's start-up.
if TYPE_CHECKING:
    import scipy.sparse as sp

log = logging.getLogger(__name__)

_PCA_CHUNK = 65536  # rows per block of the projection


def configure_faiss() -> None:
    """Use BLAS for flat searches from 20 queries up.

    This faiss build only switches its exhaustive search to BLAS from 128000 queries
    (``distance_compute_blas_threshold``); below that, 1000 queries against 10k 20-D
    vectors took ~100-190 ms here against ~8 ms with BLAS (same results).
    """
    import faiss
    faiss.cvar.distance_compute_blas_threshold = 20


# Queries up to this many go to faiss with one OpenMP thread (see :class:`faiss_threads`).
SMALL_BATCH = 20000


class faiss_threads:
    """Run a faiss call on one OpenMP thread when its batch is a frame's worth (at most
    :data:`SMALL_BATCH` queries), restoring the calling thread's count afterwards.

    libgomp keeps the thread count per calling thread, so this touches no other thread.
    Why: with faiss's default of one OpenMP thread per core, a frame's search (2000 KITTI
    descriptors against 8000 words, 20-D) took 128 ms CPU in a process beside four other
    busy ones on this 2-core machine, against 20 ms on one thread: the idle OpenMP workers
    spin waiting for work while the cores are taken. Training batches keep every thread.
    """

    def __init__(self, n_queries: int) -> None:
        self.small = n_queries <= SMALL_BATCH

    def __enter__(self) -> None:
        if self.small:
            import faiss
            self.saved = faiss.omp_get_max_threads()
            faiss.omp_set_num_threads(1)

    def __exit__(self, *exc: object) -> None:
        if self.small:
            import faiss
            faiss.omp_set_num_threads(self.saved)


def descriptor_features(desc: np.ndarray) -> np.ndarray:
    """(N, F) float32 features: unpacked bits (F = 8 B) of uint8 rows, or the float rows."""
    if desc.dtype == np.uint8:
        return np.unpackbits(desc, axis=1).astype(np.float32)
    return np.asarray(desc, dtype=np.float32)


@dataclass
class PCA:
    """Linear projection ``y = (f(x) - mean) @ components`` of descriptors x.

    mean: (F,) float32. components: (F, d) float32, orthonormal columns by decreasing
    variance. binary: whether x are packed-bit rows (f unpacks them) or float rows.
    """

    mean: np.ndarray
    components: np.ndarray
    binary: bool

    def __post_init__(self) -> None:
        self.mean = np.ascontiguousarray(self.mean, dtype=np.float32)
        self.components = np.ascontiguousarray(self.components, dtype=np.float32)
        self._offset = self.mean @ self.components
        if self.binary:
            # Nibble lookup table: (2B, 16, d), row 2j + h holding the contribution of every
            # value of byte j's low (h = 0) or high (h = 1) four bits. Summing 2B rows per
            # descriptor (:func:`_lut_rows`) took 0.44 ms CPU per 2000 KITTI descriptors
            # against 0.90 ms with a byte table ((B, 256, d): 655 kB, out of cache at d = 20;
            # this one 82 kB) and about 7 ms for unpacking the bits and a matrix product. The
            # sums agree with the product up to float rounding.
            nbytes = len(self.mean) // 8
            bits = np.unpackbits(np.arange(16, dtype=np.uint8)[:, None], axis=1, bitorder="little")[:, :4]
            comp = self.components.reshape(nbytes, 2, 4, -1)[:, :, ::-1]  # unpacked bits: most significant first
            lut = np.einsum("vb,jhbd->jhvd", bits.astype(np.float32), comp)  # (B, 2: low/high, 16, d)
            self._lut = np.ascontiguousarray(lut[:, ::-1].reshape(2 * nbytes, 16, -1))

    @property
    def dim(self) -> int:
        return self.components.shape[1]

    def transform(self, desc: np.ndarray) -> np.ndarray:
        """(N, d) float32 projections of (N, B) uint8 or (N, F) float descriptors."""
        out = np.empty((len(desc), self.dim), np.float32)
        for s in range(0, len(desc), _PCA_CHUNK):
            block = desc[s : s + _PCA_CHUNK]
            if self.binary:
                _lut_rows(self._lut, np.ascontiguousarray(block), out[s : s + _PCA_CHUNK])
            else:
                out[s : s + _PCA_CHUNK] = np.asarray(block, np.float32) @ self.components
        out -= self._offset
        return out


@jit
def _lut_rows(lut, desc, out):
    """out[i] = sum over bytes j of lut[2j, low four bits of desc[i, j]] + lut[2j + 1, high
    four bits] (float32)."""
    for i in range(desc.shape[0]):
        for t in range(lut.shape[2]):
            out[i, t] = 0
        for j in range(desc.shape[1]):
            lo = desc[i, j] & 15
            hi = desc[i, j] >> 4
            for t in range(lut.shape[2]):
                out[i, t] += lut[2 * j, lo, t] + lut[2 * j + 1, hi, t]


def fit_pca(desc: np.ndarray, dim: int, max_rows: int = 200_000, seed: int = 0) -> PCA:
    """PCA of descriptors (unpacked bits for uint8 rows) on at most ``max_rows`` of them."""
    rng = np.random.default_rng(seed)
    rows = desc if len(desc) <= max_rows else desc[np.sort(rng.choice(len(desc), max_rows, replace=False))]
    mean = np.zeros(descriptor_features(rows[:1]).shape[1], np.float64)
    for s in range(0, len(rows), _PCA_CHUNK):
        mean += descriptor_features(rows[s : s + _PCA_CHUNK]).sum(0)
    mean /= len(rows)
    cov = np.zeros((len(mean), len(mean)), np.float64)
    for s in range(0, len(rows), _PCA_CHUNK):
        f = descriptor_features(rows[s : s + _PCA_CHUNK]) - mean.astype(np.float32)
        cov += f.T.astype(np.float64) @ f
    cov /= max(len(rows) - 1, 1)
    evals, evecs = np.linalg.eigh(cov)
    order = np.argsort(evals)[::-1][:dim]
    comp = evecs[:, order]
    comp *= np.where(comp[np.abs(comp).argmax(0), np.arange(comp.shape[1])] < 0, -1, 1)  # sign convention
    log.debug("PCA to %d dims keeps %.1f%% of the variance", dim, 100 * evals[order].sum() / max(evals.sum(), 1e-12))
    return PCA(mean.astype(np.float32), comp.astype(np.float32), binary=desc.dtype == np.uint8)


def knn(x: np.ndarray, k: int, exact_max: int = 60_000, nprobe: int = 16, seed: int = 0) -> np.ndarray:
    """(N, k) int64 indices of the k nearest other rows of x (N, d) float32, self excluded.

    Exact (faiss IndexFlatL2) up to ``exact_max`` rows; above, an inverted-file index
    (IndexIVFFlat, 4 sqrt(N) lists, ``nprobe`` probed), which is approximate. Where an
    approximate search finds fewer than k others, the missing entries are -1.
    """
    import faiss
    configure_faiss()
    x = np.ascontiguousarray(x, dtype=np.float32)
    n, d = x.shape
    kq = min(k + 1, n)
    if n <= exact_max:
        index = faiss.IndexFlatL2(d)
    else:
        nlist = int(4 * np.sqrt(n))
        index = faiss.IndexIVFFlat(faiss.IndexFlatL2(d), d, nlist)
        rng = np.random.default_rng(seed)
        train = x[rng.choice(n, min(n, 64 * nlist), replace=False)]
        index.train(train)
        index.nprobe = nprobe
    index.add(x)
    _, nbr = index.search(x, kq)
    is_self = nbr == np.arange(n)[:, None]
    no_self = ~is_self.any(axis=1)
    is_self[no_self, -1] = True  # self not returned (duplicates): drop the farthest instead
    out = nbr[~is_self].reshape(n, kq - 1)
    if kq - 1 < k:
        out = np.concatenate([out, np.full((n, k - kq + 1), -1, np.int64)], axis=1)
    return out


def symmetric_adjacency(nbr: np.ndarray) -> sp.csr_matrix:
    """(N, N) float32 0/1 CSR adjacency ``max(A, A^T)`` of a kNN list (N, k); -1 entries skipped."""
    import scipy.sparse as sp
    n, k = nbr.shape
    rows = np.repeat(np.arange(n), k)
    cols = nbr.reshape(-1)
    ok = (cols >= 0) & (cols != rows)
    a = sp.csr_matrix((np.ones(int(ok.sum()), np.float32), (rows[ok], cols[ok])), shape=(n, n))
    a = a.maximum(a.T).tocsr()
    a.data[:] = 1.0
    a.sort_indices()
    return a


def normalised_adjacency(a: sp.csr_matrix) -> sp.csr_matrix:
    """GCN propagation matrix ``D^-1/2 (A + I) D^-1/2`` (D: degrees of A + I), float32 CSR."""
    import scipy.sparse as sp
    a_tilde = (a + sp.identity(a.shape[0], dtype=np.float32, format="csr")).tocsr()
    deg = np.asarray(a_tilde.sum(axis=1)).reshape(-1)
    inv_sqrt = 1.0 / np.sqrt(deg)
    d = sp.diags(inv_sqrt.astype(np.float32))
    out = (d @ a_tilde @ d).astype(np.float32).tocsr()
    out.sort_indices()
    return out


def build_graph(x: np.ndarray, k: int, exact_max: int = 60_000, nprobe: int = 16, seed: int = 0) -> sp.csr_matrix:
    """Normalised symmetric kNN graph of rows x (N, d): see the module docstring."""
    return normalised_adjacency(symmetric_adjacency(knn(x, k, exact_max, nprobe, seed)))


def gather_rows(adj: sp.csr_matrix, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Entries of the given rows of a CSR matrix.

    Returns (local_row (E,), col (E,), value (E,)): local_row indexes ``rows``.
    """
    starts = adj.indptr[rows]
    lens = adj.indptr[rows + 1] - starts
    local_row = np.repeat(np.arange(len(rows)), lens)
    pos = np.repeat(starts - np.concatenate([[0], np.cumsum(lens)[:-1]]), lens) + np.arange(int(lens.sum()))
    return local_row, adj.indices[pos].astype(np.int64), adj.data[pos]


def sample_row_entries(rows: np.ndarray, cols: np.ndarray, vals: np.ndarray, row_nodes: np.ndarray, m: int,
                       rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Keep each row's self loop and at most ``m`` of its other entries, chosen at random.

    The kept entries of a row with n > m others are scaled by n / m, so the expected
    aggregation equals the full one (neighbour sampling, Hamilton et al., GraphSAGE,
    NeurIPS 2017). rows: (E,) local row of each entry, sorted; row_nodes: node of each row.
    """
    is_self = cols == row_nodes[rows]
    key = rng.random(len(rows))
    key[is_self] = -1.0  # the self loop sorts first in its row
    order = np.lexsort((key, rows))
    rows, cols, vals = rows[order], cols[order], vals[order].copy()
    counts = np.bincount(rows, minlength=len(row_nodes))
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    rank = np.arange(len(rows)) - starts[rows]
    others = (counts - 1)[rows]
    keep = rank <= m
    scale = (rank > 0) & (others > m)
    vals[scale] *= (others[scale] / m).astype(vals.dtype)
    return rows[keep], cols[keep], vals[keep]


def two_hop_blocks(adj: sp.csr_matrix, seeds: np.ndarray, max_neighbours: int = 0,
                   rng: np.random.Generator | None = None):
    """Two-layer computation blocks for a batch of seed nodes.

    adj: normalised (N, N) CSR with self loops. seeds: (B,) node ids. max_neighbours: if
    positive, the first layer aggregates over the self loop and at most this many sampled
    neighbours of every node (see :func:`sample_row_entries`); 0: exact.
    Returns (hop2, block1, hop1, block2): ``hop2`` (N2,) sorted nodes whose inputs layer 1
    needs; ``block1`` (rows, cols, vals) of ``adj[hop1][:, hop2]`` in local indices;
    ``hop1`` (N1,) sorted nodes whose layer-1 outputs layer 2 needs; ``block2`` of
    ``adj[seeds][:, hop1]``.
    """
    r2, c2, v2 = gather_rows(adj, seeds)
    hop1 = np.unique(c2)
    r1, c1, v1 = gather_rows(adj, hop1)
    if max_neighbours > 0:
        r1, c1, v1 = sample_row_entries(r1, c1, v1, hop1, max_neighbours, rng or np.random.default_rng())
    hop2 = np.unique(c1)
    block1 = (r1, np.searchsorted(hop2, c1), v1)
    block2 = (r2, np.searchsorted(hop1, c2), v2)
    return hop2, block1, hop1, block2

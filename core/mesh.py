"""Mesh connectivity and neighbour-only local moments (Bors 2006, eqs. 1-6 and 15-16).

Everything here is vectorised over the whole mesh with a CSR 1-ring adjacency.
The moments of vertex ``i`` use its neighbours only (never ``V_i`` itself), so that moving a
carrier never moves its own boundary.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.sparse as sp

from core.parallel import CHUNK_ROWS, by_chunks, row_block


@dataclass(frozen=True)
class Adjacency:
    """1-ring adjacency of a triangle mesh in CSR form.

    Attributes
    ----------
    indptr : (n + 1,) int64
    indices : (2e,) int64
        Neighbours of vertex ``i`` are ``indices[indptr[i]:indptr[i + 1]]`` (sorted).
    rows : (2e,) int64
        Row of every entry of ``indices`` (built on first use).
    degree : (n,) int64
    boundary : (n,) bool
        Vertex on an edge used by exactly one face.
    nonmanifold : (n,) bool
        Vertex on an edge used by more than two faces.
    ring_matrix : scipy.sparse.csr_matrix, uint64
        The same pattern with every entry 1 (for :meth:`ring_sum_u64`).
    faces : (m, 3) int64
        The faces (not copied): their winding says which side of the surface is outside
        (:meth:`corner`, :func:`oriented`).
    """

    indptr: np.ndarray
    indices: np.ndarray
    degree: np.ndarray
    boundary: np.ndarray
    nonmanifold: np.ndarray
    ring_matrix: sp.csr_matrix
    faces: np.ndarray

    @cached_property
    def vertex_face(self) -> np.ndarray:
        """(n,) int64: one face of each vertex (the last that names it), -1 for a vertex of none."""
        face = np.full(len(self.degree), -1, np.int64)
        m = np.arange(len(self.faces), dtype=np.int64)
        for c in range(3):
            face[self.faces[:, c]] = m
        return face

    def corner(self, which: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The next and previous vertices, in the winding of :attr:`vertex_face`, of the vertices
        ``which`` (the vertex itself for a vertex of no face)."""
        which = np.asarray(which, np.int64)
        face = self.vertex_face[which]
        rows = self.faces[np.maximum(face, 0)]
        c = np.argmax(rows == which[:, None], axis=1)
        k = np.arange(len(which))
        none = face < 0
        return (np.where(none, which, rows[k, (c + 1) % 3]), np.where(none, which, rows[k, (c + 2) % 3]))

    @cached_property
    def rows(self) -> np.ndarray:
        return np.repeat(np.arange(len(self.degree), dtype=np.int64), self.degree)

    def ring_sum_u64(self, values: np.ndarray) -> np.ndarray:
        """Sum of ``values`` (uint64) over each vertex's neighbours, modulo 2**64.

        A sparse matrix-vector product: one pass in C, faster than gathering the ``2e``
        neighbour values and reducing them per row."""
        return np.asarray(self.ring_matrix @ np.asarray(values, np.uint64))

    def ring_block(self, lo: int, hi: int) -> sp.csr_matrix:
        """Rows ``lo:hi`` of :attr:`ring_matrix`, sharing its arrays (made once per row range): a
        product per row block, each in its own thread, gives the whole product's rows bit for bit."""
        blocks = self._ring_blocks
        if (lo, hi) not in blocks:
            blocks[lo, hi] = row_block(self.ring_matrix, lo, hi)
        return blocks[lo, hi]

    @cached_property
    def _ring_blocks(self) -> dict[tuple[int, int], sp.csr_matrix]:
        return {}

    @cached_property
    def _real_ring(self) -> sp.csr_matrix:
        ring = self.ring_matrix
        return sp.csr_matrix((np.ones(ring.nnz), ring.indices, ring.indptr), shape=ring.shape)

    def ring_sum(self, values: np.ndarray) -> np.ndarray:
        """Sum of ``values`` ((n,) or (n, k) float64) over each vertex's neighbours, added in the
        order of :attr:`indices` (as ``np.bincount(rows, values[indices])`` adds them, bit for bit,
        in a quarter of the time, and the k columns of a 2-D ``values`` in one pass over the
        adjacency, in 0.4-0.7 of the time of one pass per column at 1M vertices; the matrix of
        ones it multiplies by is made on first use)."""
        return np.asarray(self._real_ring @ np.asarray(values, np.float64))

    def ring_max(self, values: np.ndarray) -> np.ndarray:
        """Largest of ``values`` over each vertex's neighbours (0 for a vertex of none): a large
        mesh in chunks of rows, every other one in a second thread (:func:`~core.parallel.by_chunks`)."""
        def chunk(lo: int, hi: int) -> np.ndarray:
            has = self.degree[lo:hi] > 0
            out = np.zeros(hi - lo, values.dtype)
            seg = values[self.indices[self.indptr[lo]:self.indptr[hi]]]
            if seg.size:
                out[has] = np.maximum.reduceat(seg, self.indptr[lo:hi][has] - self.indptr[lo])
            return out

        n = len(self.degree)
        return np.concatenate(by_chunks(chunk, n, CHUNK_ROWS)) if n else np.zeros(0, values.dtype)

    def within(self, seeds: np.ndarray, rings: int) -> np.ndarray:
        """(n,) bool: the vertices at most ``rings`` edges from a vertex of the mask ``seeds``
        (one sparse product per ring)."""
        near = np.asarray(seeds, bool).copy()
        for _ in range(int(rings)):
            near |= self.ring_sum(near.astype(np.float64)) > 0
        return near

    def ring_entries(self, which: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Positions in ``indices`` of the neighbours of the vertices ``which``, concatenated.

        Returns
        -------
        first : (k,) int64
            Offset of each vertex's run in ``pos`` (runs are ``degree[which]`` long).
        pos : (sum of degrees,) int64
        """
        which = np.asarray(which, dtype=np.int64)
        start = self.indptr[which]
        deg = self.indptr[which + 1] - start
        ends = np.cumsum(deg)
        first = ends - deg
        total = int(ends[-1]) if which.size else 0
        return first, np.arange(total) + np.repeat(start - first, deg)


def adjacency(faces: np.ndarray, n_vertices: int) -> Adjacency:
    """Build the 1-ring :class:`Adjacency` of ``faces`` (m, 3) over ``n_vertices`` vertices.

    The half-edges are counted into a sparse matrix (scipy's counting sort, linear time) and
    symmetrised, so every entry also says how many faces use the edge.
    """
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    n = int(n_vertices)
    a = f.ravel()
    b = f[:, [1, 2, 0]].ravel()
    half = sp.csr_matrix((np.ones(a.size, np.int32), (a, b)), shape=(n, n))
    full = (half + half.T).tocsr()
    full.sum_duplicates()
    indptr = full.indptr.astype(np.int64)
    indices = full.indices.astype(np.int64)
    uses = full.data
    degree = np.diff(indptr)
    # rows of the few entries that are not interior manifold edges
    boundary = np.zeros(n, bool)
    boundary[np.searchsorted(indptr, np.flatnonzero(uses == 1), side="right") - 1] = True
    nonmanifold = np.zeros(n, bool)
    nonmanifold[np.searchsorted(indptr, np.flatnonzero(uses > 2), side="right") - 1] = True
    # scipy's own (int32) index arrays, shared rather than converted back
    ring = sp.csr_matrix((np.ones(uses.size, np.uint64), full.indices, full.indptr), shape=(n, n))
    return Adjacency(indptr, indices, degree, boundary, nonmanifold, ring, f)


def oriented(v: np.ndarray, adj: Adjacency, sel: np.ndarray, mu: np.ndarray, axes: np.ndarray) -> np.ndarray:
    """Turn, in place, the least-variance axis ``axes[:, :, 0]`` of the rings of ``sel`` (means
    ``mu``) to the side the winding of one of the vertex's faces calls outside, and return ``axes``.

    The face's normal is taken with the ring mean in place of the vertex, so the vertex's own
    position never enters (the boundary must not move with the carrier).  An eigenvector's sign is
    otherwise arbitrary; oriented, the offset along it is a signed quantity that the embedder can put
    on a known side and the detector read linearly (core/README.md, section 3, signed offsets)."""
    nx, pv = adj.corner(sel)
    a, b = v[nx] - mu, v[pv] - mu
    e = axes[:, :, 0]
    # e . (a x b), written out per component (np.cross is slow on many short rows)
    dot = (e[:, 0] * (a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1])
           + e[:, 1] * (a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2])
           + e[:, 2] * (a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]))
    axes[:, :, 0] = np.where((dot < 0)[:, None], -e, e)
    return axes


def columns(vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The three coordinate columns of ``vertices`` (n, 3), each contiguous (1-D gathers from them
    are several times faster than fancy indexing of rows)."""
    x, y, z = (np.ascontiguousarray(vertices[:, c], dtype=np.float64) for c in range(3))
    return x, y, z


def neighbour_moments(
    vertices: np.ndarray, adj: Adjacency, which: np.ndarray,
    cols: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Mean and covariance of the 1-ring neighbours of the vertices ``which`` (eqs. 2-3).

    Parameters
    ----------
    vertices : (n, 3) float64
    adj : Adjacency
    which : (k,) int64
        Vertices whose neighbourhoods are wanted (each with degree >= 1).
    cols : tuple of three (n,) float64, optional
        :func:`columns` of ``vertices``, when the caller has them.

    Returns
    -------
    mu : (k, 3) float64
        Mean of the neighbours (the vertex itself excluded).
    sigma : (k, 3, 3) float64
        Population covariance of the neighbours about ``mu``.
    """
    which = np.asarray(which, dtype=np.int64)
    k = which.size
    deg = adj.degree[which]
    seg = np.repeat(np.arange(k), deg)
    nb = adj.indices[adj.ring_entries(which)[1]]
    w = 1.0 / deg
    # one contiguous coordinate at a time: 1-D gathers and bincounts are several times faster
    # than fancy indexing of (n, 3) rows
    if cols is None:
        cols = columns(vertices)
    mu = np.empty((k, 3))
    d = []
    for c in range(3):
        pc = np.take(cols[c], nb)
        m = np.bincount(seg, pc, minlength=k) * w
        mu[:, c] = m
        d.append(pc - np.take(m, seg))
    sigma = np.empty((k, 3, 3))
    for r in range(3):
        for c in range(r, 3):
            s = np.bincount(seg, d[r] * d[c], minlength=k) * w
            sigma[:, r, c] = s
            sigma[:, c, r] = s
    return mu, sigma


def edge_lengths(vertices: np.ndarray, adj: Adjacency) -> np.ndarray:
    """Length of every undirected edge (once per edge)."""
    half = adj.rows < adj.indices
    return np.linalg.norm(vertices[adj.rows[half]] - vertices[adj.indices[half]], axis=1)


def changed_rows(new: np.ndarray, old: np.ndarray) -> np.ndarray:
    """(n,) bool: the rows of ``new`` (n, 3) that differ from those of ``old`` in any coordinate
    (column by column: ``np.any(new != old, axis=1)`` takes five times as long on (n, 3) arrays)."""
    return (new[:, 0] != old[:, 0]) | (new[:, 1] != old[:, 1]) | (new[:, 2] != old[:, 2])


def bbox_diagonal(vertices: np.ndarray) -> float:
    """Length of the axis-aligned bounding-box diagonal (0 for an empty array)."""
    if len(vertices) == 0:
        return 0.0
    # column by column: reducing an (n, 3) array along axis 0 is much slower
    return float(np.sqrt(sum((float(col.max()) - float(col.min())) ** 2 for col in vertices.T)))

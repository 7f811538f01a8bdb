"""Mesh connectivity and neighbour-only local moments (Bors 2006, eqs. 1-6 and 15-16).

Everything here is vectorised over the whole mesh with a CSR 1-ring adjacency.
The moments of vertex ``i`` use its neighbours only (never ``V_i`` itself), so that moving a
carrier never moves its own boundary.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp


@dataclass(frozen=True)
class Adjacency:
    """1-ring adjacency of a triangle mesh in CSR form.

    Attributes
    ----------
    indptr : (n + 1,) int64
    indices : (2e,) int64
        Neighbours of vertex ``i`` are ``indices[indptr[i]:indptr[i + 1]]`` (sorted).
    rows : (2e,) int64
        Row of every entry of ``indices``.
    degree : (n,) int64
    boundary : (n,) bool
        Vertex on an edge used by exactly one face.
    nonmanifold : (n,) bool
        Vertex on an edge used by more than two faces.
    """

    indptr: np.ndarray
    indices: np.ndarray
    rows: np.ndarray
    degree: np.ndarray
    boundary: np.ndarray
    nonmanifold: np.ndarray


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
    rows = np.repeat(np.arange(n, dtype=np.int64), degree)
    boundary = np.zeros(n, bool)
    boundary[rows[uses == 1]] = True
    nonmanifold = np.zeros(n, bool)
    nonmanifold[rows[uses > 2]] = True
    return Adjacency(indptr, indices, rows, degree, boundary, nonmanifold)


def neighbour_moments(
    vertices: np.ndarray, adj: Adjacency, which: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Mean and covariance of the 1-ring neighbours of the vertices ``which`` (eqs. 2-3).

    Parameters
    ----------
    vertices : (n, 3) float64
    adj : Adjacency
    which : (k,) int64
        Vertices whose neighbourhoods are wanted (each with degree >= 1).

    Returns
    -------
    mu : (k, 3) float64
        Mean of the neighbours (the vertex itself excluded).
    sigma : (k, 3, 3) float64
        Population covariance of the neighbours about ``mu``.
    """
    which = np.asarray(which, dtype=np.int64)
    start, stop = adj.indptr[which], adj.indptr[which + 1]
    deg = stop - start
    seg = np.repeat(np.arange(which.size), deg)
    offs = np.arange(deg.sum()) - np.repeat(np.cumsum(deg) - deg, deg)
    nb = adj.indices[np.repeat(start, deg) + offs]
    p = vertices[nb]
    k = which.size
    w = 1.0 / deg
    mu = np.stack([np.bincount(seg, p[:, c], minlength=k) for c in range(3)], axis=1) * w[:, None]
    d = p - mu[seg]
    sigma = np.empty((k, 3, 3))
    for r in range(3):
        for c in range(r, 3):
            s = np.bincount(seg, d[:, r] * d[:, c], minlength=k) * w
            sigma[:, r, c] = s
            sigma[:, c, r] = s
    return mu, sigma


def edge_lengths(vertices: np.ndarray, adj: Adjacency) -> np.ndarray:
    """Length of every undirected edge (once per edge)."""
    half = adj.rows < adj.indices
    return np.linalg.norm(vertices[adj.rows[half]] - vertices[adj.indices[half]], axis=1)


def bbox_diagonal(vertices: np.ndarray) -> float:
    """Length of the axis-aligned bounding-box diagonal (0 for an empty array)."""
    if len(vertices) == 0:
        return 0.0
    return float(np.linalg.norm(vertices.max(axis=0) - vertices.min(axis=0)))

"""Linear algebra over GF(2) on small dense 0/1 matrices (at most a few hundred rows).

Gaussian elimination loops over the columns; every row operation is one numpy XOR over the rows.
"""

from __future__ import annotations

import numpy as np


def _eliminate(a: np.ndarray) -> tuple[np.ndarray, list[int]]:
    """Reduced row echelon form of ``a`` (a copy) and the pivot column of each leading row."""
    a = (np.asarray(a, np.uint8) & 1).copy()
    rows, cols = a.shape
    pivots: list[int] = []
    r = 0
    for c in range(cols):
        if r == rows:
            break
        hit = np.flatnonzero(a[r:, c]) + r
        if not hit.size:
            continue
        p = int(hit[0])
        if p != r:
            a[[r, p]] = a[[p, r]]
        others = np.flatnonzero(a[:, c])
        others = others[others != r]
        a[others] ^= a[r]
        pivots.append(c)
        r += 1
    return a, pivots


def rank(a: np.ndarray) -> int:
    """Rank of the 0/1 matrix ``a`` over GF(2)."""
    return len(_eliminate(a)[1])


def inverse(a: np.ndarray) -> np.ndarray | None:
    """Inverse of the square 0/1 matrix ``a`` over GF(2), or ``None`` when it is singular."""
    n = len(a)
    red, pivots = _eliminate(np.concatenate([np.asarray(a, np.uint8), np.eye(n, dtype=np.uint8)], axis=1))
    if pivots[:n] != list(range(n)):
        return None
    return red[:, n:].copy()


def solve(a: np.ndarray, b: np.ndarray, free: np.ndarray | None = None) -> np.ndarray | None:
    """One solution ``x`` of ``a x = b`` over GF(2), or ``None`` when there is none.

    Parameters
    ----------
    a : (k, m) uint8 ndarray
    b : (k,) uint8 ndarray
    free : (m,) uint8 ndarray, optional
        Values of the unknowns that the equations leave free (default 0); the others follow.

    Returns
    -------
    (m,) uint8 ndarray or None
    """
    a = np.asarray(a, np.uint8)
    k, m = a.shape
    red, pivots = _eliminate(np.concatenate([a, np.asarray(b, np.uint8).reshape(k, 1)], axis=1))
    if m in pivots:
        return None  # a row 0 = 1
    x = np.zeros(m, np.uint8) if free is None else (np.asarray(free, np.uint8) & 1).copy()
    x[pivots] = 0
    # pivot unknown = right-hand side XOR the free unknowns of its row
    x[pivots] = (red[: len(pivots), m].astype(np.int64) + red[: len(pivots), :m].astype(np.int64) @ x) % 2
    return x

"""Closed-form eigen-decomposition of many symmetric 3x3 matrices at once.

``numpy.linalg.eigh`` on a ``(k, 3, 3)`` stack calls LAPACK once per matrix, which made it the
largest single cost of detecting a large mesh (``core/README.md`` has the profile). The solver here
is D. Eberly's "A Robust Eigensolver for 3x3 Symmetric Matrices" (Geometric Tools, 2014) written as
whole-array numpy on the six distinct entries (contiguous columns, no per-matrix work): eigenvalues
from the trigonometric solution of the characteristic cubic of the normalised matrix, the
eigenvector of the best separated eigenvalue from the largest cross product of two rows of
``A - l I``, the middle one from the 2x2 problem in its orthogonal complement (diagonalised by its
rotation angle, no eigenvalue needed), the third as a cross product;
the eigenvalues are then refined as Rayleigh quotients (the cubic loses half the digits of a double
eigenvalue, the quotient of an orthonormal basis does not). The tests compare it with LAPACK on
random, rank-deficient and (near-)degenerate matrices.
"""

from __future__ import annotations

import numpy as np

Vec = tuple[np.ndarray, np.ndarray, np.ndarray]


def _cross(a: Vec, b: Vec) -> Vec:
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _dot(a: Vec, b: Vec) -> np.ndarray:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _scaled(a: Vec, s: np.ndarray) -> Vec:
    return (a[0] * s, a[1] * s, a[2] * s)


class _Sym:
    """The six entries of a stack of symmetric matrices, as contiguous arrays."""

    def __init__(self, a00: np.ndarray, a01: np.ndarray, a02: np.ndarray, a11: np.ndarray, a12: np.ndarray,
                 a22: np.ndarray) -> None:
        self.a00, self.a01, self.a02, self.a11, self.a12, self.a22 = a00, a01, a02, a11, a12, a22

    def rows(self, lam: np.ndarray) -> tuple[Vec, Vec, Vec]:
        return ((self.a00 - lam, self.a01, self.a02), (self.a01, self.a11 - lam, self.a12),
                (self.a02, self.a12, self.a22 - lam))

    def apply(self, x: Vec) -> Vec:
        return (self.a00 * x[0] + self.a01 * x[1] + self.a02 * x[2],
                self.a01 * x[0] + self.a11 * x[1] + self.a12 * x[2],
                self.a02 * x[0] + self.a12 * x[1] + self.a22 * x[2])


def _where(mask: np.ndarray, a: Vec, b: Vec) -> Vec:
    return (np.where(mask, a[0], b[0]), np.where(mask, a[1], b[1]), np.where(mask, a[2], b[2]))


def _vector_from_rows(m: _Sym, lam: np.ndarray) -> Vec:
    """Unit eigenvector of the simple eigenvalue ``lam``: the largest cross product of two rows
    of ``m - lam I`` (the rows span the orthogonal complement of the eigenvector)."""
    r0, r1, r2 = m.rows(lam)
    best = _cross(r0, r1)
    dbest = _dot(best, best)
    for c in (_cross(r0, r2), _cross(r1, r2)):
        d = _dot(c, c)
        better = d > dbest
        best = _where(better, c, best)
        dbest = np.where(better, d, dbest)
    ok = dbest > 0
    v = _scaled(best, 1.0 / np.sqrt(np.where(ok, dbest, 1.0)))
    # m = lam I: every vector is an eigenvector
    one, zero = np.ones_like(lam), np.zeros_like(lam)
    return _where(ok, v, (one, zero, zero))


def _complement(w: Vec) -> tuple[Vec, Vec]:
    """Orthonormal ``u, v`` with ``(u, v, w)`` a right-handed orthonormal basis (``w`` unit)."""
    x, y, z = w
    use_x = np.abs(x) > np.abs(y)
    inv = 1.0 / np.sqrt(np.where(use_x, x * x + z * z, y * y + z * z))
    zero = np.zeros_like(x)
    u = (np.where(use_x, -z, zero) * inv, np.where(use_x, zero, z) * inv, np.where(use_x, x, -y) * inv)
    return u, _cross(w, u)


def _second_vector(m: _Sym, w: Vec, larger: np.ndarray) -> Vec:
    """Unit eigenvector of the middle eigenvalue, orthogonal to the eigenvector ``w`` of an outer
    one: of ``m`` restricted to the plane orthogonal to ``w``, the eigenvector of the ``larger``
    (``w`` the largest's) or the smaller of its two eigenvalues, from the rotation angle
    ``atan2(2 m01, m00 - m11) / 2`` (no eigenvalue needed: the cubic's is only good to about
    sqrt(eps) of the largest, which picked an arbitrary vector within a pair closer than that)."""
    u, v = _complement(w)
    mv = m.apply(v)
    m00 = _dot(u, m.apply(u))
    m01 = _dot(u, mv)
    m11 = _dot(v, mv)
    theta = 0.5 * np.arctan2(2.0 * m01, m00 - m11)
    c, s = np.cos(theta), np.sin(theta)
    # (c, s) belongs to the larger eigenvalue of the 2x2 problem, (-s, c) to the smaller
    a = np.where(larger, c, -s)
    b = np.where(larger, s, c)
    return (a * u[0] + b * v[0], a * u[1] + b * v[1], a * u[2] + b * v[2])


def eigh3(m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eigenvalues (ascending) and eigenvectors (columns) of symmetric 3x3 matrices.

    Parameters
    ----------
    m : (k, 3, 3) float64, symmetric

    Returns
    -------
    lam : (k, 3) ascending eigenvalues
    vec : (k, 3, 3) orthonormal eigenvectors, ``vec[:, :, j]`` belongs to ``lam[:, j]``
    """
    m = np.asarray(m, np.float64)
    k = len(m)
    if k == 0:
        return np.zeros((0, 3)), np.zeros((0, 3, 3))
    # normalise by the largest entry (no overflow or underflow in the cubic)
    entries = [np.ascontiguousarray(m[:, i, j]) for i, j in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))]
    big = np.abs(entries[0])
    for e in entries[1:]:
        np.maximum(big, np.abs(e), out=big)
    zero = ~(big > 0)
    den = np.where(zero, 1.0, big)
    a = _Sym(*(e / den for e in entries))
    off = a.a01 * a.a01 + a.a02 * a.a02 + a.a12 * a.a12
    q = (a.a00 + a.a11 + a.a22) / 3.0
    b00, b11, b22 = a.a00 - q, a.a11 - q, a.a22 - q
    p = np.sqrt((b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * off) / 6.0)
    # diagonal matrices (including multiples of I) are handled apart, below.  Off-diagonal entries
    # below 1e-100 of the largest are taken as zero: they move no eigenvalue by more than that, and
    # below it p**3 can underflow to 0 (found by hypothesis: an entry 1.4e-151 gave 0/0)
    diag = ~(off > 1e-200)
    ps = np.where(diag, 1.0, p)
    det = (b00 * (b11 * b22 - a.a12 * a.a12) - a.a01 * (a.a01 * b22 - a.a12 * a.a02)
           + a.a02 * (a.a01 * a.a12 - b11 * a.a02))
    half = np.clip(det / (2.0 * ps**3), -1.0, 1.0)
    angle = np.arccos(half) / 3.0
    beta2 = 2.0 * np.cos(angle)
    beta0 = 2.0 * np.cos(angle + 2.0 * np.pi / 3.0)
    # the eigenvector of the best separated eigenvalue first (the largest when half >= 0)
    top = half >= 0
    w = _vector_from_rows(a, q + ps * np.where(top, beta2, beta0))
    mid = _second_vector(a, w, top)
    third = _cross(w, mid)
    e0, e2 = _where(top, third, w), _where(top, w, third)
    vec = np.empty((k, 3, 3))
    for j, ev in enumerate((e0, mid, e2)):
        for i in range(3):
            vec[:, i, j] = ev[i]
    # Rayleigh quotients: accurate also for (near-)double eigenvalues
    lam = np.stack([_dot(ev, a.apply(ev)) for ev in (e0, mid, e2)], axis=1)
    if diag.any():
        # the axes, sorted by the diagonal entries
        d = np.stack([a.a00[diag], a.a11[diag], a.a22[diag]], axis=1)
        order = np.argsort(d, axis=1, kind="stable")
        lam[diag] = np.take_along_axis(d, order, axis=1)
        vec[diag] = np.eye(3)[order].transpose(0, 2, 1)
    # refinement may swap two nearly equal eigenvalues: keep them ascending
    swapped = np.flatnonzero((lam[:, 0] > lam[:, 1]) | (lam[:, 1] > lam[:, 2]))
    if swapped.size:
        order = np.argsort(lam[swapped], axis=1, kind="stable")
        lam[swapped] = np.take_along_axis(lam[swapped], order, axis=1)
        vec[swapped] = np.take_along_axis(vec[swapped], order[:, None, :], axis=2)
    lam *= np.where(zero, 0.0, big)[:, None]
    return lam, vec

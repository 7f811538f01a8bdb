"""Undo uniform Laplacian smoothing before detection.

Uniform Laplacian smoothing, ``n`` iterations of ``V += lam (mean(N(V)) - V)`` on every vertex,
is the linear filter ``(I - lam K)^n`` with ``K = I - D^-1 A`` on the mesh's own connectivity,
which the attack keeps.  It removes the carriers' offsets from their rings (a high-frequency
signal: after ``0.1 x 30`` the sign of a carrier's statistic was wrong for 36-49 % of the
carriers on the shared meshes, and only the turbine blade still read).  ``D^-1 A`` is similar
to the symmetric ``D^-1/2 A D^-1/2``, so the spectrum of ``K`` is real, in ``[0, 2]``, and the
filter's smallest gain is ``(1 - 2 lam)^n`` (``1.2e-3`` for ``0.1 x 30``): the filter is
*invertible* on the suspect mesh alone.  Smoothed 0.1 x 30 and undone, the bunny's positions
come back to 2e-9 of its median edge (stored in double precision; in float32 or with 6
significant digits the mark still reads).

* **The inverse.**  ``(I - lam K)^-n`` is a polynomial in ``K`` evaluated by the Chebyshev
  three-term recurrence on ``X = K - I = -D^-1 A`` (spectrum in ``[-1, 1]``), one sparse
  product per degree, for all the ``n`` of a ladder at once.  ``(1 - lam k)^-n`` is analytic up
  to ``k = 1 / lam``, so its Chebyshev coefficients fall geometrically: 21 terms at ``n = 30``,
  32 at ``n = 95`` (:data:`COEFFICIENT_FLOOR`).  The input's rounding is amplified by up to
  ``0.8^-n`` (:data:`MAX_ITERATIONS`).
* **Which ``n``.**  The detector does not know the number of iterations, and a wrong ``n'``
  leaves (or adds) a filter ``(1 - lam k)^(n - n')``: on the bunny, ``n' = 20`` or ``40`` for
  ``n = 30`` left 42 % and 16 % of the carriers on the wrong side, and ``n' = 28`` did not read
  the weakly marked cycloidal gear (ellipsoids) where ``n' = 30`` did.  The carriers' votes agree
  within their slots only near the right ``n`` (:class:`Scorer`: the detector's agreement test,
  one vote per label), so ``n`` is chosen by it: a ladder of :data:`LADDER` iterations about
  ``2^(1/4)`` apart, then the integers between the best rung's neighbours, each set from one
  recurrence, read at the scored carriers' rings only.  The agreement does not change when the
  votes of a slot all change sign, so choosing by it leaves the chance that random bits pass a
  CRC as it was: the detector decodes the one unsmoothed mesh (when the agreement reaches
  :data:`MIN_SCORE`), and counts it as one more file read.  After 0.1 x 30, planes picked the
  exact ``n`` on 6 of the 8 shared meshes tried (horse 29, beetle 33), ellipsoids 29-36 (a
  slightly sharpened mesh agrees more); every one of them read.
* **Other smoothing.**  The ladder inverts ``lam = LAMBDA``; another step is matched
  approximately by some ``n`` (``(1 - lam k)^n`` and ``(1 - lam' k)^n'`` agree to first order
  when ``lam n = lam' n'``).  Measured on the bunny (both methods; dragon, ellipsoids): 0.3 x 10,
  0.05 x 60, 0.5 x 6, 0.2 x 15, trimesh's ``filter_laplacian`` (0.5 x 10, and 0.1 x 30 with its
  volume constraint) and ``filter_humphrey`` all read, at ``n`` 25-76.  Not undone: noise of
  1e-3 of the diagonal or quantisation to 12 bits *after* 0.1 x 30 (the inverse amplifies them
  up to 800 times; noise of 1e-4, 16 bits, float32 storage, noise *before* the smoothing and
  crops before or after it read).

Nothing here needs more than the suspect's connectivity and the carriers' analyses; the detector
tries this view last, only when nothing else reads (:func:`core.pipeline._detect_doc`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import scipy.sparse as sp

from core.analysis import Analysis, method_moments, ring_boundaries, statistic
from core.detection import adaptive_threshold, median
from core.mesh import Adjacency, adjacency
from core.parallel import halves_product
from core.slots import assign_slots
from core.tolerances import TOL, Tolerances

#: the smoothing step the inverse assumes (the benchmark's and the usual small step)
LAMBDA = 0.1
#: iterations tried first: 10 x 2^(i/4), 10 to 95 (lam x n from 1 to 9.5)
LADDER = tuple(round(10 * 2 ** (i / 4)) for i in range(14))
#: the largest number of iterations inverted (the rounding, see COEFFICIENT_FLOOR)
MAX_ITERATIONS = 100
#: at most this many integers are tried between the best rung's neighbours
REFINE_AT_MOST = 16
#: trailing Chebyshev coefficients below this share of the largest are dropped (the interpolation's
#: own rounding leaves them at 1e-15 to 1e-14 of it): 21 are kept at n = 30, 32 at n = 95; on the
#: bunny smoothed n times and unsmoothed, the largest error is 2e-9 (n = 30) and 1.2e-3 (n = 95) of
#: the median edge, 0.03 at n = 110 and 3 at n = 130 (the input's rounding, amplified 0.8^-n)
COEFFICIENT_FLOOR = 1e-13
#: degrees of the recurrence gathered before they are added to the outputs
ACCUMULATE_BLOCK = 8
#: degree of the Chebyshev interpolation the coefficients come from
INTERPOLATION_DEGREE = 64
#: carriers (of all parts) the choice of ``n`` looks at: a fixed, evenly spread subset above this
SCORE_CARRIERS = 20000
#: the unsmoothed mesh is decoded only when its agreement reaches this many standard deviations:
#: unmarked files read at most 2.5-4.6 (the largest over ~28 positions x 65 codeword lengths x 2
#: methods; 46 pairs of a shared mesh and a key), smoothed marked ones 8.5-660 (the least: the
#: bunny and the dragon smoothed 0.1 x 30 then given noise of 1e-4 of the diagonal)
MIN_SCORE = 6.0


def walk_matrix(adj: Adjacency) -> sp.csr_matrix:
    """``D^-1 A``: every row the mean over the vertex's neighbours (zero for an isolated vertex)."""
    n = len(adj.degree)
    off = adj.rows != adj.indices
    rows, cols = adj.rows[off], adj.indices[off]
    deg = np.bincount(rows, minlength=n).astype(np.float64)
    w = 1.0 / np.maximum(deg, 1.0)
    return sp.csr_matrix((w[rows], (rows, cols)), shape=(n, n))


def coefficients(iterations: float, lam: float = LAMBDA) -> np.ndarray:
    """Chebyshev coefficients of ``(1 - lam k)^-iterations`` on ``k`` in ``[0, 2]`` (variable
    ``x = k - 1``), interpolated at the Chebyshev points of degree :data:`INTERPOLATION_DEGREE`;
    trailing ones below :data:`COEFFICIENT_FLOOR` of the largest are dropped."""
    m = INTERPOLATION_DEGREE + 1
    theta = np.pi * (np.arange(m) + 0.5) / m
    values = (1.0 - lam * (np.cos(theta) + 1.0)) ** (-float(iterations))
    c = (2.0 / m) * (np.cos(np.outer(np.arange(m), theta)) @ values)
    c[0] /= 2.0
    big = np.abs(c) > COEFFICIENT_FLOOR * np.abs(c).max()
    return c[: int(np.flatnonzero(big)[-1]) + 1]


def unsmooth_at(vertices: np.ndarray, walk: sp.csr_matrix, iterations: Sequence[float],
                at: np.ndarray | None = None, lam: float = LAMBDA) -> np.ndarray:
    """``(I - lam K)^-n V`` for every ``n`` of ``iterations``, from one recurrence.

    Parameters
    ----------
    vertices : (n, 3) float64 ndarray
    walk : (n, n) sparse
        :func:`walk_matrix` of the mesh.
    iterations : sequence of float
    at : (q,) int64 ndarray, optional
        Only these vertices are returned (default: all).

    Returns
    -------
    (len(iterations), q, 3) float64 ndarray
        Isolated vertices (no neighbour: smoothing leaves them) are returned as they are.
    """
    v = np.ascontiguousarray(vertices, np.float64)
    cs = [coefficients(n, lam) for n in iterations]
    degree = max(len(c) for c in cs)
    c = np.zeros((len(cs), degree))
    for r, ci in enumerate(cs):
        c[r, : len(ci)] = ci
    q = len(v) if at is None else len(at)
    out = np.zeros((len(cs), q, 3))
    # T_j(X) v for X = K - I = -walk; several outputs gather a block of degrees at ``at`` and add it
    # to every output at once (one matrix product per block instead of one broadcast per degree),
    # one output of the whole mesh adds each degree in place (no block of whole-mesh copies)
    width = ACCUMULATE_BLOCK if len(cs) > 1 else 1
    block = np.empty((width if width > 1 else 0, q, 3))
    prev, cur = v, v
    product = halves_product(walk)  # a large mesh's rows in two threads
    for j in range(degree):
        if j == 1:
            cur = -product(v)
        elif j > 1:
            prev, cur = cur, -2.0 * product(cur) - prev
        if width == 1:
            out[0] += c[0, j] * (cur if at is None else cur[at])
            continue
        block[j % width] = cur if at is None else cur[at]
        if j % width == width - 1 or j == degree - 1:
            lo = j - j % width
            out += (c[:, lo:j + 1] @ block[: j - lo + 1].reshape(j - lo + 1, -1)).reshape(out.shape)
    isolated = np.asarray(walk.getnnz(axis=1) == 0)
    if at is not None:
        isolated = isolated[at]
    out[:, isolated] = (v if at is None else v[at])[isolated]
    return out


def unsmooth(vertices: np.ndarray, adj: Adjacency, iterations: float, lam: float = LAMBDA) -> np.ndarray:
    """The positions before ``iterations`` steps of uniform Laplacian smoothing of step ``lam``."""
    return unsmooth_at(vertices, walk_matrix(adj), [iterations], lam=lam)[0]


def _statistics(v: np.ndarray, adj: Adjacency, sel: np.ndarray, methods: Sequence[str],
                tol: Tolerances) -> dict[str, np.ndarray]:
    """``z`` of the carriers ``sel`` at positions ``v``, per method (0 where the ring is degenerate:
    no vote)."""
    mu, axes, lam, scale = ring_boundaries(v, adj, sel)
    ok = scale > 0
    safe = np.where(ok, scale, 1.0)
    out = {}
    for method in methods:
        lam_m = method_moments(method, lam, safe, tol)
        with np.errstate(divide="ignore", invalid="ignore"):
            z = statistic(method, v[sel], mu, axes, lam_m, safe, tol)
        out[method] = np.where(ok & np.isfinite(z), z, 0.0)
    return out


def _votes(z: np.ndarray) -> np.ndarray:
    """The adaptive variant's clipped soft votes (:func:`core.detection._soft_values`), centred."""
    zc = z - adaptive_threshold(z)
    w = median(np.abs(zc)) or 1.0
    u = np.clip(zc / w, -1.0, 1.0)
    return u - u.mean()


class Scorer:
    """The agreement of the carriers' votes at candidate positions, for the choice of ``n``.

    ``analyses``: the suspect file's connectivity carriers (one list of parts, one method: the
    carriers and slot hashes are the same for every method), at most :data:`SCORE_CARRIERS` of
    them kept, evenly spread; ``lengths``: the codeword lengths the detection tries.  The score of
    a length is the detector's agreement test (:func:`core.detection._agreement_z`) with one vote
    per *label*, the mean of the adaptive variant's votes of its carriers:
    ``(sum_j S_j^2 - sum w^2) / (mean w^2 sqrt(2 pairs))`` over its slots ``j`` (``S_j``: sum of
    the label votes ``w`` of slot ``j``; ``pairs``: ordered pairs of labels in one slot); the
    score of a position, the largest over the lengths.  Carriers of one label always share their
    slot and have alike statistics: counted one by one, their sums vary like ``c`` votes rather
    than ``sqrt(c)``, and the agreement of the unmarked bunny read 5-10 standard deviations with
    any key (the detector's test leaves out their pairs, but not their sums' variance).  With a
    vote per label, random slot maps read the largest of about N(0, 1) (2.5-3.8 over the ~28
    positions x 65 lengths x 2 methods on the unmarked bunny, six keys).  Keeping only the labels
    of one carrier is not enough: the CAD counter's 9349 carriers have 4 of them."""

    def __init__(self, analyses: list[Analysis], lengths: Sequence[int]) -> None:
        total = sum(len(a.carriers) for a in analyses)
        step = max(1, -(-total // SCORE_CARRIERS))
        keep = [np.arange(0, len(a.carriers), step) for a in analyses]
        self.carriers = [a.carriers[k] for a, k in zip(analyses, keep, strict=True)]
        hashes = [a.slot_hash for a in analyses]
        sub = np.concatenate([h[k] for h, k in zip(hashes, keep, strict=True)]) if analyses \
            else np.zeros(0, np.uint64)
        _, first, group, count = np.unique(sub, return_index=True, return_inverse=True, return_counts=True)
        self.group, self.count = group.ravel(), count.astype(np.float64)
        #: (L, slot of every label, ordered pairs of labels in one slot) per codeword length, the
        #: slots as the decoder assigns them over all the carriers (ranked or hashed)
        self.lengths: list[tuple[int, np.ndarray, float]] = []
        for L in sorted(set(lengths)) if analyses else []:
            slots = np.concatenate([s[k] for s, k in zip(assign_slots(hashes, L), keep, strict=True)])[first]
            n = np.bincount(slots, minlength=L).astype(np.float64)
            pairs = float((n * (n - 1)).sum())
            if pairs > 0:
                self.lengths.append((L, slots, pairs))

    def scores(self, zs: list[list[np.ndarray]]) -> list[float]:
        """Per position, the largest agreement (standard deviations) over the codeword lengths of
        the kept carriers' statistics (``zs``: per position one array per part, in the kept
        carriers' order); 0 without two labels in one slot.  One vote per label and position,
        then every position's slot sums of a codeword length in one ``bincount`` (each position's
        votes added in the order they would be alone: the same figures bit for bit)."""
        if not self.lengths:
            return [0.0] * len(zs)
        w = np.stack([np.bincount(self.group, _votes(np.concatenate(z))) / self.count for z in zs])
        w -= w.mean(axis=1, keepdims=True)
        sq = (w * w).sum(axis=1)
        var = sq / w.shape[1]
        flat, rows = w.ravel(), np.arange(len(zs))[:, None]
        best = np.zeros(len(zs))
        for L, slots, pairs in self.lengths:
            s = np.bincount((slots + L * rows).ravel(), flat, minlength=L * len(zs)).reshape(-1, L)
            with np.errstate(divide="ignore", invalid="ignore"):  # var 0: every vote alike, scored 0
                best = np.maximum(best, ((s * s).sum(axis=1) - sq) / (var * np.sqrt(2.0 * pairs)))
        return [float(b) if v > 0 else 0.0 for b, v in zip(best, var, strict=True)]


def ring_mesh(adjs: Sequence[Adjacency], carriers: Sequence[np.ndarray]
              ) -> tuple[np.ndarray, Adjacency, np.ndarray]:
    """The 1-rings of the ``carriers`` of several meshes as one mesh of their own, the meshes'
    vertices numbered one after another: its vertices (the carriers and their neighbours, sorted),
    the adjacency of the carriers' faces on them, and the carriers' places among them.  Every
    carrier keeps its neighbours in their order and its face of
    :meth:`~core.mesh.Adjacency.corner`, so its ring statistics there are its own mesh's, bit for
    bit, whatever the positions of the other vertices."""
    rings, faces, places, base, size = [], [], [], 0, 0
    for adj, c in zip(adjs, carriers, strict=True):
        ring = np.unique(np.concatenate([c, adj.indices[adj.ring_entries(c)[1]]]))
        touches = np.zeros(len(adj.degree), bool)
        touches[c] = True
        faces.append(np.searchsorted(ring, adj.faces[touches[adj.faces].any(axis=1)]) + size)
        places.append(np.searchsorted(ring, c) + size)
        rings.append(ring + base)
        base, size = base + len(adj.degree), size + len(ring)
    return (np.concatenate(rings), adjacency(np.concatenate(faces).reshape(-1, 3), size),
            np.concatenate(places))


def choose_iterations(parts: list[tuple[np.ndarray, Adjacency]], analyses: dict[str, list[Analysis]],
                      lengths: Sequence[int], tol: Tolerances = TOL) -> tuple[int, float]:
    """The number of iterations (step :data:`LAMBDA`) whose inverse makes the carriers' votes
    agree best, and that agreement (standard deviations; the largest over the methods).

    ``parts``: each part's (smoothed) vertices and adjacency; ``analyses``: per method, the
    suspect's connectivity analyses of those parts."""
    methods = list(analyses)
    scorer = Scorer(analyses[methods[0]], lengths)
    live = [k for k in range(len(parts)) if len(scorer.carriers[k])]
    if not live:
        return LADDER[0], 0.0
    # the parts as one mesh; the statistics read only the carriers' rings, so each position is read
    # on their mesh alone (:func:`ring_mesh`)
    vertices = np.concatenate([parts[k][0] for k in live]).astype(np.float64, copy=False)
    walks = [walk_matrix(parts[k][1]) for k in live]
    walk = walks[0] if len(walks) == 1 else sp.block_diag(walks, format="csr")
    rings, local, sel = ring_mesh([parts[k][1] for k in live], [scorer.carriers[k] for k in live])

    def scores(ns: list[int]) -> list[float]:
        z = [_statistics(at, local, sel, methods, tol) for at in unsmooth_at(vertices, walk, ns, rings)]
        per_method = [scorer.scores([[zi[m]] for zi in z]) for m in methods]
        return [max(s) for s in zip(*per_method, strict=True)]

    ladder = [n for n in LADDER if n <= MAX_ITERATIONS]
    tried = dict(zip(ladder, scores(ladder), strict=True))
    best = max(tried, key=lambda n: tried[n])
    i = ladder.index(best)
    lo = ladder[i - 1] if i > 0 else max(1, 2 * best - ladder[i + 1])
    hi = ladder[i + 1] if i + 1 < len(ladder) else min(MAX_ITERATIONS, 2 * best - ladder[i - 1])
    between = [n for n in range(lo + 1, hi) if n not in tried]
    if len(between) > REFINE_AT_MOST:
        between = sorted({between[int(j)] for j in np.linspace(0, len(between) - 1, REFINE_AT_MOST)})
    if between:
        tried.update(zip(between, scores(between), strict=True))
    best = max(tried, key=lambda n: tried[n])
    return best, tried[best]

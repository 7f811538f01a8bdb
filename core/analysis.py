"""The detector's view of a mesh: its carriers under a key, their boundaries and statistics.

A carrier ``i`` (chosen by :mod:`core.sync`) is described by its neighbours only: their mean
``mu`` (eq. 2) and covariance ``Sigma`` (eq. 3), eigenvalues ``l1 <= l2 <= l3`` with eigenvectors
``e1, e2, e3``, and the local scale ``s = sqrt(trace Sigma)``.  The statistic ``z`` is
dimensionless (a length divided by ``s``), so similarity transforms change nothing; ``z > 0``
reads bit 0 (outside the boundary), ``z < 0`` bit 1 (inside).  Constants are fields of
:class:`~core.tolerances.Tolerances`.

``planes`` (eqs. 15-20)
    ``Q = e1`` (the least-variance axis of the neighbours: the paper's mean normal depends on the
    carrier itself), ``Psi = sqrt(l1)`` (eq. 16).  ``z = (|(V - mu).Q| - tau) / s`` with
    ``tau = max(Psi, plane_floor * s)``.
``ellipsoids`` (eqs. 21-25)
    Mahalanobis radius ``rho`` of ``V`` in ``Sigma + alpha s^2 I`` against ``K = radius``;
    ``z = (rho - K) sqrt(l1') / s``, the distance to the ellipsoid along ``e1`` in units of ``s``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np

from core.coding import COMPACT_BELOW
from core.eig3 import eigh3
from core.geosync import Placement, Rings, geometric_carriers
from core.hashing import derive, mix64
from core.mesh import Adjacency, adjacency, columns, neighbour_moments, oriented
from core.options import METHODS
from core.parallel import by_rows
from core.sync import TIE_BITS, Labels, select_carriers, tie_broken, vertex_labels
from core.tolerances import TOL, Tolerances


@dataclass
class Analysis:
    """Carriers of one mesh under one key and method, with their boundaries and statistics.

    Attributes
    ----------
    carriers : (k,) int64 ndarray
        Vertex indices.
    slot_hash : (k,) uint64 ndarray
        Keyed hash of each carrier's label, which decides its codeword slot (:mod:`core.slots`).
    z : (k,) float64 ndarray
        Signed statistic: > 0 reads bit 0, < 0 reads bit 1.
    mu : (k, 3) float64 ndarray
        Mean of each carrier's neighbours.
    axes : (k, 3, 3) float64 ndarray
        Eigenvectors (columns) of the neighbours' covariance, by ascending eigenvalue.
    lam : (k, 3) float64 ndarray
        Eigenvalues (regularised for ``ellipsoids``).
    scale : (k,) float64 ndarray
        Local scale ``s``.
    regular : bool
        The labels used the geometric fallback of regular meshes.
    geometric : bool
        The carriers were chosen by position in the surface's frame (:mod:`core.geosync`), their
        slot hashes are cell hashes, and their slots are always hashed (never ranked).
    muted : (k,) bool ndarray, optional
        Carriers that keep their slots but do not vote (a connectivity carrier that is also a
        geometric carrier of the same view, read as the latter).
    signed : (k,) float64 ndarray, optional
        :func:`signed_statistic` of every carrier (what the detector's signed variant reads).
    """

    carriers: np.ndarray
    slot_hash: np.ndarray
    z: np.ndarray
    mu: np.ndarray
    axes: np.ndarray
    lam: np.ndarray
    scale: np.ndarray
    regular: bool
    geometric: bool = False
    muted: np.ndarray | None = None
    signed: np.ndarray | None = None

    def copy(self) -> Analysis:
        """A copy whose arrays the embedder may change in place."""
        return self.subset(np.arange(len(self.carriers)))

    def subset(self, which: np.ndarray) -> Analysis:
        """The carriers selected by ``which`` (a boolean mask or indices)."""
        return Analysis(self.carriers[which], self.slot_hash[which], self.z[which], self.mu[which],
                        self.axes[which], self.lam[which], self.scale[which], self.regular, self.geometric,
                        None if self.muted is None else self.muted[which],
                        None if self.signed is None else self.signed[which])


#: vertices from which equal priorities are told apart by geometry: on smaller meshes a carrier's
#: move is a large share of an edge, moves the tie-break of its neighbours and changes the
#: selection (the Sink's parts: the key code no longer read back)
TIE_BREAK_FROM = 2000


def _key_salts(key: str | bytes) -> tuple[np.uint64, np.uint64]:
    return np.uint64(derive(key, "meshmark-prio")), np.uint64(derive(key, "meshmark-slot"))


def statistic(method: str, v: np.ndarray, mu: np.ndarray, axes: np.ndarray, lam: np.ndarray,
              scale: np.ndarray, tol: Tolerances = TOL) -> np.ndarray:
    """Signed, dimensionless side of the boundary of carriers at positions ``v``.

    Parameters
    ----------
    method : str
        ``"planes"`` or ``"ellipsoids"``.
    v, mu : (k, 3) float64 ndarray
        Carrier positions and their neighbours' means.
    axes : (k, 3, 3) float64 ndarray
    lam : (k, 3) float64 ndarray
        Eigenvectors and eigenvalues (regularised for ``ellipsoids``).
    scale : (k,) float64 ndarray

    Returns
    -------
    (k,) float64 ndarray
        ``z``: > 0 outside the boundary (bit 0), < 0 inside (bit 1).
    """
    return _statistic(method, v, mu, axes, lam, scale, tol, None)


#: connectivity carriers (of a file, in one method) from which the embedder puts carriers on their
#: keyed sides and the detector reads the signed statistic (:data:`core.detection.SIGNED`): fewer
#: do not survive noise at any payload length, and every decoding variant adds to the false positives
SIGNED_FROM = COMPACT_BELOW

#: what :func:`keyed_sides` mixes into a slot hash before taking its top bit
_SIDE_SALT = np.uint64(0x5D1E5D1E5D1E5D1E)


def keyed_sides(slot_hash: np.ndarray) -> np.ndarray:
    """The side (+1: the one the faces call outside, -1: inside; :func:`core.mesh.oriented`) on which
    the embedder puts each carrier that it moves outside its boundary: one keyed bit of the carrier's
    slot hash, so that half the marks go out and half in (all outwards would inflate the surface, and
    move the frame of the geometric layer, by a little every time)."""
    return np.where(mix64(np.asarray(slot_hash, np.uint64) ^ _SIDE_SALT) >> np.uint64(63), -1.0, 1.0)


def signed_statistic(method: str, v: np.ndarray, mu: np.ndarray, axes: np.ndarray, lam: np.ndarray,
                     scale: np.ndarray, sides: np.ndarray, tol: Tolerances = TOL) -> np.ndarray:
    """:func:`statistic` with the offset along the oriented axis ``e1`` (:func:`core.mesh.oriented`)
    kept signed, towards the carrier's keyed side ``sides`` (:func:`keyed_sides`): equal to it on
    that side, and on the other the boundary's mirror image (planes ``(y0 - tau) / s``; ellipsoids
    the radius with the sign of ``y0``).  The embedder puts the carriers it moves outside on their
    keyed side, so attacks that add zero-mean errors (noise, quantisation) move this statistic
    linearly where ``|y0|`` moves by their square: what the detector's
    :data:`~core.detection.SIGNED` variant reads."""
    return _statistic(method, v, mu, axes, lam, scale, tol, sides)


def plane_width(lam: np.ndarray, scale: np.ndarray, tol: Tolerances = TOL) -> np.ndarray:
    """``planes``: the half-width ``tau = max(sqrt(l1), plane_floor * s)`` of each carrier's planes."""
    return np.maximum(np.sqrt(np.maximum(lam[:, 0], 0.0)), tol.plane_floor * scale)


def _statistic(method: str, v: np.ndarray, mu: np.ndarray, axes: np.ndarray, lam: np.ndarray,
               scale: np.ndarray, tol: Tolerances, sides: np.ndarray | None) -> np.ndarray:
    y = np.einsum("kij,ki->kj", axes, v - mu)  # coordinates in the eigenbasis
    if method == "planes":
        tau = plane_width(lam, scale, tol)
        return ((np.abs(y[:, 0]) if sides is None else sides * y[:, 0]) - tau) / scale
    rho = np.sqrt((y * y / lam).sum(axis=1))
    if sides is not None:
        rho = np.where(sides * y[:, 0] < 0, -rho, rho)
    return (rho - tol.radius) * np.sqrt(lam[:, 0]) / scale


def slot_hashes(labels: Labels, key: str | bytes, chosen: np.ndarray) -> np.ndarray:
    """Keyed hash of the labels of the connectivity carriers ``chosen``: their slots' hashes."""
    return mix64(labels.labels[chosen] ^ _key_salts(key)[1])


def _surface(lam: np.ndarray, scale: np.ndarray, tol: Tolerances) -> np.ndarray:
    """Rings that span a surface: not a point, not a line (``l2 > min_flatness * l3``)."""
    return (scale > 0) & (lam[:, 1] > tol.min_flatness * np.maximum(lam[:, 2], 1e-300))


def priorities(vertices: np.ndarray, adj: Adjacency, labels: Labels, key: str | bytes) -> np.ndarray:
    """Keyed selection priority of every vertex: a hash of its label, with the geometric tie-break
    of :func:`~core.sync.tie_broken` from :data:`TIE_BREAK_FROM` vertices."""
    prio = mix64(labels.labels ^ _key_salts(key)[0])
    return tie_broken(prio, vertices, adj) if len(vertices) >= TIE_BREAK_FROM else prio


def same_order(before: np.ndarray, after: np.ndarray, adj: Adjacency,
               pairs: tuple[np.ndarray, np.ndarray] | None = None) -> bool:
    """Whether two priority vectors order every pair of neighbours alike (ties included), i.e.
    give the same greedy selection (:func:`~core.sync.select_carriers` only compares neighbours).
    ``pairs``: :func:`tied_pairs` of either, when the two differ only in their tie-break."""
    a, b = (adj.rows, adj.indices) if pairs is None else pairs
    return bool(np.array_equal(before[a] > before[b], after[a] > after[b])
                and np.array_equal(before[a] == before[b], after[a] == after[b]))


def tied_pairs(prio: np.ndarray, adj: Adjacency) -> tuple[np.ndarray, np.ndarray]:
    """The neighbours (both directions) whose priorities have the same label hash above the
    tie-break's :data:`~core.sync.TIE_BITS`: the only pairs that two priority vectors of the same
    labels (:func:`priorities` at other positions) can order differently, the others being
    ordered by those bits alone."""
    high = prio >> np.uint64(TIE_BITS)
    t = np.flatnonzero(high[adj.rows] == high[adj.indices])
    return adj.rows[t], adj.indices[t]


def _within_scale(scale: np.ndarray, ok: np.ndarray, n: int, tol: Tolerances) -> np.ndarray:
    """``ok`` without the carriers whose scale exceeds the median of those it keeps by more than
    ``tol.max_scale`` times on a mesh of ``n`` vertices (``tol.max_scale_small`` below
    :data:`TIE_BREAK_FROM`)."""
    if not ok.any():
        return ok
    limit = tol.max_scale if n >= TIE_BREAK_FROM else tol.max_scale_small
    return ok & (scale <= limit * np.median(scale[ok]))


def analyse_methods(vertices: np.ndarray, faces: np.ndarray, key: str | bytes, methods: Sequence[str],
                    adj: Adjacency | None = None, labels: Labels | None = None,
                    tol: Tolerances = TOL, prio: np.ndarray | None = None) -> dict[str, Analysis]:
    """Select the carriers of a mesh and read their statistics (the detector's view).

    Parameters
    ----------
    vertices : (n, 3) float64 ndarray
    faces : (m, 3) int64 ndarray
    key : str or bytes
    methods : sequence of str
        Names from :data:`~core.options.METHODS`.
    adj, labels : optional
        The mesh's adjacency and :func:`~core.sync.vertex_labels`, when the caller has them.
    prio : (n,) uint64 ndarray, optional
        The vertices' :func:`priorities` under ``key`` at these positions, when the caller has them.

    Returns
    -------
    dict of str to Analysis
        One per method.  The carriers and their neighbourhoods do not depend on the method, only
        the statistic does, so the methods share one selection.
    """
    for method in methods:
        if method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}")
    v = np.asarray(vertices, np.float64)
    if adj is None:
        adj = adjacency(faces, len(v))
    if labels is None:
        labels = vertex_labels(v, adj)
    if prio is None:
        prio = priorities(v, adj, labels, key)
    sel = select_carriers(adj, prio, labels.usable)
    return carrier_statistics(v, adj, sel, lambda chosen: slot_hashes(labels, key, chosen), methods,
                              labels.regular, False, tol)


def vertex_pool(vertices: np.ndarray, adj: Adjacency, labels: Labels, methods: Sequence[str],
                tol: Tolerances = TOL) -> dict[str, Analysis]:
    """Per method, the boundary and statistic of every usable vertex as if it were a carrier (the
    scale test against the median of them all), for a search that selects carriers many times on
    the same positions (:func:`pooled`); slot hashes 0."""
    sel = np.flatnonzero(labels.usable)
    v = np.asarray(vertices, np.float64)
    return carrier_statistics(v, adj, sel, np.zeros(len(sel), np.uint64), methods, labels.regular, False, tol)


def pooled(pool: Analysis, labels: Labels, key: str | bytes, prio: np.ndarray, adj: Adjacency) -> Analysis:
    """The carriers :func:`select_carriers` chooses by ``prio``, read from ``pool``
    (:func:`vertex_pool`) with their slot hashes under ``labels``: what :func:`analyse_methods`
    gives but for the scale test (here against every usable vertex, there against the carriers)."""
    sel = select_carriers(adj, prio, labels.usable)
    if not len(pool.carriers) or not len(sel):
        return pool.subset(np.zeros(0, np.int64))
    at, held = _rows_in(pool.carriers, sel)
    got = pool.subset(at[held])
    return replace(got, slot_hash=slot_hashes(labels, key, got.carriers))


def ring_boundaries(v: np.ndarray, adj: Adjacency, sel: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """First and second moments of the 1-rings of the vertices ``sel``: the ring means ``mu``,
    principal axes (the least-variance one :func:`~core.mesh.oriented`), moments ``lam`` (clipped at
    0) and scale ``sqrt(sum lam)``; a large ``sel`` in two threads (:func:`~core.parallel.by_rows`)."""

    cols = columns(v)

    def rows(part: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        mu, sigma = neighbour_moments(v, adj, part, cols)
        lam, axes = eigh3(sigma)
        lam = np.maximum(lam, 0.0)
        return mu, oriented(v, adj, part, mu, axes), lam, np.sqrt(lam.sum(axis=1))

    mu, axes, lam, scale = by_rows(rows, np.asarray(sel, np.int64))
    return mu, axes, lam, scale


def method_moments(method: str, lam: np.ndarray, scale: np.ndarray, tol: Tolerances = TOL) -> np.ndarray:
    """The moments a method's boundary uses: the ring's, widened by ``tol.alpha`` scale^2 for
    ``ellipsoids`` (a flat ring's ellipsoid keeps a thickness)."""
    return lam + tol.alpha * (scale**2)[:, None] if method == "ellipsoids" else lam


def carrier_statistics(v: np.ndarray, adj: Adjacency, sel: np.ndarray,
                       slot_hash: np.ndarray | Callable[[np.ndarray], np.ndarray], methods: Sequence[str],
                       regular: bool, geometric: bool, tol: Tolerances = TOL) -> dict[str, Analysis]:
    """Boundaries and statistics of the chosen vertices ``sel``, one :class:`Analysis` per method.

    Vertices whose neighbourhood is a line or far coarser than the others' (``tol.min_flatness``,
    ``tol.max_scale``) are dropped.  ``slot_hash``: one per vertex of ``sel``, or a function of the
    kept vertices."""
    mu, axes, lam, scale = ring_boundaries(v, adj, sel)
    ok = _surface(lam, scale, tol)
    ok = _within_scale(scale, ok, len(v), tol)
    sel, mu, axes, lam, scale = sel[ok], mu[ok], axes[ok], lam[ok], scale[ok]
    hashes = slot_hash(sel) if callable(slot_hash) else np.asarray(slot_hash)[ok]
    out = {}
    for method in methods:
        lam_m = method_moments(method, lam, scale, tol)
        z = statistic(method, v[sel], mu, axes, lam_m, scale, tol)
        # the geometric layer's carriers stay on their sides (crossing, they turn their neighbours'
        # tangent planes and change which vertex is nearest a cell's centre: more rounds)
        t = None if geometric else signed_statistic(method, v[sel], mu, axes, lam_m, scale,
                                                    keyed_sides(hashes), tol)
        out[method] = Analysis(sel, hashes, z, mu, axes, lam_m, scale, regular, geometric, signed=t)
    return out


def _rows_in(carriers: np.ndarray, sel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each vertex of ``sel``, its row in the sorted, non-empty ``carriers`` of an analysis and
    whether it is one of them (the row is meaningless where it is not)."""
    at = np.minimum(np.searchsorted(carriers, sel), len(carriers) - 1)
    return at, carriers[at] == sel


def reanalysed(prev: Analysis, v: np.ndarray, adj: Adjacency, labels: Labels, key: str | bytes, method: str,
               prio: np.ndarray, moved: np.ndarray, tol: Tolerances = TOL) -> Analysis:
    """:func:`analyse` of the connectivity layer at positions ``v`` with priorities ``prio``, equal to
    it array for array, reading only the carriers that ``prev`` cannot give.

    ``prev``: an analysis of the same mesh, labels and method whose boundaries were read while no
    vertex of the mask ``moved`` had moved, and whose statistics are those at ``v`` (what the
    embedder keeps: it reads a carrier again when it moves it).  A carrier of both selections with
    no moved neighbour keeps ``prev``'s boundary, its ring being where it was (and it passed the
    flatness test then); the others are read.  The scale test (against the median of every
    selected carrier's) is made again over the whole selection, as :func:`carrier_statistics` does."""
    sel = select_carriers(adj, prio, labels.usable)
    if not len(prev.carriers) or prev.signed is None or prev.geometric:
        return analyse(v, adj.faces, key, method, adj=adj, labels=labels, tol=tol, prio=prio)
    at, held = _rows_in(prev.carriers, sel)
    ring_moved = adj.ring_sum_u64(moved.astype(np.uint64)) > 0
    reuse = held & ~ring_moved[sel]
    at, fresh = at[reuse], np.flatnonzero(~reuse)
    k = len(sel)
    mu, axes, lam, scale = np.empty((k, 3)), np.empty((k, 3, 3)), np.empty((k, 3)), np.empty(k)
    z, signed = np.empty(k), np.empty(k)
    mu[reuse], axes[reuse], lam[reuse] = prev.mu[at], prev.axes[at], prev.lam[at]
    scale[reuse], z[reuse], signed[reuse] = prev.scale[at], prev.z[at], prev.signed[at]
    f_mu, f_axes, f_lam, f_scale = ring_boundaries(v, adj, sel[fresh])
    ok = np.ones(k, bool)
    ok[fresh] = _surface(f_lam, f_scale, tol)
    mu[fresh], axes[fresh], scale[fresh] = f_mu, f_axes, f_scale
    lam[fresh] = method_moments(method, f_lam, f_scale, tol)
    ok = _within_scale(scale, ok, len(v), tol)
    hashes = slot_hashes(labels, key, sel)
    read = fresh[ok[fresh]]
    args = (method, v[sel[read]], mu[read], axes[read], lam[read], scale[read])
    z[read] = statistic(*args, tol)
    signed[read] = signed_statistic(*args, keyed_sides(hashes[read]), tol)
    return Analysis(sel[ok], hashes[ok], z[ok], mu[ok], axes[ok], lam[ok], scale[ok], labels.regular, False,
                    signed=signed[ok])


#: the statistic the geometric layer's carriers are moved and read with, whichever method the file
#: is marked with (the method then only says how the connectivity layer is read).  Ellipsoids cost
#: more per mark (a ring flatter than the ellipsoid's floor, alpha s^2, must be left by more than
#: that floor) and under the RMS budget read weaker: the rocker arm's geometric carriers read right
#: 0.75 untouched with ellipsoids, 0.98 with planes; the gear's ellipsoid layer did not read alone.
#: Engine table, ellipsoid rows (stop 30): 8 cells gained, none lost
GEOMETRIC_METHOD = "planes"


def analyse_geometric(vertices: np.ndarray, adj: Adjacency, key: str | bytes, methods: Sequence[str],
                      placement: Placement, tol: Tolerances = TOL,
                      chosen: tuple[np.ndarray, np.ndarray] | None = None,
                      rings: Rings | None = None) -> dict[str, Analysis]:
    """The geometric carriers of a mesh (:func:`core.geosync.geometric_carriers` at ``placement``,
    or ``chosen`` when the caller has them) and their statistics (``geometric=True``): the same
    :class:`Analysis`, read with :data:`GEOMETRIC_METHOD`, under every method of ``methods``;
    ``rings``: the mesh's kept ring axes, when the caller has them."""
    v = np.asarray(vertices, np.float64)
    if chosen is None:
        chosen = geometric_carriers(v, adj, placement.frame, placement.axes, placement.rung, key, rings)
    sel, cell_hash = chosen
    got = carrier_statistics(v, adj, sel, cell_hash, [GEOMETRIC_METHOD], False, True, tol)[GEOMETRIC_METHOD]
    return dict.fromkeys(methods, got)


def geometric_read(known: Sequence[Analysis], vertices: np.ndarray, adj: Adjacency,
                   chosen: tuple[np.ndarray, np.ndarray], tol: Tolerances = TOL) -> Analysis:
    """:func:`analyse_geometric` at the carriers ``chosen`` (vertices, cell hashes), equal to it array
    for array, reading only the carriers that no analysis of ``known`` holds.

    ``known``: geometric analyses (carriers sorted, as every analysis has them) whose every row is
    current at ``vertices`` (the boundary from the present positions of the carrier's neighbours, the
    statistic from its own), as the embedder keeps its own (:meth:`core.embedding._Mesh.round` reads
    again what a move changes).  A row taken from them is tested again for a surface (a neighbour's
    move may have flattened its ring), and the scale test (against the median of every kept
    carrier's) is made over the whole choice, as :func:`carrier_statistics` does."""
    v = np.asarray(vertices, np.float64)
    sel, hashes = np.asarray(chosen[0], np.int64), np.asarray(chosen[1], np.uint64)
    known = [a for a in known if len(a.carriers)]
    if not known or not len(sel) or GEOMETRIC_METHOD != "planes":
        # (other moments than the ring's are kept for another statistic: the surface test needs these)
        return carrier_statistics(v, adj, sel, hashes, [GEOMETRIC_METHOD], False, True, tol)[GEOMETRIC_METHOD]
    k = len(sel)
    mu, axes, lam = np.empty((k, 3)), np.empty((k, 3, 3)), np.empty((k, 3))
    scale, z = np.empty(k), np.empty(k)
    have = np.zeros(k, bool)
    for a in known:
        at, held = _rows_in(a.carriers, sel)
        # (a scale below 1e-300 was read with a floor in the embedder's re-reading: read it afresh)
        hit = ~have & held & (a.scale[at] >= 1e-300)
        src = at[hit]
        mu[hit], axes[hit], lam[hit] = a.mu[src], a.axes[src], a.lam[src]
        scale[hit], z[hit] = a.scale[src], a.z[src]
        have |= hit
    fresh = np.flatnonzero(~have)
    mu[fresh], axes[fresh], lam[fresh], scale[fresh] = ring_boundaries(v, adj, sel[fresh])
    ok = _within_scale(scale, _surface(lam, scale, tol), len(v), tol)
    read = fresh[ok[fresh]]
    z[read] = statistic(GEOMETRIC_METHOD, v[sel[read]], mu[read], axes[read], lam[read], scale[read], tol)
    return Analysis(sel[ok], hashes[ok], z[ok], mu[ok], axes[ok], lam[ok], scale[ok], False, True)


def analyse(vertices: np.ndarray, faces: np.ndarray, key: str | bytes, method: str,
            adj: Adjacency | None = None, labels: Labels | None = None,
            tol: Tolerances = TOL, prio: np.ndarray | None = None) -> Analysis:
    """:func:`analyse_methods` for one method."""
    return analyse_methods(vertices, faces, key, [method], adj, labels, tol, prio)[method]


def prepare(vertices: Sequence[np.ndarray], faces: Sequence[np.ndarray]) -> list[tuple[Adjacency, Labels]]:
    """Adjacency and keyless labels of each mesh: what every analysis of it needs first."""
    out = []
    for v, f in zip(vertices, faces, strict=True):
        adj = adjacency(f, len(v))
        out.append((adj, vertex_labels(np.asarray(v, np.float64), adj)))
    return out

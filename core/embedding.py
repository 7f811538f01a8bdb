"""Moving carriers across their boundaries, verified after the file's own rounding.

A carrier on the wrong side of its boundary, or too close to it, moves to ``|z| = strength``:
along ``e1`` (planes; ellipsoids when the tangential part fits inside), or to the closest point of
the inner ellipsoid (ellipsoid bit 1 with a large tangential offset).  Boundaries never depend on
the carrier itself, and carriers are never adjacent, so moving one changes no carrier's boundary.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import Future
from dataclasses import dataclass
from functools import partial

import numpy as np

from core.analysis import (
    GEOMETRIC_METHOD,
    SIGNED_FROM,
    Analysis,
    analyse,
    geometric_read,
    keyed_sides,
    method_moments,
    plane_width,
    prepare,
    priorities,
    reanalysed,
    ring_boundaries,
    same_order,
    signed_statistic,
    statistic,
    tied_pairs,
)
from core.geosync import Placement, Rings, follow, geometric_carriers
from core.mesh import Adjacency, bbox_diagonal, changed_rows
from core.parallel import SPLIT_FROM, beside, by_rows
from core.slots import assign_slots, ranked_by_default
from core.sync import Labels, vertex_labels
from core.tolerances import TOL, Tolerances

#: what storing positions in the file does to them (float32, printed decimals)
#: ``quantize(mesh, vertex_indices, positions)``: what storing those vertices of that mesh gives
Quantize = Callable[[int, np.ndarray, np.ndarray], np.ndarray]
#: ``slot_rule(slot_hashes, length)``: the codeword slot of every carrier of every part
SlotRule = Callable[[list[np.ndarray], int], list[np.ndarray]]
#: pairs of neighbours, (rows, columns) (:func:`~core.analysis.tied_pairs`)
Pairs = tuple[np.ndarray, np.ndarray]


def target_positions(method: str, a: Analysis, v: np.ndarray, bits: np.ndarray, margin: float,
                     tol: Tolerances = TOL, keyed: bool = True) -> np.ndarray:
    """Positions that put carriers on the side of ``bits`` with ``|z| = margin``.

    Parameters
    ----------
    method : str
    a : Analysis
        The carriers' boundaries.
    v : (k, 3) float64 ndarray
        The carriers' current positions.
    bits : (k,) uint8 ndarray
        The bit each carrier must read.
    margin : float
    keyed : bool
        Carriers moved outside their boundary go to their keyed side of the ring where that is not
        much further (:func:`_side`), when ``a`` has a signed statistic (the geometric layer has
        none); False: every carrier stays on its side.

    Returns
    -------
    (k, 3) float64 ndarray
        New positions; carriers already on the right side with at least ``margin`` keep theirs.
    """
    want = np.where(bits == 0, 1.0, -1.0)  # sign of z wanted
    z = statistic(method, v, a.mu, a.axes, a.lam, a.scale, tol)
    need = want * z < margin
    y = np.einsum("kij,ki->kj", a.axes, v - a.mu)
    # keyed sides for the carriers whose signed statistic the detector reads (not the geometric
    # layer's: analysis.carrier_statistics)
    sides = keyed_sides(a.slot_hash) if keyed and a.signed is not None else None
    s = a.scale
    if method == "planes":
        tau = plane_width(a.lam, s, tol)
        target = np.maximum(tau + want * margin * s, 0.0)
        y[:, 0] = _side(y[:, 0], target, want, sides) * target
    else:
        l1 = a.lam[:, 0]
        rho_t = np.maximum(tol.radius + want * margin * s / np.sqrt(l1), 0.0)
        rt = (y[:, 1:] ** 2 / a.lam[:, 1:]).sum(axis=1)
        fits = rho_t**2 >= rt
        y0 = np.sqrt(np.maximum(rho_t**2 - rt, 0.0) * l1)
        sgn = _side(y[:, 0], y0, want, sides)
        out = y.copy()
        out[fits, 0] = sgn[fits] * y0[fits]
        far = ~fits
        if far.any():
            yf = y[far]
            yf[:, 0] = sgn[far] * np.abs(yf[:, 0])
            out[far] = closest_on_ellipsoid(yf, rho_t[far, None] * np.sqrt(a.lam[far]))
        y = out
    new = a.mu + np.einsum("kij,kj->ki", a.axes, y)
    return np.where(need[:, None], new, v)


#: a carrier moved outside its boundary goes to its keyed side of its ring
#: (:func:`core.analysis.keyed_sides`) unless it is more than this share of its target offset on
#: the other side (``bench.attack_ab``, 234 attacked detections: the nearest side 151; every moved
#: carrier outwards unless 0.25 / 0.5 / 1.0 of it inside 154 / 159 / 157; keyed sides at 0.5, 160;
#: core/README.md, section 3)
KEYED_SIDE_FROM = 0.5


def deepest(method: str, a: Analysis, tol: Tolerances = TOL) -> np.ndarray:
    """The largest ``-z`` (bit 1) each carrier of ``a`` can read, at its ring's mean: ``tau / s``
    for ``planes`` (``|y0| = 0``), ``K sqrt(l1') / s`` for ``ellipsoids`` (Mahalanobis radius 0)."""
    s = np.maximum(a.scale, 1e-300)
    if method == "planes":
        return plane_width(a.lam, s, tol) / s
    return tol.radius * np.sqrt(np.maximum(a.lam[:, 0], 0.0)) / s


def _side(y0: np.ndarray, target: np.ndarray, want: np.ndarray, sides: np.ndarray | None) -> np.ndarray:
    """The side (+1 or -1 along the oriented ``e1``) that carriers at offsets ``y0`` go to for the
    target offsets ``target`` (``want`` > 0: outside the boundary; ``sides``: their keyed sides, or
    None to keep every carrier on its side).

    A carrier moved outside its boundary goes to its keyed side unless that is much further than
    the other; the detector's signed variant (:func:`core.analysis.signed_statistic`) then reads the
    carriers of flat rings, which sit on their planes, linearly in attacks that add zero-mean
    errors.  A carrier moved inside stays on its side (reading further inside there)."""
    near = np.where(y0 >= 0, 1.0, -1.0)
    if sides is None:
        return near
    return np.where((want > 0) & (sides * y0 >= -KEYED_SIDE_FROM * target), sides, near)


def closest_on_ellipsoid(y: np.ndarray, axes: np.ndarray, iterations: int = 40) -> np.ndarray:
    """Closest points on axis-aligned ellipsoids to points outside them.

    Parameters
    ----------
    y : (k, 3) float64 ndarray
        Points, in each ellipsoid's principal frame, outside the ellipsoid.
    axes : (k, 3) float64 ndarray
        Semi-axes.

    Returns
    -------
    (k, 3) float64 ndarray
        Closest points: ``x_j = y_j a_j^2 / (a_j^2 + t)`` with ``t >= 0`` the root of
        ``sum (y_j a_j / (a_j^2 + t))^2 = 1``, found by Newton's method from ``t = 0`` (the
        function is convex and decreasing there, so the iterates increase monotonically to the
        root).
    """
    # an ellipsoid shrunk to its centre (all semi-axes 0) has the centre as closest point; Newton
    # would divide 0 by 0 there
    collapsed = ~(axes.max(axis=1) > 0)
    a2 = np.maximum(np.where(collapsed[:, None], 1.0, axes), 1e-300) ** 2
    t = np.zeros(len(y))
    ya = y * y * a2
    for _ in range(iterations):
        d = a2 + t[:, None]
        f = (ya / d**2).sum(axis=1) - 1.0
        df = -2.0 * (ya / d**3).sum(axis=1)
        step = np.where(df < 0, -f / np.minimum(df, -1e-300), 0.0)
        t = np.maximum(t + step, 0.0)
        if np.all(np.abs(step) <= 1e-12 * (1.0 + t)):
            break
    x = y * a2 / (a2 + t[:, None])
    x[collapsed] = 0.0
    # land just inside whatever Newton left: rescale onto the ellipsoid
    r = np.sqrt((x * x / a2).sum(axis=1))
    return x / np.maximum(r, 1.0)[:, None]


def budget_cap(moves: np.ndarray, rms: float, n: int) -> float:
    """Largest displacement such that the moves up to it, taken in increasing order, keep the
    RMS over ``n`` vertices within ``rms`` (``inf`` when all of them fit)."""
    m = np.sort(moves)
    fits = np.cumsum(m * m) <= rms * rms * n
    if fits.all():
        return float("inf")
    return float(m[fits][-1]) if fits.any() else 0.0


#: under an RMS budget every carrier's margin may go down to this share of the strength before the
#: largest moves are left out, and up to MAX_MARGIN times it where the marks cost less than the
#: budget (found by MARGIN_STEPS halvings)
MIN_MARGIN, MAX_MARGIN, MARGIN_STEPS = 0.4, 2.0, 12
#: the geometric layer's margin, as a share of the connectivity layer's: its carriers are for the
#: re-triangulations (that keep their surviving vertices in place), so they need less margin than
#: noise asks for, and leave more of the RMS budget to the connectivity layer (engine table, 20
#: rows, one draw: 1.0 / 0.6 / 0.4 read 287 / 289 / 289 cells; 0.6 gained beetle planes' noise
#: 0.3 % 0/2 -> 2/2 and beetle ellipsoids' quadric 30 %, lost rocker-arm ellipsoids' meshopt 10 %;
#: 0.4 lost the counter's and horse ellipsoids' quadric 50 %)
GEOMETRIC_MARGIN = 0.6
#: rounds after which a mesh with geometric carriers stops when at most SETTLED of its carriers
#: still read wrong: cells whose nearest vertex flips with the moves around it never settle (on the
#: bunny 28 carriers of 11,400 kept flipping between two states from round 5 on)
SETTLE_AFTER, SETTLED = 3, 0.005
#: a carrier that reads bit 1 within this share of the deepest reading its boundary allows
#: (:func:`deepest`) is not moved again: with planes, a bit 1 on a ring flatter than the margin
#: reads at most plane_floor = 0.07, which is half the margin the RMS budget left on the 1M-vertex
#: turbine blade, so 114k carriers at their best were "moved" by rounding in all 12 rounds and the
#: embedding never settled
AT_BEST = 0.01


@dataclass(frozen=True)
class EmbedStats:
    """What the embedding did to one mesh.

    ``carriers`` counts the connectivity layer's carriers; ``geometric`` is the detector's view of
    the geometric layer after the embedding (``None`` without one), ``skipped`` the carriers of
    either layer left alone."""

    carriers: int
    skipped: int
    moved: int
    rounds: int
    geometric: Analysis | None = None


def _refresh(a: Analysis, v: np.ndarray, adj: Adjacency, which: np.ndarray, method: str,
             tol: Tolerances) -> None:
    """Recompute, in place, the boundaries and statistics of the carriers ``which`` (indices into
    ``a``) at positions ``v``: their neighbourhoods moved (a geometric carrier next to them did)."""
    if not which.size:
        return
    mu, axes, lam, scale = ring_boundaries(v, adj, a.carriers[which])
    lam_m = method_moments(method, lam, scale, tol)
    a.mu[which], a.axes[which], a.lam[which], a.scale[which] = mu, axes, lam_m, scale
    _restate(a, v, which, method, tol)


def _restate(a: Analysis, v: np.ndarray, which: np.ndarray, method: str, tol: Tolerances) -> None:
    """Read again, in place, the statistics of the carriers ``which`` of ``a`` at positions ``v``."""
    args = (method, v[a.carriers[which]], a.mu[which], a.axes[which], a.lam[which],
            np.maximum(a.scale[which], 1e-300))
    a.z[which] = statistic(*args, tol)
    if a.signed is not None:
        a.signed[which] = signed_statistic(*args, keyed_sides(a.slot_hash[which]), tol)


@dataclass(frozen=True)
class Selection:
    """Where the embedding of one mesh starts from, when the caller made it (once for every try,
    at the original positions and with tolerances of which :func:`~core.pipeline._capped` changes
    nothing these read): the connectivity layer's selection priorities under the key and its
    analysis with the method; the tied pairs of those priorities (:func:`~core.analysis.tied_pairs`)
    and the geometric layer's analysis at the carriers of the placement the caller passes with it,
    either of them when it is being made in another thread."""

    prio: np.ndarray
    analysis: Analysis
    tied: Future[Pairs] | None = None
    geometric: Future[Analysis | None] | None = None


@dataclass
class _Moves:
    """Where the carriers of one layer that read wrong would go: their vertices ``idx``, new
    positions, whether each move is made (``ok``), was cut to the cap (``over``), and its length
    within the cap (``eff``)."""

    idx: np.ndarray
    new: np.ndarray
    ok: np.ndarray
    over: np.ndarray
    eff: np.ndarray


def _moves(method: str, b: Analysis, bits: np.ndarray, bad: np.ndarray, v: np.ndarray, v0: np.ndarray,
           margin: float, cap: float, tol: Tolerances, keyed: bool = True) -> _Moves:
    """The moves that put the carriers ``bad`` of ``b`` on the side of their ``bits`` with ``margin``;
    a move over ``cap`` (or the carrier's own limit) is cut to it and made when the carrier then
    still reads its bit with ``tol.clip_margin x margin``, else not made.  ``keyed``: carriers moved
    outside go to their keyed sides (:func:`target_positions`) where that is within the limit.
    Every carrier's move is its own: many carriers are moved in two threads
    (:func:`~core.parallel.by_rows`)."""
    idx, new, ok, over, eff = by_rows(
        lambda rows: _moves_of(method, b, bits, rows, v, v0, margin, cap, tol, keyed), np.flatnonzero(bad))
    return _Moves(idx, new, ok, over, eff)


def _moves_of(method: str, b: Analysis, bits: np.ndarray, bad: np.ndarray, v: np.ndarray, v0: np.ndarray,
              margin: float, cap: float, tol: Tolerances, keyed: bool
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_moves` of the carriers ``bad`` (indices into ``b``)."""
    idx = b.carriers[bad]
    sub = b.subset(bad)
    want = np.where(bits[bad] == 0, 1.0, -1.0)
    new = target_positions(method, sub, v[idx], bits[bad], margin, tol, keyed)
    move = np.linalg.norm(new - v0[idx], axis=1)
    lim = np.minimum(tol.max_local_move * sub.scale, cap)
    ok = move <= lim
    over = np.flatnonzero(~ok)
    if over.size and keyed:  # over the limit on the keyed side: the carrier's own side, when that is shorter
        near = target_positions(method, sub.subset(over), v[idx[over]], bits[bad][over], margin, tol, False)
        near_move = np.linalg.norm(near - v0[idx[over]], axis=1)
        shorter = near_move < move[over]
        new[over[shorter]] = near[shorter]
        move[over[shorter]] = near_move[shorter]
        ok = move <= lim
        over = np.flatnonzero(~ok)
    if over.size:
        base = v0[idx[over]]
        new[over] = base + (new[over] - base) * (lim[over] / move[over])[:, None]
        cut = sub.subset(over)
        zc = statistic(method, new[over], cut.mu, cut.axes, cut.lam, cut.scale, tol)
        ok[over[want[over] * zc >= tol.clip_margin * margin]] = True
    return idx, new, ok, move > lim, np.minimum(move, lim)


def embed_parts(meshes: Sequence[tuple[np.ndarray, np.ndarray]], key: str | bytes, codeword: np.ndarray,
                method: str, strength: float, quantize: Quantize | None = None, tol: Tolerances = TOL,
                prepared: list[tuple[Adjacency, Labels]] | None = None, rms_budget: float | None = None,
                diagonal: float | None = None, slot_rule: SlotRule | None = None,
                placements: Sequence[Placement | None] | None = None,
                selections: Sequence[Selection] | None = None, still: Sequence[np.ndarray] | None = None
                ) -> tuple[list[np.ndarray], list[EmbedStats], list[Analysis]]:
    """Move carriers of one or several meshes so that the detector reads ``codeword``.

    Parameters
    ----------
    meshes : sequence of (vertices (n, 3) float64, faces (m, 3) int64)
        Welded meshes of one file; the codeword is spread over all of them (:mod:`core.slots`).
    key : str or bytes
    codeword : (L,) uint8 ndarray
        Whitened codeword.
    method : str
    strength : float
        Margin ``|z|`` after embedding.
    quantize : callable, optional
        What storing the positions does to them; carriers are verified after it.
    tol : Tolerances
    prepared : list of (Adjacency, Labels), optional
        Each mesh's :func:`~core.analysis.prepare`, when the caller has it (retries, the
        distortion report).
    rms_budget : float, optional
        Largest RMS displacement of each mesh's vertices, as a fraction of its bounding-box
        diagonal: the first round moves carriers in order of increasing displacement while the
        budget lasts and leaves the others (``tol.rms_budget`` at the default strength).  The
        geometric layer's moves count against it: priced in the first round at the carriers of the
        original frame, made once the frame has followed the connectivity layer's moves.
    diagonal : float, optional
        The bounding-box diagonal the displacement ceiling and the RMS budget refer to: the
        file's, so that a small part of a scene is not held to its own size (default: each
        mesh's own).
    slot_rule : callable, optional
        The slots of the carriers (default: :func:`~core.slots.assign_slots`, ranked or hashed by
        the carrier count); the compact frame's are :func:`~core.slots.bucketed_slots`.
    placements : sequence of Placement or None, optional
        Per mesh, where its geometric carriers are (:mod:`core.geosync`); they carry the same
        codeword with hashed slots (``cell hash mod L``).  A vertex that is a carrier of both
        layers reads the geometric layer's bit.
    selections : sequence of Selection, optional
        Per mesh, the selection priorities under ``key`` and the connectivity layer's analysis
        (``method``) at the original positions, when the caller made them (they depend on ``tol``
        only through what :func:`~core.pipeline._capped` leaves alone), with what else of the
        start it made.
    still : sequence of (n_i,) bool ndarray, optional
        Per mesh, vertices that are never moved (a carrier among them reads whatever it reads at
        its original position): the carriers whose moves made the selection swap vertices in an
        earlier embedding (:func:`~core.pipeline._embed_doc`).

    Returns
    -------
    new_vertices : list of (n, 3) float64 ndarray
    stats : list of EmbedStats
        With each mesh's geometric carriers as the detector will see them.
    analyses : list of Analysis
        The detector's view of the connectivity layer's carriers (the verification).

    Notes
    -----
    Connectivity carriers are independent (no two adjacent), so moving them changes no carrier's
    neighbourhood: with connectivity labels the selection of the stego mesh is the same, and
    only the moved carriers' statistics need re-reading after quantisation.  Geometric carriers
    may sit next to connectivity carriers: after every round the carriers next to a moved vertex
    are read again, and the geometric carriers chosen again (moves change which vertex is nearest
    to a cell's centre).  With the regular fallback the labels depend on geometry, so each round
    re-analyses the whole mesh.
    """
    L = len(codeword)
    v0s = [np.asarray(v, np.float64) for v, _ in meshes]
    faces = [np.asarray(f, np.int64) for _, f in meshes]
    if prepared is None:
        prepared = prepare(v0s, faces)
    places = list(placements) if placements is not None else [None] * len(meshes)
    chosen0 = list(selections) if selections is not None else [None] * len(meshes)
    keep = list(still) if still is not None else [None] * len(meshes)
    states = [_Mesh(v, f, adj, lab, key, method, tol, p, bbox_diagonal(v) if diagonal is None else diagonal,
                    strength, sel, k)
              for v, f, (adj, lab), p, sel, k in zip(v0s, faces, prepared, places, chosen0, keep,
                                                     strict=True)]
    an = [st.local for st in states]
    ranked = ranked_by_default(sum(len(a.carriers) for a in an), L)
    # keyed sides only where the detector reads the signed statistic: a file of fewer connectivity
    # carriers embeds as before (each crossing costs displacement and buys nothing there)
    keyed = sum(len(a.carriers) for a in an) >= SIGNED_FROM
    for st in states:
        st.keyed = keyed

    def slots_of(hashes: list[np.ndarray]) -> list[np.ndarray]:
        return assign_slots(hashes, L, ranked) if slot_rule is None else slot_rule(hashes, L)

    rounds = [0] * len(meshes)
    # the priorities each selection was made with: the tie-break of large meshes reads neighbour
    # means, which a moved carriers changes for its (non-carrier) neighbours, so a selection can
    # change under the embedding; it is checked when the moves are done, and made again if it did
    chosen = [st.prio for st in states]
    ahead: tuple[list[int], list[tuple[int, np.ndarray, Analysis]]] | None = None
    for r in range(1, tol.verify_rounds + 1):
        slots = slots_of([a.slot_hash for a in an])
        any_bad = False
        for k, st in enumerate(states):
            st.local = an[k]
            store = None if quantize is None else partial(quantize, k)
            if st.round(r, codeword, slots[k], rms_budget, store):
                any_bad = True
                rounds[k] = r
            an[k] = st.local
        if any_bad:
            continue
        # settled: the geometric cells, then the connectivity selection, as the detector will see them
        # (on a large mesh, once the frame has followed the moves, the connectivity check is made
        # beside the geometric choice, which reads the same positions and changes neither the
        # positions nor the connectivity layer; it is used at this settle or, when the geometric
        # choice changed and the round after it moved nothing, at the next)
        if _beside_worth(states):
            versions = [st.version for st in states]
            check = beside(partial(_selections, states, key, method, tol, chosen, an))
            changed = [st.reselect() for st in states]  # every mesh, not just up to the first change
            ahead = (versions, check.result())
        else:
            changed = [st.reselect() for st in states]
        if any(changed):
            continue
        made = ahead[1] if ahead is not None and ahead[0] == [st.version for st in states] else None
        ahead = None  # once: the selections it would make are those this settle makes
        if not _reselect(states, key, method, tol, chosen, an, slots_of, codeword, made):
            break
    else:
        # out of rounds: the caller verifies what the detector will see
        for st in states:
            st.reselect()
        _reselect(states, key, method, tol, chosen, an, None, codeword)
    stats = [EmbedStats(len(st.local0), int(st.skipped.sum()), int(changed_rows(st.v, st.v0).sum()),
                        rounds[k], st.view) for k, st in enumerate(states)]
    return [st.v for st in states], stats, an


class _Mesh:
    """One mesh being embedded: its positions, both layers' carriers and what the rounds decided
    (carriers left alone, carriers cut to the cap and readable, caps and margins)."""

    def __init__(self, v0: np.ndarray, faces: np.ndarray, adj: Adjacency, labels: Labels, key: str | bytes,
                 method: str, tol: Tolerances, placement: Placement | None, diagonal: float,
                 strength: float, selection: Selection | None = None,
                 still: np.ndarray | None = None) -> None:
        self.v0, self.v, self.faces, self.adj, self.labels = v0, v0.copy(), faces, adj, labels
        self.key, self.method, self.tol, self.placement, self.diag = key, method, tol, placement, diagonal
        #: the least-variance axes of the rings the geometric choices compared (:class:`Rings`), kept
        #: from one choice to the next but for the rings a move changed (:meth:`_reread`)
        self.rings = Rings(self.v, adj)
        if selection is None:
            prio = priorities(v0, adj, labels, key)
            selection = Selection(prio, analyse(v0, faces, key, method, adj=adj, labels=labels, tol=tol,
                                                prio=prio))
        #: the selection priorities the connectivity layer was chosen with (:func:`_reselect`)
        self.prio = selection.prio
        self.local = selection.analysis.copy()
        self.local0 = self.local.carriers
        self.followed = False  # the placement's frame was made again at the moved positions
        #: the geometric carriers were just chosen in the followed frame: the next round moves them
        #: to the full margin (:meth:`round`)
        self.fresh = False
        # the embedder's placement comes with its carriers at the original positions
        made = None if selection.geometric is None or placement is None else selection.geometric.result()
        self.geo = made.copy() if made is not None else \
            self._geometric(None if placement is None else placement.chosen)
        #: the detector's view of the geometric layer when it was last chosen; ``geo``, which the
        #: rounds move, also holds the carriers that lost their cell to a neighbour after the
        #: follow (:meth:`reselect`)
        self.view = self.geo
        self.dirty = False  # vertices moved since the geometric carriers were last chosen
        self.version = 0  # rounds that moved vertices
        #: :func:`~core.analysis.tied_pairs` of the selection (the label hashes do not change: once
        #: per mesh), which the settle's connectivity check needs: on a large mesh whose check runs
        #: beside the geometric choice, made in another thread while the other core has less to do
        #: (beside the connectivity layer's analysis when the caller made it, else beside the first
        #: round), instead of on the settle's longest path (:meth:`tied`)
        self._tied: Future[Pairs] | Pairs | None = selection.tied
        if self._tied is None and placement is not None and not labels.regular and len(v0) >= SPLIT_FROM:
            self._tied = beside(partial(tied_pairs, self.prio, adj))
        self.skipped = np.zeros(len(v0), bool)
        self.held = np.zeros(len(v0), bool)
        #: vertices never moved (embed_parts' ``still``)
        self.still = np.zeros(len(v0), bool) if still is None else still
        med = float(np.median(self.local.scale)) if len(self.local.scale) else 0.0
        own = max(tol.max_move * bbox_diagonal(v0), tol.coarse_move * med)
        self.cap = min(own, tol.max_displacement * diagonal)
        self.strength = strength
        self.margin = strength  # smaller when the RMS budget asks for it
        self.keyed = True  # carriers moved outside go to their keyed sides (set by embed_parts)

    def _of(self, a: Analysis) -> str:
        """The statistic the carriers of ``a`` are moved with: the geometric layer's own
        (:data:`~core.analysis.GEOMETRIC_METHOD`) or the file's method."""
        return GEOMETRIC_METHOD if a.geometric else self.method

    def tied(self) -> Pairs:
        """:func:`~core.analysis.tied_pairs` of the priorities the selection was first made with."""
        if self._tied is None:
            self._tied = tied_pairs(self.prio, self.adj)
        elif isinstance(self._tied, Future):
            self._tied = self._tied.result()
        return self._tied

    def _geometric(self, chosen: tuple[np.ndarray, np.ndarray] | None = None,
                   known: Sequence[Analysis] = ()) -> Analysis | None:
        """The geometric carriers at the current positions (``chosen``: the placement's own, when
        they are known to be those) and their statistics, the rows of ``known`` (analyses kept
        current at these positions) taken from there (:func:`~core.analysis.geometric_read`)."""
        p = self.placement
        if p is None:
            return None
        if chosen is None:
            chosen = geometric_carriers(self.v, self.adj, p.frame, p.axes, p.rung, self.key, self.rings)
        return geometric_read(known, self.v, self.adj, chosen, self.tol)

    def round(self, r: int, codeword: np.ndarray, local_slots: np.ndarray, rms_budget: float | None,
              quantize: Callable[[np.ndarray, np.ndarray], np.ndarray] | None) -> bool:
        """Move this round's carriers that read wrong or too close; False when none needed to."""
        L = len(codeword)
        a, g = self.local, self.geo
        in_g = np.zeros(len(self.v), bool)
        # (analysis, bits, carriers it may move, share of the margin): the geometric layer first
        # (it reads a vertex that is a carrier of both layers)
        layers: list[tuple[Analysis, np.ndarray, np.ndarray, float]] = []
        if g is not None and len(g.carriers):
            in_g[g.carriers] = True
            layers.append((g, codeword[(g.slot_hash % np.uint64(L)).astype(np.int64)],
                           np.ones(len(g.carriers), bool), GEOMETRIC_MARGIN))
        # until the frame has followed the connectivity layer's moves (:meth:`reselect`) the
        # geometric carriers of the original frame are priced (the first round's margin and cap),
        # not moved: most of them lose their cell to a neighbour once the frame follows (39,348 of
        # 41,855 on the 1M-vertex turbine blade), and their moves would be spent on vertices that
        # carry nothing; the connectivity layer meanwhile moves every one of its carriers
        defer = g is not None and not self.followed
        free = np.ones(len(a.carriers), bool) if defer else ~in_g[a.carriers]
        layers.append((a, codeword[local_slots], free, 1.0))
        # the geometric carriers just chosen in the followed frame are moved to the full margin, as
        # the first round moves the connectivity layer's
        fresh = self.fresh

        def needing(limit: float) -> list[tuple[Analysis, np.ndarray, np.ndarray, float]]:
            out = []
            for b, bits, free, share in layers:
                if b.geometric and defer and not (r == 1 and rms_budget is not None):
                    continue
                lim = self.margin if b.geometric and fresh else limit
                want = np.where(bits == 0, 1.0, -1.0)
                # a bit 1 read within AT_BEST of the deepest its boundary allows has nowhere to go
                deep = (want < 0) & (want * b.z >= (1.0 - AT_BEST) * deepest(self._of(b), b, self.tol))
                bad = (want * b.z < share * lim) & ~deep & free
                bad &= ~self.skipped[b.carriers] & ~self.held[b.carriers] & ~self.still[b.carriers]
                if bad.any():
                    out.append((b, bits, bad, share))
            return out

        def at(m: float, todo: list[tuple[Analysis, np.ndarray, np.ndarray, float]]) -> list[_Moves]:
            return [_moves(self._of(b), b, bits, bad, self.v, self.v0, share * m, self.cap, self.tol,
                           self.keyed)
                    for b, bits, bad, share in todo]

        todo = needing(self.margin if r == 1 else 0.5 * self.margin)
        moves: list[_Moves] | None = None
        if r == 1 and rms_budget is not None:
            self.margin, moves = self._margin_within(lambda m: at(m, needing(m)), rms_budget)
            todo = needing(self.margin)
        self.fresh = False
        if not todo:
            return False
        if g is not None and r > SETTLE_AFTER and \
                sum(int(t[2].sum()) for t in todo) <= SETTLED * (len(a.carriers) + len(g.carriers)):
            # the geometric choice of a few cells flips between two vertices with every move of
            # their neighbours: what is left is too little to matter (the caller verifies)
            return False
        if moves is None:
            moves = at(self.margin, todo)
        if r == 1 and rms_budget is not None:
            # what still does not fit leaves out the largest moves (the code absorbs them)
            room = (rms_budget * self.diag) ** 2 * len(self.v)
            effs = np.concatenate([mv.eff[mv.ok] for mv in moves])
            self.cap = min(self.cap, budget_cap(effs, np.sqrt(room / max(len(self.v), 1)), len(self.v)))
            for mv in moves:
                mv.ok &= mv.eff <= self.cap
            if defer:
                moves = [mv for t, mv in zip(todo, moves, strict=True) if not t[0].geometric]
                if not moves:
                    return False
        idx = np.concatenate([mv.idx for mv in moves])
        new = np.concatenate([mv.new for mv in moves])
        ok = np.concatenate([mv.ok for mv in moves])
        over = np.concatenate([mv.over for mv in moves])
        self.held[idx[ok & over]] = True
        self.skipped[idx[~ok]] = True
        placed = new[ok] if quantize is None else quantize(idx[ok], new[ok])
        self.v[idx[ok]] = placed
        self.dirty = True
        self.version += 1
        self._reread(idx[ok])
        return True

    def _margin_within(self, at: Callable[[float], list[_Moves]], budget: float
                       ) -> tuple[float, list[_Moves]]:
        """The first round's margin, one for every carrier of the mesh: the largest that keeps the
        RMS budget, between MIN_MARGIN and MAX_MARGIN x strength (found by MARGIN_STEPS halvings of
        the interval: a mesh whose marks cost less than the budget at the strength gets stronger
        ones, up to the budget, and one whose marks cost more gets weaker ones), and the moves
        ``at`` it (the moves of every margin tried are evaluated anyway: the one returned is not
        evaluated again, a whole pass over the carriers of a large mesh)."""
        room = (budget * self.diag) ** 2 * len(self.v)
        last: list[tuple[float, list[_Moves]]] = []  # the moves of the latest margin that fits

        def fits(m: float) -> bool:
            moves = at(m)
            ok = sum(float((mv.eff[mv.ok] ** 2).sum()) for mv in moves) <= room
            if ok:
                last[:] = [(m, moves)]
            return ok

        s = self.strength
        lo, hi = (s, MAX_MARGIN * s) if fits(s) else (MIN_MARGIN * s, s)
        if lo == s and fits(hi):
            lo = hi
        else:
            for _ in range(MARGIN_STEPS):
                mid = 0.5 * (lo + hi)
                lo, hi = (mid, hi) if fits(mid) else (lo, mid)
        return lo, last[0][1] if last and last[0][0] == lo else at(lo)

    def _reread(self, moved_idx: np.ndarray) -> None:
        """Statistics after the vertices ``moved_idx`` moved: the whole analysis of a regular mesh
        (its labels depend on positions); else the moved carriers' statistics and, with geometric
        carriers (which may be next to connectivity carriers), the boundaries of the carriers of
        either layer with a moved neighbour.  Which vertex is nearest a cell's centre is looked at
        again when the carriers settle (:meth:`reselect`)."""
        moved = np.zeros(len(self.v), bool)
        moved[moved_idx] = True
        # the vertices next to a moved one (whose rings moved): only needed with both layers
        near = None
        if self.geo is not None:
            near = np.zeros(len(self.v), bool)
            near[self.adj.indices[self.adj.ring_entries(moved_idx)[1]]] = True
        if self.labels.regular:
            self.labels = vertex_labels(self.v, self.adj, self.labels)
            self.local = analyse(self.v, self.faces, self.key, self.method, adj=self.adj, labels=self.labels,
                                 tol=self.tol)
        else:
            self._own(self.local, moved, near)
        if near is not None:  # (the geometric layer exists)
            assert self.geo is not None
            self._own(self.geo, moved, near)
            self.rings.forget(near)

    def _own(self, a: Analysis, moved: np.ndarray, near: np.ndarray | None) -> None:
        """Re-read the carriers of ``a`` that moved, and the boundaries of those next to a moved
        vertex (``near``) when the other layer exists (one layer alone is an independent set)."""
        _restate(a, self.v, np.flatnonzero(moved[a.carriers]), self._of(a), self.tol)
        if near is not None:
            _refresh(a, self.v, self.adj, np.flatnonzero(near[a.carriers]), self._of(a), self.tol)

    def reselect(self) -> bool:
        """Choose the geometric carriers again at the current positions (the moves change which
        vertex is nearest a few cells' centres, and the surface's frame: on the counter plate by a
        tenth of a cell, so the frame is made again the first time); True when more than
        :data:`SETTLED` of them are new, and always the first time (the rounds have not moved the
        geometric layer yet).

        After the follow, a carrier that loses its cell stays among those the rounds move (held to
        its cell's bit): the cells that keep changing are ties between two neighbours, and the move
        of one turns the other's tangent plane, so without it they flip back and forth with every
        round (on the 1M-vertex turbine blade 1,200-2,600 of 45,000 cells, 95-99 % of them back to
        the vertex they had two selections before, never settling in 12 rounds).  Held, both
        vertices of such a cell read its bit, whichever the detector finds nearest, and a cell is
        counted as changed only when its new carrier was never chosen before."""
        if self.geo is None or (self.followed and not self.dirty):
            return False  # nothing moved since the last choice: the same carriers
        assert self.placement is not None
        self.dirty = False
        if not self.followed:
            # the first choice: the geometric layer has not moved yet (:meth:`round`); its frame
            # follows the connectivity layer's moves, and the carriers of the original frame that
            # lose their cell are held like any other (each is its cell's runner-up, and carries
            # its bit too): the rounds then move them all, to the full margin
            self.followed = self.fresh = True
            if np.any(self.v != self.v0):
                self.placement = follow(self.placement, self.v, self.faces)
                self._choose()
            return True
        return self._choose()

    def _choose(self) -> bool:
        """Choose the geometric carriers at the current positions (:attr:`view`), keeping those that
        lost their cell among the carriers the rounds move (:attr:`geo`); True when more than
        :data:`SETTLED` of the chosen ones are new."""
        assert self.geo is not None
        now = self._geometric(known=[self.geo])
        assert now is not None
        self.view = now
        new = int(np.count_nonzero(~np.isin(now.carriers, self.geo.carriers, assume_unique=True)))
        held = ~np.isin(self.geo.carriers, now.carriers, assume_unique=True)
        carriers = np.concatenate([now.carriers, self.geo.carriers[held]])
        hashes = np.concatenate([now.slot_hash, self.geo.slot_hash[held]])
        order = np.argsort(carriers)
        self.geo = self._geometric((carriers[order], hashes[order]), known=[now, self.geo])
        return new > SETTLED * max(len(now.carriers), 1)


def _beside_worth(states: list[_Mesh]) -> bool:
    """Whether the settle's geometric choice is worth a connectivity check beside it: a large file
    whose geometric layer has followed the moves' frame (the first choice after the moves makes
    the frame again and always changes, so a check beside it would be wasted) and has moved since."""
    geo = [st for st in states if st.geo is not None]
    return (sum(len(st.v) for st in states) >= SPLIT_FROM and bool(geo)
            and all(st.followed and st.dirty for st in geo))


def _selections(states: list[_Mesh], key: str | bytes, method: str, tol: Tolerances, chosen: list[np.ndarray],
                an: list[Analysis]) -> list[tuple[int, np.ndarray, Analysis]]:
    """``(mesh, priorities, analysis)`` of every mesh whose priorities at the current positions no
    longer order its neighbours as when its selection was made (``chosen``), with the selection
    made again (:func:`~core.analysis.reanalysed`: only the carriers whose boundaries the moves
    changed, or that it adds, are read).  Reads the states; changes nothing but each mesh's
    cached :func:`~core.analysis.tied_pairs`."""
    out = []
    for k, st in enumerate(states):
        if st.labels.regular:
            continue  # analysed afresh after every move already
        now = priorities(st.v, st.adj, st.labels, key)
        if same_order(chosen[k], now, st.adj, st.tied()):
            continue
        moved = changed_rows(st.v, st.v0)
        out.append((k, now, reanalysed(an[k], st.v, st.adj, st.labels, key, method, now, moved, tol)))
    return out


def _reselect(states: list[_Mesh], key: str | bytes, method: str, tol: Tolerances, chosen: list[np.ndarray],
              an: list[Analysis], slots_of: Callable[[list[np.ndarray]], list[np.ndarray]] | None,
              codeword: np.ndarray, made: list[tuple[int, np.ndarray, Analysis]] | None = None) -> bool:
    """Make again, in place, the selection of every mesh whose priorities no longer order its
    neighbours as when it was made (``chosen``; ``made``: :func:`_selections` at the current
    positions, when the caller has it).  True when more moves are needed: a selection was made
    again and, with ``slots_of`` (the slot rule), some slot's centred hard votes no longer agree
    with ``codeword`` (when they all do, the detector's first variant reads the codeword exactly,
    and the handful of carriers the new selection adds or drops is absorbed: a 1M-vertex mesh
    re-selected three times in a row before this check)."""
    again = False
    for k, now, a in (_selections(states, key, method, tol, chosen, an) if made is None else made):
        chosen[k], an[k] = now, a
        again = True
    if not again or slots_of is None:
        return again
    slots = np.concatenate(slots_of([a.slot_hash for a in an]))
    votes = np.concatenate([np.where(a.z > 0, 1.0, -1.0) for a in an])
    if not len(votes):
        return True
    L = len(codeword)
    sums = np.bincount(slots, (votes - votes.mean()) * np.where(codeword[slots] == 0, 1.0, -1.0), minlength=L)
    filled = np.bincount(slots, minlength=L) > 0
    return not (filled.all() and np.all(sums > 0))

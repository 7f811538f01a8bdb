"""Moving carriers across their boundaries, verified after the file's own rounding.

A carrier on the wrong side of its boundary, or too close to it, moves to ``|z| = strength``:
along ``e1`` (planes; ellipsoids when the tangential part fits inside), or to the closest point of
the inner ellipsoid (ellipsoid bit 1 with a large tangential offset).  Boundaries never depend on
the carrier itself, and carriers are never adjacent, so moving one changes no carrier's boundary.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from core.analysis import Analysis, analyse, prepare, priorities, same_order, statistic
from core.mesh import Adjacency, bbox_diagonal
from core.slots import assign_slots, ranked_by_default
from core.sync import Labels, vertex_labels
from core.tolerances import TOL, Tolerances

#: what storing positions in the file does to them (float32, printed decimals)
#: ``quantize(mesh, vertex_indices, positions)``: what storing those vertices of that mesh gives
Quantize = Callable[[int, np.ndarray, np.ndarray], np.ndarray]
#: ``slot_rule(slot_hashes, length)``: the codeword slot of every carrier of every part
SlotRule = Callable[[list[np.ndarray], int], list[np.ndarray]]


def target_positions(method: str, a: Analysis, v: np.ndarray, bits: np.ndarray, margin: float,
                     tol: Tolerances = TOL) -> np.ndarray:
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

    Returns
    -------
    (k, 3) float64 ndarray
        New positions; carriers already on the right side with at least ``margin`` keep theirs.
    """
    want = np.where(bits == 0, 1.0, -1.0)  # sign of z wanted
    z = statistic(method, v, a.mu, a.axes, a.lam, a.scale, tol)
    need = want * z < margin
    y = np.einsum("kij,ki->kj", a.axes, v - a.mu)
    sgn = np.where(y[:, 0] >= 0, 1.0, -1.0)
    s = a.scale
    if method == "planes":
        tau = np.maximum(np.sqrt(a.lam[:, 0]), tol.plane_floor * s)
        target = np.maximum(tau + want * margin * s, 0.0)
        y[:, 0] = sgn * target
    else:
        l1 = a.lam[:, 0]
        rho_t = np.maximum(tol.radius + want * margin * s / np.sqrt(l1), 0.0)
        rt = (y[:, 1:] ** 2 / a.lam[:, 1:]).sum(axis=1)
        fits = rho_t**2 >= rt
        y0 = sgn * np.sqrt(np.maximum(rho_t**2 - rt, 0.0) * l1)
        out = y.copy()
        out[fits, 0] = y0[fits]
        far = ~fits
        if far.any():
            out[far] = closest_on_ellipsoid(y[far], rho_t[far, None] * np.sqrt(a.lam[far]))
        y = out
    new = a.mu + np.einsum("kij,kj->ki", a.axes, y)
    return np.where(need[:, None], new, v)


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


@dataclass(frozen=True)
class EmbedStats:
    """What the embedding did to one mesh."""

    carriers: int
    skipped: int
    moved: int
    rounds: int


def embed_parts(meshes: Sequence[tuple[np.ndarray, np.ndarray]], key: str | bytes, codeword: np.ndarray,
                method: str, strength: float, quantize: Quantize | None = None, tol: Tolerances = TOL,
                prepared: list[tuple[Adjacency, Labels]] | None = None, rms_budget: float | None = None,
                diagonal: float | None = None, slot_rule: SlotRule | None = None
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
        budget lasts and leaves the others (``tol.rms_budget`` at the default strength).
    diagonal : float, optional
        The bounding-box diagonal the displacement ceiling and the RMS budget refer to: the
        file's, so that a small part of a scene is not held to its own size (default: each
        mesh's own).
    slot_rule : callable, optional
        The slots of the carriers (default: :func:`~core.slots.assign_slots`, ranked or hashed by
        the carrier count); the compact frame's are :func:`~core.slots.bucketed_slots`.

    Returns
    -------
    new_vertices : list of (n, 3) float64 ndarray
    stats : list of EmbedStats
    analyses : list of Analysis
        The detector's view of the result (the verification).

    Notes
    -----
    Carriers are independent (no two adjacent), so moving them changes no carrier's
    neighbourhood: with connectivity labels the selection of the stego mesh is the same, and
    only the moved carriers' statistics need re-reading after quantisation.  With the regular
    fallback the labels depend on geometry, so each round re-analyses the whole mesh.
    """
    L = len(codeword)
    v0s = [np.asarray(v, np.float64) for v, _ in meshes]
    faces = [np.asarray(f, np.int64) for _, f in meshes]
    if prepared is None:
        prepared = prepare(v0s, faces)
    adjs = [adj for adj, _ in prepared]
    labels = [lab for _, lab in prepared]
    vs = [v.copy() for v in v0s]
    skipped = [np.zeros(len(v), bool) for v in v0s]
    held = [np.zeros(len(v), bool) for v in v0s]
    an = [analyse(v, f, key, method, adj=adj, labels=lab, tol=tol)
          for v, f, adj, lab in zip(v0s, faces, adjs, labels, strict=True)]
    carriers = [len(a.carriers) for a in an]
    caps = []
    diags = [bbox_diagonal(v) if diagonal is None else diagonal for v in v0s]
    for v, a, diag in zip(v0s, an, diags, strict=True):
        med = float(np.median(a.scale)) if len(a.scale) else 0.0
        own = max(tol.max_move * bbox_diagonal(v), tol.coarse_move * med)
        caps.append(min(own, tol.max_displacement * diag))
    ranked = ranked_by_default(sum(carriers), L)

    def slots_of(hashes: list[np.ndarray]) -> list[np.ndarray]:
        return assign_slots(hashes, L, ranked) if slot_rule is None else slot_rule(hashes, L)

    rounds = [0] * len(meshes)
    # the priorities each selection was made with: the tie-break of large meshes reads neighbour
    # means, which a moved carrier changes for its (non-carrier) neighbours, so a selection can
    # change under the embedding; it is checked when the moves are done, and made again if it did
    chosen = [priorities(v, adj, lab, key) for v, adj, lab in zip(v0s, adjs, labels, strict=True)]
    for r in range(1, tol.verify_rounds + 1):
        hashes = [a.slot_hash for a in an]
        slots = slots_of(hashes)
        margin = strength if r == 1 else 0.5 * strength
        any_bad = False
        for k, a in enumerate(an):
            bits = codeword[slots[k]]
            want = np.where(bits == 0, 1.0, -1.0)
            bad = (want * a.z < margin) & ~skipped[k][a.carriers] & ~held[k][a.carriers]
            if not bad.any():
                continue
            any_bad = True
            rounds[k] = r
            v, v0 = vs[k], v0s[k]
            idx = a.carriers[bad]
            sub = a.subset(bad)
            new = target_positions(method, sub, v[idx], bits[bad], strength, tol)
            move = np.linalg.norm(new - v0[idx], axis=1)
            lim = np.minimum(tol.max_local_move * sub.scale, caps[k])
            # a move over the cap is cut to the cap: kept when the carrier still ends up on the
            # right side with some margin (then not pushed again), else the carrier is left alone
            okm = move <= lim
            over = np.flatnonzero(~okm)
            if over.size:
                base = v0[idx[over]]
                new[over] = base + (new[over] - base) * (lim[over] / move[over])[:, None]
                cut = sub.subset(over)
                zc = statistic(method, new[over], cut.mu, cut.axes, cut.lam, cut.scale, tol)
                okm[over[want[bad][over] * zc >= tol.clip_margin * strength]] = True
            if r == 1 and rms_budget is not None:
                # the budget goes to the smallest moves; the largest are left
                eff = np.minimum(move, lim)
                caps[k] = min(caps[k], budget_cap(eff[okm], rms_budget * diags[k], len(v)))
                okm &= eff <= caps[k]
            held[k][idx[okm & (move > lim)]] = True
            skipped[k][idx[~okm]] = True
            moved_v = new[okm]
            if quantize is not None:
                moved_v = quantize(k, idx[okm], moved_v)
            v[idx[okm]] = moved_v
            if labels[k].regular:
                labels[k] = vertex_labels(v, adjs[k], labels[k])
                an[k] = analyse(v, faces[k], key, method, adj=adjs[k], labels=labels[k], tol=tol)
            else:
                sel = np.flatnonzero(bad)
                a.z[sel] = statistic(method, v[idx], sub.mu, sub.axes, sub.lam, sub.scale, tol)
        if not any_bad and not _reselect(vs, faces, adjs, labels, key, method, tol, chosen, an, slots_of,
                                         codeword):
            break
    else:
        # out of rounds: the caller verifies what the detector will see
        _reselect(vs, faces, adjs, labels, key, method, tol, chosen, an, None, codeword)
    stats = [EmbedStats(carriers[k], int(skipped[k].sum()), int(np.any(vs[k] != v0s[k], axis=1).sum()),
                        rounds[k]) for k in range(len(meshes))]
    return vs, stats, an


def _reselect(vs: list[np.ndarray], faces: list[np.ndarray], adjs: list[Adjacency], labels: list[Labels],
              key: str | bytes, method: str, tol: Tolerances, chosen: list[np.ndarray], an: list[Analysis],
              slots_of: Callable[[list[np.ndarray]], list[np.ndarray]] | None, codeword: np.ndarray) -> bool:
    """Make again, in place, the selection of every mesh whose priorities no longer order its
    neighbours as when it was made (``chosen``).  True when more moves are needed: a selection was
    made again and, with ``slots_of`` (the slot rule), some slot's centred hard votes no longer
    agree with ``codeword`` (when they all do, the detector's first variant reads the codeword
    exactly, and the handful of carriers the new selection adds or drops is absorbed: a 1M-vertex
    mesh re-selected three times in a row before this check)."""
    again = False
    for k, v in enumerate(vs):
        if labels[k].regular:
            continue  # analysed afresh after every move already
        now = priorities(v, adjs[k], labels[k], key)
        if same_order(chosen[k], now, adjs[k]):
            continue
        chosen[k] = now
        an[k] = analyse(v, faces[k], key, method, adj=adjs[k], labels=labels[k], tol=tol)
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

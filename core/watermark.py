"""The two local-moment watermarking methods on arrays: analysis, embedding, reading.

A carrier ``i`` (see :mod:`core.sync`) is described by its neighbours only: their mean
``mu`` (eq. 2) and covariance ``Sigma`` (eq. 3), eigenvalues ``l1 <= l2 <= l3`` with
eigenvectors ``e1, e2, e3``, and the local scale ``s = sqrt(trace Sigma)``.  Every quantity
below is dimensionless (divided by ``s``), so similarity transforms change nothing.

``planes`` (eqs. 15-20)
    ``Q = e1`` (least-variance axis of the neighbours: the paper's mean normal depends on the
    carrier), ``Psi = sqrt(l1)`` (eq. 16).  Statistic ``z = (|(V - mu).Q| - tau) / s`` with
    ``tau = max(Psi, PLANE_FLOOR * s)``; bit 1 inside the planes (z < 0), bit 0 outside.
``ellipsoids`` (eqs. 21-25)
    Mahalanobis radius ``rho`` of ``V`` in the regularised ``Sigma + ALPHA s^2 I`` against
    ``K = 1``; ``z = (rho - 1) sqrt(l1') / s`` (the distance to the ellipsoid along ``e1`` in
    units of ``s``); bit 1 inside, bit 0 outside.

Embedding moves a carrier just across its boundary, to ``|z| = strength``; boundaries never
depend on the carrier itself.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core.eig3 import eigh3
from core.hashing import derive, mix64
from core.mesh import Adjacency, adjacency, bbox_diagonal, neighbour_moments
from core.sync import Labels, select_carriers, vertex_labels

METHODS = ("ellipsoids", "planes")


@dataclass(frozen=True)
class Tolerances:
    """Every constant of the method in one place (see core/README.md for how they were chosen)."""

    strength: float = 0.07          # default margin |z| after embedding, in units of the local scale
    plane_floor: float = 0.07       # planes: tau >= plane_floor * s (so bit 1 is reachable on flat rings)
    alpha: float = 0.05             # ellipsoids: Sigma regularised by alpha * s^2 * I
    radius: float = 0.8             # ellipsoids: K
    min_flatness: float = 0.05      # l2 / l3 of the ring: below, the ring is a line (skip)
    max_scale: float = 4.0          # skip carriers whose scale exceeds max_scale x median scale
    max_local_move: float = 0.8     # displacement cap, units of the local scale
    max_move: float = 5e-3          # displacement cap, fraction of the bounding-box diagonal...
    coarse_move: float = 0.25       # ...or this fraction of the median local scale on coarse meshes
    verify_rounds: int = 12         # embed -> re-analyse -> fix rounds (regular fallback: up to 10 seen)


TOL = Tolerances()


@dataclass
class Analysis:
    """Carriers of one mesh under one key and method, with their boundaries and statistics."""

    carriers: np.ndarray   # (k,) vertex indices
    slot_hash: np.ndarray  # (k,) uint64 keyed hash deciding the codeword slot
    z: np.ndarray          # (k,) signed statistic: > 0 reads bit 0, < 0 reads bit 1
    mu: np.ndarray         # (k, 3)
    axes: np.ndarray       # (k, 3, 3) eigenvectors (columns) of Sigma, ascending eigenvalues
    lam: np.ndarray        # (k, 3) eigenvalues (regularised for ellipsoids)
    scale: np.ndarray      # (k,)
    regular: bool


def _key_salts(key: str | bytes) -> tuple[np.uint64, np.uint64]:
    return np.uint64(derive(key, "meshmark-prio")), np.uint64(derive(key, "meshmark-slot"))


def statistic(method: str, v: np.ndarray, mu: np.ndarray, axes: np.ndarray, lam: np.ndarray,
              scale: np.ndarray, tol: Tolerances = TOL) -> np.ndarray:
    """Signed, dimensionless side of the boundary for carriers at positions ``v`` (k, 3)."""
    y = np.einsum("kij,ki->kj", axes, v - mu)  # coordinates in the eigenbasis
    if method == "planes":
        tau = np.maximum(np.sqrt(np.maximum(lam[:, 0], 0.0)), tol.plane_floor * scale)
        return (np.abs(y[:, 0]) - tau) / scale
    rho = np.sqrt((y * y / lam).sum(axis=1))
    return (rho - tol.radius) * np.sqrt(lam[:, 0]) / scale


def analyse_methods(vertices: np.ndarray, faces: np.ndarray, key: str | bytes,
                    methods: list[str] | tuple[str, ...],
                    adj: Adjacency | None = None, labels: Labels | None = None,
                    tol: Tolerances = TOL) -> dict[str, Analysis]:
    """Select the carriers of a mesh and read their statistics (the detector's view).

    The carriers and their neighbourhoods do not depend on the method; only the statistic does,
    so several methods share one selection.
    """
    for method in methods:
        if method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}")
    v = np.asarray(vertices, np.float64)
    if adj is None:
        adj = adjacency(faces, len(v))
    if labels is None:
        labels = vertex_labels(v, adj)
    salt_p, salt_s = _key_salts(key)
    prio = mix64(labels.labels ^ salt_p)
    sel = select_carriers(adj, prio, labels.usable)
    mu, sigma = neighbour_moments(v, adj, sel)
    lam, axes = eigh3(sigma)
    lam = np.maximum(lam, 0.0)
    scale = np.sqrt(lam.sum(axis=1))
    ok = (scale > 0) & (lam[:, 1] > tol.min_flatness * np.maximum(lam[:, 2], 1e-300))
    if ok.any():
        ok &= scale <= tol.max_scale * np.median(scale[ok])
    sel, mu, axes, lam, scale = sel[ok], mu[ok], axes[ok], lam[ok], scale[ok]
    slot_hash = mix64(labels.labels[sel] ^ salt_s)
    out = {}
    for method in methods:
        lam_m = lam + tol.alpha * (scale**2)[:, None] if method == "ellipsoids" else lam
        z = statistic(method, v[sel], mu, axes, lam_m, scale, tol)
        out[method] = Analysis(sel, slot_hash, z, mu, axes, lam_m, scale, labels.regular)
    return out


def analyse(vertices: np.ndarray, faces: np.ndarray, key: str | bytes, method: str,
            adj: Adjacency | None = None, labels: Labels | None = None,
            tol: Tolerances = TOL) -> Analysis:
    """:func:`analyse_methods` for one method."""
    return analyse_methods(vertices, faces, key, [method], adj, labels, tol)[method]


def target_positions(method: str, a: Analysis, v: np.ndarray, bits: np.ndarray, margin: float,
                     tol: Tolerances = TOL) -> np.ndarray:
    """Positions that put carriers at ``v`` (k, 3) on the side of ``bits`` with ``|z| = margin``.

    Carriers already on the right side with at least ``margin`` keep their position.
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
    y : (k, 3) points, in each ellipsoid's principal frame, outside the ellipsoid.
    axes : (k, 3) semi-axes.

    Returns
    -------
    (k, 3) closest points: ``x_j = y_j a_j^2 / (a_j^2 + t)`` with ``t >= 0`` the root of
    ``sum (y_j a_j / (a_j^2 + t))^2 = 1``, found by Newton's method from ``t = 0`` (the function
    is convex and decreasing there, so the iterates increase monotonically to the root).
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


@dataclass(frozen=True)
class EmbedStats:
    carriers: int
    skipped: int
    moved: int
    rounds: int


def embed_parts(meshes: list[tuple[np.ndarray, np.ndarray]], key: str | bytes, codeword: np.ndarray,
                method: str, strength: float, quantize=None, tol: Tolerances = TOL,
                prepared: list[tuple[Adjacency, Labels]] | None = None,
                ) -> tuple[list[np.ndarray], list[EmbedStats], list[Analysis]]:
    """Move carriers of one or several meshes so that the detector reads ``codeword``.

    Parameters
    ----------
    meshes : list of (vertices (n, 3), faces (m, 3))
        Welded meshes of one file; the payload is spread over all of them (see
        :func:`assign_slots`).
    codeword : (L,) uint8
        Whitened codeword.
    strength : float
        Margin ``|z|`` after embedding.
    quantize : callable, optional
        What storing the positions does to them (float32, printed decimals); carriers are
        verified after it.
    prepared : list of (Adjacency, Labels), optional
        Each mesh's adjacency and :func:`~core.sync.vertex_labels` of its input positions, when
        the caller has them (retries, the distortion report).

    Returns
    -------
    new_vertices : list of (n, 3) float64
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
    an = [analyse(v, f, key, method, adj=adj, labels=lab, tol=tol)
          for v, f, adj, lab in zip(v0s, faces, adjs, labels, strict=True)]
    carriers = [len(a.carriers) for a in an]
    caps = []
    for v, a in zip(v0s, an, strict=True):
        med = float(np.median(a.scale)) if len(a.scale) else 0.0
        caps.append(max(tol.max_move * bbox_diagonal(v), tol.coarse_move * med))
    ranked = sum(carriers) < HASHED_FROM * L
    rounds = [0] * len(meshes)
    for r in range(1, tol.verify_rounds + 1):
        slots = assign_slots_all(an, L, ranked)
        margin = strength if r == 1 else 0.5 * strength
        any_bad = False
        for k, a in enumerate(an):
            bits = codeword[slots[k]]
            want = np.where(bits == 0, 1.0, -1.0)
            bad = (want * a.z < margin) & ~skipped[k][a.carriers]
            if not bad.any():
                continue
            any_bad = True
            rounds[k] = r
            v, v0 = vs[k], v0s[k]
            idx = a.carriers[bad]
            sub = Analysis(idx, a.slot_hash[bad], a.z[bad], a.mu[bad], a.axes[bad], a.lam[bad], a.scale[bad],
                           a.regular)
            new = target_positions(method, sub, v[idx], bits[bad], strength, tol)
            move = np.linalg.norm(new - v0[idx], axis=1)
            okm = move <= np.minimum(tol.max_local_move * sub.scale, caps[k])
            skipped[k][idx[~okm]] = True
            moved_v = new[okm]
            if quantize is not None:
                moved_v = quantize(moved_v)
            v[idx[okm]] = moved_v
            if labels[k].regular:
                labels[k] = vertex_labels(v, adjs[k], labels[k])
                an[k] = analyse(v, faces[k], key, method, adj=adjs[k], labels=labels[k], tol=tol)
            else:
                sel = np.flatnonzero(bad)
                a.z[sel] = statistic(method, v[idx], sub.mu, sub.axes, sub.lam, sub.scale, tol)
        if not any_bad:
            break
    stats = [EmbedStats(carriers[k], int(skipped[k].sum()), int(np.any(vs[k] != v0s[k], axis=1).sum()),
                        rounds[k]) for k in range(len(meshes))]
    return vs, stats, an


def prepare(vertices: list[np.ndarray], faces: list[np.ndarray]) -> list[tuple[Adjacency, Labels]]:
    """Adjacency and keyless labels of each mesh (what :func:`embed_parts` needs first)."""
    out = []
    for v, f in zip(vertices, faces, strict=True):
        adj = adjacency(f, len(v))
        out.append((adj, vertex_labels(np.asarray(v, np.float64), adj)))
    return out


def embed_arrays(vertices: np.ndarray, faces: np.ndarray, key: str | bytes, codeword: np.ndarray,
                 method: str, strength: float, quantize=None, tol: Tolerances = TOL,
                 ) -> tuple[np.ndarray, EmbedStats, Analysis]:
    """:func:`embed_parts` for a single mesh."""
    vs, stats, an = embed_parts([(vertices, faces)], key, codeword, method, strength, quantize, tol)
    return vs[0], stats[0], an[0]


#: carriers per slot from which the embedder assigns slots by hash rather than by rank
HASHED_FROM = 4
#: carriers per slot from which one part of a multi-mesh file is ranked on its own
OWN_RANKING_FROM = 1.5


def assign_slots_all(analyses: list[Analysis], L: int, ranked: bool | None = None,
                     cache: dict | None = None) -> list[np.ndarray]:
    """Codeword slot of every carrier of every part.

    Many carriers (>= ``HASHED_FROM`` per slot over the file): ``slot_hash mod L``, purely
    local, so a cropped piece or one mesh of the file still decodes.  Few carriers: the carriers
    of all parts ranked together by ``slot_hash`` take the slots in turn (dense ranks, so equal
    hashes share a slot; the rank does not depend on the parts' order), which covers every slot
    as soon as there are ``L`` carriers, as the paper's small models need (a part with
    ``OWN_RANKING_FROM x L`` distinct labels is ranked alone, so that it decodes when extracted).
    ``ranked=None`` chooses by the number of carriers (the embedder's choice); the detector also
    tries the other, since cropping changes that number.  ``cache``: a dict reused across calls
    on the same analyses (ranks do not depend on ``L``).
    """
    cache = {} if cache is None else cache
    total = sum(len(a.carriers) for a in analyses)
    if ranked is None:
        ranked = total < HASHED_FROM * L
    if not ranked:
        return [(a.slot_hash % np.uint64(L)).astype(np.int64) for a in analyses]
    if "distinct" not in cache:
        cache["distinct"] = [np.unique(a.slot_hash).size for a in analyses]
    distinct = cache["distinct"]
    out = [np.zeros(0, np.int64) for _ in analyses]
    # a part that can hold a copy by itself is ranked alone (so it decodes when extracted);
    # the small ones are ranked together
    small = []
    for k, a in enumerate(analyses):
        if len(a.carriers) >= OWN_RANKING_FROM * L and distinct[k] >= OWN_RANKING_FROM * L:
            if ("own", k) not in cache:
                cache[("own", k)] = _dense_rank(a.slot_hash)
            out[k] = cache[("own", k)] % L
        elif len(a.carriers):
            small.append(k)
    if small:
        group = ("joint", tuple(small))
        if group not in cache:
            cache[group] = _dense_rank(np.concatenate([analyses[k].slot_hash for k in small]))
        slots = cache[group] % L
        for k, part in zip(small, np.split(slots, np.cumsum([len(analyses[k].carriers) for k in small])[:-1]),
                           strict=True):
            out[k] = part
    return out


def own_copy(a: Analysis, L: int) -> bool:
    """A part has room for a copy of its own: enough *distinct* slot hashes (symmetric parts
    repeat labels, and equal labels share a slot)."""
    return len(a.carriers) >= OWN_RANKING_FROM * L and np.unique(a.slot_hash).size >= OWN_RANKING_FROM * L


def _dense_rank(h: np.ndarray) -> np.ndarray:
    """Rank of each value among the distinct values (equal values share a rank)."""
    _, rank = np.unique(h, return_inverse=True)
    return rank.ravel().astype(np.int64)

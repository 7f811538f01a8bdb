"""Undo one step of 1-to-4 subdivision (midpoint or Loop) before detection.

A subdivision step keeps the connectivity labels of no vertex (every ring gains the new edge
vertices), so the local layer's synchronisation is lost although the marked vertices are still
there: midpoint subdivision keeps them exactly, and their neighbours' moments scale with the new,
half-length ring (``z`` is dimensionless: it barely changes); Loop's scheme moves them by a fixed
linear rule. Both are *recognisable* and *invertible* from the suspect mesh alone:

* **Connectivity.** After one 1-to-4 step every face is either a *corner* face (one original,
  "even", vertex and two edge, "odd", ones) or a *centre* face (three odd vertices); no two even
  vertices are neighbours; odd vertices have valence 6 (4 on a boundary). Even vertices are found
  by propagation from the vertices whose valence an odd vertex cannot have, with three rules
  (neighbours of an even vertex are odd; across each edge of a centre face lies an even vertex;
  across the odd-odd edge of a corner face lies an odd one), in whole-array rounds. The labelling
  is accepted only when it is complete and every face and vertex obeys the structure; the coarse
  faces are read off the centre faces, in their orientation.
* **Positions.** Midpoint: the even vertices did not move (checked: every odd vertex is the
  midpoint of its two even neighbours). Loop: every odd vertex is ``3/8 (a + b) + 1/8 (c + d)``
  of the coarse positions (``(a + b) / 2`` on a boundary), the same in every variant of the scheme
  (the even rule's weight differs between Loop's and Warren's beta), so the coarse positions are
  the least-squares solution of the odd vertices' equations (about three equations per unknown).

Nothing here needs the key: the detector tries the coarse mesh as one more view when the suspect
mesh does not read, and counts it in the false-positive figure.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from core.formats.base import nondegenerate
from core.mesh import bbox_diagonal

#: a vertex with a valence an odd vertex cannot have (interior 6, boundary 4) seeds the
#: propagation; below this share of valence-6 vertices a mesh is not a subdivision (3/4 of the
#: vertices of a subdivided closed mesh are odd, all of valence 6)
MIN_REGULAR_SHARE = 0.6
#: rounds of propagation before giving up (each round crosses about one ring)
MAX_ROUNDS = 200
#: an odd vertex is a midpoint when it is within this share of its edge's length of it
MIDPOINT_TOL = 1e-4

#: conjugate-gradient iterations allowed for the Loop inverse
CG_MAX_ITER = 500

#: share of vertices whose label may stay unknown or contradictory (merged by a writer, slivers of
#: a CAD face); their faces are left out of the coarse mesh, which then has small holes (the
#: local layer reads a holed mesh as it reads a cropped one)
MAX_BAD_SHARE = 0.1

EVEN, ODD, UNKNOWN, BAD = 0, 1, -1, -2


#: what :func:`_opposite` gives an edge of one face, and an edge of more than two
BORDER, BRANCH = -1, -2


def _opposite(faces: np.ndarray, n: int) -> np.ndarray:
    """(m, 3) third vertex of the other face on edge j = (f[j], f[j+1]) of every face, or
    :data:`BORDER` where there is none (a boundary) and :data:`BRANCH` on an edge of more than two
    faces. Edges are matched without their direction, so that faces oriented inconsistently (CAD
    exports have them) still pair."""
    m = len(faces)
    u = faces.ravel()
    v = faces[:, [1, 2, 0]].ravel()
    w = faces[:, [2, 0, 1]].ravel()
    key = np.minimum(u, v) * n + np.maximum(u, v)
    # the two faces of an edge get each other's third vertex, whichever sorts first: no stable sort
    # needed (0.84 -> 0.37 s for the 6M half-edges of the 1M-vertex benchmark mesh)
    order = np.argsort(key)
    sk = key[order]
    starts = np.flatnonzero(np.r_[True, sk[1:] != sk[:-1]])
    counts = np.diff(np.r_[starts, len(sk)])
    pairs = starts[counts == 2]
    a, b = order[pairs], order[pairs + 1]
    out = np.full(3 * m, BORDER, np.int64)
    out[a] = w[b]
    out[b] = w[a]
    out[order[np.repeat(counts, counts) > 2]] = BRANCH  # every half-edge of an edge of > 2 faces
    return out.reshape(m, 3)


def _labels(faces: np.ndarray, n: int, opp: np.ndarray) -> np.ndarray | None:
    """Even/odd label of every vertex (BAD where the rules contradict each other: a few vertices
    that a writer merged or a CAD face's slivers), or None when the mesh is not one 1-to-4 step."""
    deg = np.bincount(faces.ravel(), minlength=n)  # faces per vertex
    boundary = np.zeros(n, bool)
    branch = np.zeros(n, bool)
    for mask, on in ((opp == BORDER, boundary), (opp == BRANCH, branch)):
        on[faces[mask]] = True
        on[faces[:, [1, 2, 0]][mask]] = True
    # valence = faces around an interior vertex, faces + 1 on a boundary; a vertex on an edge of
    # more than two faces (CAD sheets meeting: 242 edges of four faces on the cycloidal gear) has
    # no valence that tells even from odd, and seeding its midpoints as even made 831 of the gear's
    # vertices contradictory after a midpoint step
    valence = deg + boundary
    lab = np.full(n, UNKNOWN, np.int8)
    seeds = np.where(boundary, valence != 4, valence != 6) & ~branch
    if not seeds.any() or (valence == 6).mean() < MIN_REGULAR_SHARE:
        return None
    lab[seeds] = EVEN
    # the rules per face corner column (reductions along the rows of (m, 3) arrays are several
    # times slower: 0.25 s a round on the 2M faces of the 1M-vertex benchmark mesh)
    fc = [faces[:, c] for c in range(3)]  # views: copies would add 48 MB at 1M to the peak
    oc = [opp[:, c] for c in range(3)]
    for _ in range(MAX_ROUNDS):
        before = lab.copy()
        lf = [lab[f] for f in fc]
        clean = (lf[0] != BAD) & (lf[1] != BAD) & (lf[2] != BAD)
        even = [x == EVEN for x in lf]
        odd = [x == ODD for x in lf]
        even_in = clean & (even[0] | even[1] | even[2])
        to_odd = np.zeros(n, bool)
        to_even = np.zeros(n, bool)
        for c in range(3):
            # neighbours of an even vertex are odd
            to_odd[fc[c][even_in & ~even[c]]] = True
        # centre faces: across each edge an even vertex
        centre = clean & odd[0] & odd[1] & odd[2]
        for c in range(3):
            across = oc[c][centre]
            to_even[across[across >= 0]] = True
        # corner faces: across the odd-odd edge (the one after the even corner) an odd vertex
        corner = even_in & (odd[0].astype(np.int8) + odd[1] + odd[2] == 2)
        for c in range(3):
            across = oc[(c + 1) % 3][corner & even[c]]
            to_odd[across[across >= 0]] = True
        bad = (to_odd & (to_even | (lab == EVEN))) | (to_even & (lab == ODD))
        lab[to_odd & (lab != BAD)] = ODD
        lab[to_even & (lab != BAD)] = EVEN
        lab[bad] = BAD
        if np.array_equal(lab, before):
            break
    if np.count_nonzero(lab < 0) > MAX_BAD_SHARE * n:
        return None
    return lab


def _centre_faces(faces: np.ndarray, lab: np.ndarray, opp: np.ndarray) -> np.ndarray | None:
    """The centre faces (three odd corners, an even vertex across each edge) when at least
    (1 - MAX_BAD_SHARE) of the faces' structure is a 1-to-4 step, else None."""
    lf = lab[faces]
    clean = (lf >= 0).all(axis=1)
    # two even vertices are never neighbours: such faces are where the step was not clean
    if np.count_nonzero(clean & ((lf == EVEN).sum(axis=1) > 1)) > MAX_BAD_SHARE * len(faces):
        return None
    o = np.where(opp >= 0, opp, 0)
    centre = clean & (lf == ODD).all(axis=1) & (opp >= 0).all(axis=1) & (lab[o] == EVEN).all(axis=1)
    if 4 * centre.sum() < (1 - MAX_BAD_SHARE) * len(faces):
        return None
    return np.flatnonzero(centre)


def undo_subdivision(vertices: np.ndarray, faces: np.ndarray) -> tuple[str, np.ndarray, np.ndarray] | None:
    """The coarse mesh one subdivision step down, or None when ``faces`` is not such a step.

    Returns
    -------
    scheme : str
        ``"midpoint"`` when the odd vertices of a 1-to-4 step are the midpoints of their edges,
        ``"loop"`` for another 1-to-4 step, ``"sqrt3"`` for Kobbelt's sqrt(3) step.
    vertices : (k, 3) float64
        Coarse positions (the even vertices; for Loop and sqrt(3), the least-squares inverse of the
        rule that placed the new vertices).
    faces : (j, 3) int64
        Coarse triangles, oriented like the fine ones.
    """
    vertices = np.asarray(vertices, np.float64)
    faces = np.asarray(faces, np.int64)
    n = len(vertices)
    if len(faces) < 4 or n < 6:
        return None
    undone = _undo_one_to_four(vertices, faces) or _undo_sqrt3(vertices, faces)
    if undone is None or undone[0] == "midpoint":  # (positions kept: copies were welded when read)
        return undone
    return undone[0], *_merged(undone[1], undone[2])


#: coarse vertices solved to within this share of the bounding-box diagonal of each other, and not
#: neighbours, are one vertex that the subdivider split (trimesh's Loop splits the vertices of an
#: edge of more than two faces: 294 of the cycloidal gear's 21,384 came back twice, 1e-12 apart,
#: and the copies' rings changed the labels around them enough that the gear's mark, read when
#: the payload was given, was not found blind)
MERGE_TOL = 1e-7


def _merged(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(vertices, faces)`` with every group of vertices within :data:`MERGE_TOL` of each other
    (pairs of neighbours excepted) made one, at its first vertex's position; faces that lose a
    corner to it are dropped, and the vertices left keep their order."""
    n = len(vertices)
    pairs = cKDTree(vertices).query_pairs(MERGE_TOL * bbox_diagonal(vertices), output_type="ndarray")
    if len(pairs):
        edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
        pairs = pairs[~np.isin(pairs[:, 0] * n + pairs[:, 1], edges[:, 0] * n + edges[:, 1])]
    if not len(pairs):
        return vertices, faces
    graph = sp.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, group = connected_components(graph, directed=False)
    first = np.full(n, n, np.int64)
    np.minimum.at(first, group, np.arange(n))
    rep = first[group]
    keep = np.flatnonzero(rep == np.arange(n))
    index = np.full(n, -1, np.int64)
    index[keep] = np.arange(len(keep))
    return vertices[keep], nondegenerate(index[rep[faces]], False)


def _undo_one_to_four(vertices: np.ndarray, faces: np.ndarray) -> tuple[str, np.ndarray, np.ndarray] | None:
    n = len(vertices)
    opp = _opposite(faces, n)
    lab = _labels(faces, n, opp)
    if lab is None:
        return None
    centre = _centre_faces(faces, lab, opp)
    if centre is None:
        return None
    # centre (p, q, r) = (m_ab, m_bc, m_ca): a across (r, p), b across (p, q), c across (q, r)
    o = opp[centre]
    corners = np.stack([o[:, 2], o[:, 0], o[:, 1]], axis=1)
    even = np.unique(corners)
    new_index = np.full(n, -1, np.int64)
    new_index[even] = np.arange(len(even))
    coarse = new_index[corners]
    mids = faces[centre]  # (k, 3): m_ab, m_bc, m_ca
    # odd vertex -> its coarse edge (a, b) and the opposite coarse corner, once per adjacent face
    faces_per_odd = np.bincount(mids.ravel(), minlength=n)
    fine_boundary = np.zeros(n, bool)
    fine_boundary[faces[opp < 0]] = True
    # an odd vertex of one coarse edge, inside (two coarse faces) or on the mesh's boundary (one;
    # next to a hole left by unlabelled vertices it has one too, and no equation)
    per = faces_per_odd[mids]
    usable = ((per == 2) | ((per == 1) & fine_boundary[mids])).ravel()
    odd_v = mids.ravel()[usable]
    ends_a = coarse[:, [0, 1, 2]].ravel()[usable]
    ends_b = coarse[:, [1, 2, 0]].ravel()[usable]
    apex = coarse[:, [2, 0, 1]].ravel()[usable]
    a_pos, b_pos = vertices[even][ends_a], vertices[even][ends_b]
    edge = np.linalg.norm(b_pos - a_pos, axis=1)
    mid_err = np.linalg.norm(vertices[odd_v] - 0.5 * (a_pos + b_pos), axis=1)
    if np.all(mid_err <= MIDPOINT_TOL * np.maximum(edge, 1e-300)):
        return "midpoint", vertices[even], coarse
    # Loop: odd = 3/8 (a + b) + 1/8 (c + d) inside, (a + b) / 2 on a boundary edge
    inner = faces_per_odd[odd_v] == 2
    rows = np.concatenate([odd_v, odd_v, odd_v[inner]])
    cols = np.concatenate([ends_a, ends_b, apex[inner]])
    wa = np.where(inner, 3.0 / 16.0, 0.5)
    vals = np.concatenate([wa, wa, np.full(int(inner.sum()), 1.0 / 8.0)])
    odd = np.unique(odd_v)
    row_index = np.full(n, -1, np.int64)
    row_index[odd] = np.arange(len(odd))
    S = sp.csr_matrix((vals, (row_index[rows], cols)), shape=(len(odd), len(even)))
    solved = _least_squares(S, vertices[odd], vertices[even])
    return None if solved is None else ("loop", solved, coarse)


def _least_squares(S: sp.csr_matrix, rhs_points: np.ndarray, start: np.ndarray) -> np.ndarray | None:
    """Positions ``x`` minimising ``|S x - rhs_points|`` (three coordinates), from ``start``."""
    normal = (S.T @ S).tocsr()
    rhs = S.T @ rhs_points
    # well conditioned (Loop's odd rule averages 4 coarse vertices, sqrt(3)'s centroid 3, and each
    # coarse vertex is in about 6 equations): conjugate gradients from the fine mesh's own positions
    # of those vertices converge in a few dozen iterations, where a sparse LU of Loop's system took
    # 0.7 s on 35k unknowns
    diag = normal.diagonal()
    if np.any(diag <= 0):
        return None
    precond = sp.diags(1.0 / diag)
    solved = np.empty((S.shape[1], 3))
    for k in range(3):
        x, info = spla.cg(normal, rhs[:, k], x0=start[:, k], rtol=1e-13, atol=0.0, M=precond,
                          maxiter=CG_MAX_ITER)
        if info != 0:
            return None
        solved[:, k] = x
    return solved if np.all(np.isfinite(solved)) else None


def _undo_sqrt3(vertices: np.ndarray, faces: np.ndarray) -> tuple[str, np.ndarray, np.ndarray] | None:
    """Kobbelt's sqrt(3) step undone: every face of the step has one old vertex and two new ones
    (face centroids, valence 6, three old neighbours); old vertices are seeded where a new one is
    impossible (valence != 6) and propagated face by face; the coarse faces are the new vertices'
    old neighbours, oriented like the fine fan around them; positions are the least-squares
    solution of "a new vertex is the centroid of its face" (the old vertices were relaxed)."""
    n = len(vertices)
    deg = np.bincount(faces.ravel(), minlength=n)
    if (deg == 6).mean() < MIN_REGULAR_SHARE:
        return None
    lab = np.full(n, UNKNOWN, np.int8)
    lab[deg != 6] = EVEN  # old
    if not (lab == EVEN).any():
        return None
    fc = [faces[:, c] for c in range(3)]  # per column, as in _labels
    for _ in range(MAX_ROUNDS):
        before = lab.copy()
        lf = [lab[f] for f in fc]
        clean = (lf[0] != BAD) & (lf[1] != BAD) & (lf[2] != BAD)
        unknown = [x == UNKNOWN for x in lf]
        one_old = clean & ((lf[0] == EVEN).astype(np.int8) + (lf[1] == EVEN) + (lf[2] == EVEN) == 1)
        two_new = clean & ((lf[0] == ODD).astype(np.int8) + (lf[1] == ODD) + (lf[2] == ODD) == 2)
        to_new = np.zeros(n, bool)
        to_old = np.zeros(n, bool)
        for c in range(3):
            to_new[fc[c][one_old & unknown[c]]] = True
            to_old[fc[c][two_new & unknown[c]]] = True
        bad = to_new & to_old
        lab[to_new & ~bad & (lab == UNKNOWN)] = ODD
        lab[to_old & ~bad & (lab == UNKNOWN)] = EVEN
        lab[bad] = BAD
        if np.array_equal(lab, before):
            break
    if np.count_nonzero(lab < 0) > MAX_BAD_SHARE * n:
        return None
    lf = lab[faces]
    regular = ((lf == EVEN).sum(axis=1) == 1) & ((lf == ODD).sum(axis=1) == 2)
    if regular.sum() < (1 - MAX_BAD_SHARE) * len(faces):
        return None
    # (new vertex, old neighbour) pairs from the regular faces, each pair once
    fr = faces[regular]
    old_pos = np.argmax(lab[fr] == EVEN, axis=1)
    olds = fr[np.arange(len(fr)), old_pos]
    news = np.stack([fr[np.arange(len(fr)), (old_pos + 1) % 3], fr[np.arange(len(fr)), (old_pos + 2) % 3]], 1)
    pairs = np.unique(np.stack([news.ravel(), np.repeat(olds, 2)], 1), axis=0)
    count = np.bincount(pairs[:, 0], minlength=n)
    new_vertices = np.flatnonzero(count == 3)
    if len(new_vertices) < (1 - MAX_BAD_SHARE) * np.count_nonzero(lab == ODD):
        return None
    rows = pairs[count[pairs[:, 0]] == 3]  # sorted by new vertex, three old each
    tri = rows[:, 1].reshape(-1, 3)
    centre_of = rows[::3, 0]
    even = np.unique(tri)
    index = np.full(n, -1, np.int64)
    index[even] = np.arange(len(even))
    coarse = index[tri]
    # orientation: like the fan of fine faces around the new vertex
    fan = np.zeros((n, 3))
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    normals = np.cross(b - a, c - a)
    for k in range(3):
        np.add.at(fan, faces[:, k], normals)
    p0, p1, p2 = (vertices[tri[:, k]] for k in range(3))
    flip = (np.cross(p1 - p0, p2 - p0) * fan[centre_of]).sum(axis=1) < 0
    coarse[flip] = coarse[flip][:, ::-1]
    rows3 = np.repeat(np.arange(len(coarse)), 3)
    S = sp.csr_matrix((np.full(coarse.size, 1.0 / 3.0), (rows3, coarse.ravel())),
                      shape=(len(coarse), len(even)))
    solved = _least_squares(S, vertices[centre_of], vertices[even])
    return None if solved is None else ("sqrt3", solved, coarse)

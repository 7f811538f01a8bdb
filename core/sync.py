"""Carrier selection and synchronisation without a global order (the paper's gap closed).

The paper ranks vertices by D(V) on the current mesh and orders every carrier by its distance
to one head vertex.  Both change when carriers move, and cropping removes the head.  Here:

* every vertex gets a *label* from its local connectivity only: Weisfeiler-Lehman colour
  refinement over ``ROUNDS`` rings, which no geometric change (the embedding itself, noise,
  similarity transforms) can alter and which ignores vertex and face order;
* on regular meshes, where connectivity alone leaves most vertices alike (icospheres,
  subdivided CAD), the label is combined with the cell of the neighbours' mean in a
  normalised frame of the mesh (the geometric fallback);
* the key turns labels into a priority and a bit slot; carriers are the greedy maximal
  independent set by priority (no two carriers adjacent, so no carrier is in another's
  neighbourhood), built in parallel rounds: a vertex joins when its priority beats every live
  neighbour's.  Ties are never broken by index: tied neighbours both stay out.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, replace

import numpy as np

from core.hashing import combine, mix64
from core.mesh import Adjacency
from core.parallel import SPLIT_FROM, by_chunks

#: rings of colour refinement (the label of a vertex depends on its ROUNDS-ring), then the
#: larger neighbourhoods tried on regular meshes before the geometric fallback
ROUNDS = 3
ROUND_STEPS = (3, 6, 9, 12)
#: more rings while fewer than this share of the usable vertices have distinct labels, and, once
#: there are ENOUGH_LABELS, as long as wider rings multiply them by MORE_RINGS_GAIN (a CAD part gains
#: 5 % from 3 to 12 rings, and 12-ring labels were lost to a crop: 0/2 against 2/2 with 3)
MORE_RINGS_BELOW, MORE_RINGS_GAIN = 0.5, 1.1
#: a mesh counts as regular (connectivity cannot tell its vertices apart) when fewer than
#: MORE_RINGS_BELOW of its usable vertices have distinct labels and these are fewer than
#: ENOUGH_LABELS (too few slots for a long codeword: the Sink's largest part) or than REGULAR_SHARE
#: of the vertices; a CAD part of 26 % distinct labels but 11k of them keeps its connectivity
ENOUGH_LABELS, REGULAR_SHARE = 1024, 0.02
#: distinct labels are counted exactly up to this many vertices, estimated above (distinct_count)
EXACT_UP_TO = 1 << 16
#: ...or when more than this share of them has a neighbour with the same label (rings of a surface
#: of revolution: tied neighbours never win, and no pose-invariant quantity tells them apart)
TIED_SHARE = 0.5
#: bits of a priority that a pose-invariant geometric tie-break replaces (equal labels only differ there)
TIE_BITS = 20
#: offset of the fallback grid, in cells (irrational, so that symmetric meshes do not sit on cell
#: boundaries: a cube's faces would otherwise lie exactly on grid planes)
GRID_OFFSET = np.array([0.381966, 0.2360679, 0.1458980])
#: fallback grid cell = CELLS_PER_RADIUS x RMS radius / sqrt(vertex count), about half an edge
CELLS_PER_RADIUS = 2.0
#: valences a carrier may have
MIN_DEGREE, MAX_DEGREE = 4, 12
#: boundary vertices (open rings) may carry too, with at least this many neighbours
MIN_BOUNDARY_DEGREE = 3


def wl_colours(adj: Adjacency, rounds: int = ROUNDS, start: np.ndarray | None = None,
               first: int = 0) -> np.ndarray:
    """Colour refinement of the connectivity graph.

    Parameters
    ----------
    rounds : int
        Refinement rounds: the colour of a vertex then depends on its ``rounds``-ring.
    start, first : optional
        Resume from the colours ``start`` obtained after ``first`` rounds.

    Returns
    -------
    (n,) uint64
        Hash of each vertex's ``rounds``-ring connectivity (degree, boundary and non-manifold
        flags), independent of vertex numbering and of geometry.
    """
    if start is None:
        init = (adj.degree.astype(np.uint64) << np.uint64(2)) | (
            adj.boundary.astype(np.uint64) << np.uint64(1))
        c = mix64(init | adj.nonmanifold.astype(np.uint64))
        first = 0
    else:
        c = start
    n = len(c)
    if not n:
        return c
    # a large mesh in two row halves, the second in the rows' worker: each round's hashes, then its
    # neighbour sums (the whole vector of hashes is needed first) and their combination; a smaller
    # one in one piece, in this thread
    half = -(-n // 2) if n >= SPLIT_FROM else n
    for t in range(first, rounds):
        salt = np.uint64(0x5851F42D4C957F2D * (t + 1) % 2**64)

        def hashed(lo: int, hi: int, c: np.ndarray = c, salt: np.uint64 = salt) -> np.ndarray:
            return mix64(c[lo:hi] ^ salt)

        m = np.concatenate(by_chunks(hashed, n, half))

        def refined(lo: int, hi: int, c: np.ndarray = c, m: np.ndarray = m) -> np.ndarray:
            return combine(c[lo:hi], adj.ring_block(lo, hi) @ m)

        c = np.concatenate(by_chunks(refined, n, half))
    return c


def distinct_count(values: np.ndarray) -> int:
    """Number of distinct values of well-mixed uint64 hashes: exact (``np.unique``) up to
    :data:`EXACT_UP_TO` values, else linear counting over the low 22 bits (within ~1 % at a few
    million values, and an O(n) scatter instead of a sort: ``np.unique`` took 0.6-1.6 s per
    refinement step on a 1M-vertex mesh).  Depends on the set of values only, not their order."""
    if values.size <= EXACT_UP_TO:
        return int(np.unique(values).size)
    m = 1 << 22
    seen = np.zeros(m, bool)
    seen[(values & np.uint64(m - 1)).astype(np.intp)] = True
    filled = int(np.count_nonzero(seen))
    if filled >= m:
        return int(values.size)
    return min(int(values.size), round(-m * np.log1p(-filled / m)))


def is_regular(colours: np.ndarray, usable: np.ndarray, adj: Adjacency | None = None,
               distinct: int | None = None) -> bool:
    """True when connectivity labels cannot tell the usable vertices apart: a minority of distinct
    values and, of those, fewer than :data:`ENOUGH_LABELS` or fewer than :data:`REGULAR_SHARE` of
    the vertices (counted by value with :func:`distinct_count`: a 1/16 sample by value read 0.89
    distinct on a CAD part where the truth was 0.06, missing its few dominant labels); or, given
    ``adj``, more than :data:`TIED_SHARE` of them next to a vertex of the same label (looked at
    only with a minority of distinct values).  ``distinct``: the count, when the caller has it."""
    count = int(usable.sum())
    if count == 0:
        return False
    if distinct is None:
        distinct = distinct_count(colours[usable])
    if distinct >= MORE_RINGS_BELOW * count:
        return False
    if distinct < ENOUGH_LABELS or distinct < REGULAR_SHARE * count:
        return True
    if adj is None or not adj.indices.size:
        return False
    tied = np.bincount(adj.rows, colours[adj.rows] == colours[adj.indices], minlength=len(colours)) > 0
    return bool(tied[usable].mean() > TIED_SHARE)


def tie_broken(priority: np.ndarray, vertices: np.ndarray, adj: Adjacency) -> np.ndarray:
    """``priority`` with its low :data:`TIE_BITS` replaced by the distance of each vertex's
    neighbour mean to the centroid of the mesh, quantised: neighbours with equal labels (equal
    priorities, which never win against each other) are then told apart by a quantity that
    rotation, translation, scaling and re-ordering leave alone, and that moving a carrier does not
    change (its neighbours are not carriers)."""
    n = len(vertices)
    x = neighbour_means(vertices, adj) - vertices.mean(axis=0)
    d = np.sqrt(x[:, 0] ** 2 + x[:, 1] ** 2 + x[:, 2] ** 2)
    top = float(d.max()) if n else 0.0
    q = np.floor(d / (top or 1.0) * ((1 << TIE_BITS) - 1)).astype(np.uint64)
    high = priority & ~np.uint64((1 << TIE_BITS) - 1)
    # a priority of 0 never wins: keep the tie-broken ones above it
    return np.maximum(high | q, np.uint64(1))


#: two second moments of a regular mesh's vertices within this share of the largest are a
#: degenerate pair (a surface of revolution, a cylinder); all three alike: no frame but the file's
FRAME_GAP = 0.1
#: a third moment under this share of ``r^3`` does not fix the sign of its axis
FRAME_SKEW = 1e-3
#: the angle of a degenerate pair: the vertices' angular harmonics about the unique axis (weighted
#: by the distance to it) up to FRAME_HARMONICS; the lowest within FRAME_FUNDAMENTAL of the strongest
#: is the pair's (the capsule's 100 segments read 1.0 at m = 100 and at 200), and the strongest must
#: reach FRAME_HARMONIC_MIN, else the pair has no angle and the file's axes stay
FRAME_HARMONICS, FRAME_FUNDAMENTAL, FRAME_HARMONIC_MIN = 256, 0.9, 0.5
#: angle bins of the histogram whose FFT ranks the harmonics (the chosen one is then summed exactly)
FRAME_BINS = 4096


@dataclass(frozen=True)
class CellFrame:
    """A normalised frame of a regular mesh's vertices: ``origin``, ``unit`` (RMS radius) and
    ``axes`` (rows).  ``others``: the frames the detector also tries, where this one rests on
    what a rotation changes (:func:`cell_frame`)."""

    origin: np.ndarray
    unit: float
    axes: np.ndarray
    others: tuple[np.ndarray, ...] = ()


#: the file direction that signs the axes a third moment leaves loose and from which the turns of a
#: degenerate pair are counted: not along nor across the axes of usual files (file axes, their
#: diagonals), so that the choice does not jump when carriers move (the largest coordinate, or the
#: file axis least along the unique one, did on a cylinder: two file axes tie there)
FRAME_REFERENCE = np.array([3.0, 2.0, 1.0]) / np.sqrt(14.0)


def _file_aligned(axis: np.ndarray) -> np.ndarray:
    """``axis`` with the sign that puts it along :data:`FRAME_REFERENCE`."""
    return axis if axis @ FRAME_REFERENCE >= 0 else -axis


def _harmonic(x: np.ndarray, p: np.ndarray, q: np.ndarray) -> tuple[int, float] | None:
    """The pair's harmonic ``m`` and its phase, about the plane ``(p, q)`` of the centred points
    ``x``: ranked on a histogram of the angles, the chosen one summed exactly; None below
    :data:`FRAME_HARMONIC_MIN`."""
    a, b = x @ p, x @ q
    rho = np.hypot(a, b)
    total = float(rho.sum())
    if not total > 0:
        return None
    theta = np.arctan2(b, a)
    bins = (np.floor((theta + np.pi) / (2.0 * np.pi) * FRAME_BINS).astype(np.int64)) % FRAME_BINS
    hist = np.bincount(bins, rho, minlength=FRAME_BINS)
    mag = np.abs(np.fft.fft(hist)[1:FRAME_HARMONICS + 1]) / total
    if mag.max() < FRAME_HARMONIC_MIN:
        return None
    m = int(np.flatnonzero(mag >= FRAME_FUNDAMENTAL * mag.max())[0]) + 1
    s = complex((rho * np.exp(1j * m * theta)).sum())
    if abs(s) < FRAME_HARMONIC_MIN * total:
        return None
    return m, float(np.angle(s)) / m


def cell_frame(vertices: np.ndarray) -> CellFrame:
    """The frame of the geometric fallback: centroid, RMS radius as unit, and the principal axes.

    * Three separate second moments (>= :data:`FRAME_GAP` apart): the principal axes, each signed
      by its third moment; where all three fix their signs this is all (as before the candidates).
      An axis whose third moment does not (:data:`FRAME_SKEW`: a symmetric part) takes the sign
      along :data:`FRAME_REFERENCE`, and the last such one the sign that makes the frame
      right-handed; the detector tries the other signs of all but the last.
    * A degenerate pair beside a unique axis (a surface of revolution): the unique axis (signed
      as above) and, about it, the angle of the vertices' strongest angular harmonic ``m``
      (:func:`_harmonic`), which fixes it up to ``2 pi / m``: the embedder takes the turn nearest
      :data:`FRAME_REFERENCE`, the detector tries the other ``m - 1`` (and the
      unique axis turned over, when its sign is not fixed).  Without a harmonic: the file's axes.
    * Three alike (a sphere, a cube): the file's axes.

    Wherever the frame rests on the file's axes, the detector also tries the file's axes
    themselves (what the fallback used for every such mesh before the candidates)."""
    c = vertices.mean(axis=0)
    x = vertices - c
    r = float(np.sqrt((x * x).sum(axis=1).mean())) or 1.0
    eye = np.eye(3)
    w, e = np.linalg.eigh(x.T @ x / len(x))
    gaps = np.diff(w) / max(w[-1], 1e-300)
    axes = e.T.copy()
    skew = ((x @ e) ** 3).mean(axis=0)
    sure = np.abs(skew) > FRAME_SKEW * r**3
    if np.all(gaps > FRAME_GAP):
        if sure.all():
            return CellFrame(c, r, axes * np.sign(skew)[:, None])
        loose = np.flatnonzero(~sure)
        for k in range(3):
            axes[k] = axes[k] * np.sign(skew[k]) if sure[k] else _file_aligned(axes[k])
        if np.linalg.det(axes) < 0:
            axes[loose[-1]] = -axes[loose[-1]]
        others = [eye]
        free = loose[:-1]
        for flips in range(1, 1 << len(free)):
            alt = axes.copy()
            for bit, k in enumerate(free):
                if flips >> bit & 1:
                    alt[k] = -alt[k]
            # the last loose axis keeps the frame right-handed
            if np.linalg.det(alt) < 0:
                alt[loose[-1]] = -alt[loose[-1]]
            others.append(alt)
        return CellFrame(c, r, axes, tuple(others))
    if np.all(gaps <= FRAME_GAP):
        return CellFrame(c, r, eye)
    unique = 2 if gaps[0] <= FRAME_GAP else 0
    u = axes[unique] * np.sign(skew[unique]) if sure[unique] else _file_aligned(axes[unique])
    # the turns are counted from the reference direction (a file axis where the unique axis lies
    # along it)
    p = FRAME_REFERENCE - (FRAME_REFERENCE @ u) * u
    if np.linalg.norm(p) < 1e-3:
        p = eye[int(np.argmin(np.abs(u)))] - u[int(np.argmin(np.abs(u)))] * u
    p /= np.linalg.norm(p)
    q = np.cross(u, p)
    got = _harmonic(x, p, q)
    if got is None:
        return CellFrame(c, r, eye)
    m, phase = got
    pair = [0, 1] if unique == 2 else [1, 2]

    def turned(angle: float, sign: float) -> np.ndarray:
        e0 = np.cos(angle) * p + np.sin(angle) * q
        out = np.empty((3, 3))
        out[unique], out[pair[0]] = sign * u, e0
        out[pair[1]] = np.cross(out[unique], e0) if unique == 2 else np.cross(e0, out[unique])
        return out

    turns = phase + 2.0 * np.pi * np.arange(m) / m
    signs = (1.0,) if sure[unique] else (1.0, -1.0)
    frames = [turned(t, s) for s in signs for t in turns]
    return CellFrame(c, r, frames[0], (eye, *frames[1:]))


def frame_cells(points: np.ndarray, frame: CellFrame, cell: float, axes: np.ndarray | None = None
                ) -> np.ndarray:
    """Hash of the grid cell of ``points`` in ``frame`` (``axes``: one of its ``others`` instead of
    its own axes), cells of ``cell`` RMS radii."""
    e = (frame.axes if axes is None else axes).T
    q = np.floor(((points - frame.origin) @ e) / (frame.unit * cell) + GRID_OFFSET).astype(np.int64)
    h = mix64(q[:, 0].view(np.uint64))
    h = combine(h, q[:, 1].view(np.uint64))
    return combine(h, q[:, 2].view(np.uint64))


@dataclass(frozen=True)
class Labels:
    """Per-vertex synchronisation labels (keyless) and whether the geometric fallback was used."""

    labels: np.ndarray
    usable: np.ndarray
    regular: bool
    connectivity: np.ndarray  # the colour refinement alone (reused when only geometry changed)
    rounds: int = ROUNDS  # rounds of the refinement


def vertex_labels(vertices: np.ndarray, adj: Adjacency, previous: Labels | None = None) -> Labels:
    """Keyless label of every vertex and the mask of vertices that may carry a bit.

    ``previous``: labels of the same connectivity (only the geometric fallback is recomputed).
    """
    if previous is not None:
        if not previous.regular:
            return previous
        labels = combine(previous.connectivity, _fallback_cells(vertices, adj))
        return replace(previous, labels=labels)
    usable = (~adj.nonmanifold) & (adj.degree >= np.where(adj.boundary, MIN_BOUNDARY_DEGREE, MIN_DEGREE)) & (
        adj.degree <= MAX_DEGREE)
    # more rings only where fewer cannot tell vertices apart (subdivided meshes); the choice
    # depends on connectivity only, so embedder and detector make the same one
    colours: np.ndarray | None = None
    done = 0
    distinct = 0
    for rounds in ROUND_STEPS:
        wider = wl_colours(adj, rounds, colours, done)
        count = distinct_count(wider[usable])
        if colours is not None and distinct >= ENOUGH_LABELS and count < MORE_RINGS_GAIN * distinct:
            break  # plenty of labels, and wider rings barely add any (CAD): keep the narrower ones
        colours, done, distinct = wider, rounds, count
        if not usable.any() or distinct >= MORE_RINGS_BELOW * usable.sum():
            break
    assert colours is not None
    return _labelled(vertices, adj, colours, usable, done, distinct)


def _stepped_rounds(labels: Labels, step: int) -> int | None:
    """The round count ``step`` steps of :data:`ROUND_STEPS` from ``labels``' (None: past either
    end, or no usable vertex)."""
    k = ROUND_STEPS.index(labels.rounds) + step if labels.rounds in ROUND_STEPS else -1
    return ROUND_STEPS[k] if 0 <= k < len(ROUND_STEPS) and labels.usable.any() else None


def has_step(labels: Labels, step: int) -> bool:
    """Whether :func:`stepped_labels` has labels ``step`` steps of :data:`ROUND_STEPS` from these."""
    return _stepped_rounds(labels, step) is not None


def stepped_labels(vertices: np.ndarray, adj: Adjacency, labels: Labels, step: int) -> Labels | None:
    """The labels of :func:`vertex_labels` refined ``step`` steps of :data:`ROUND_STEPS` further (+1)
    or fewer (-1), or None when there is no such step (the choice depends on connectivity only).
    What the whole mesh had when a crop made its piece stop elsewhere.  A crop breaks the symmetries
    that leave labels alike, so the piece has more distinct labels at fewer rounds and can stop a
    step earlier (the Beast: 0.38 of its labels distinct at 3 rounds, 6 chosen; its crops to 25 %:
    0.54-0.62 at 3 rounds, 3 chosen, and no carrier of theirs with a label of the whole); or wider
    rings gain more labels in the piece than in the whole, and it goes a step further (the Ogre: 9
    rounds, 12 adding under 10 %; a crop to 50 %: 12).  Wider labels resume the refinement from
    ``labels``; narrower ones are refined anew."""
    rounds = _stepped_rounds(labels, step)
    if rounds is None:
        return None
    colours = (wl_colours(adj, rounds, labels.connectivity, labels.rounds) if rounds > labels.rounds
               else wl_colours(adj, rounds))
    return _labelled(vertices, adj, colours, labels.usable, rounds, distinct_count(colours[labels.usable]))


def _labelled(vertices: np.ndarray, adj: Adjacency, colours: np.ndarray, usable: np.ndarray, rounds: int,
              distinct: int) -> Labels:
    """:class:`Labels` of the colours after ``rounds`` rounds, ``distinct`` of them on ``usable``
    vertices (with the geometric fallback on a regular mesh)."""
    if is_regular(colours, usable, adj, distinct):
        return Labels(combine(colours, _fallback_cells(vertices, adj)), usable, True, colours, rounds)
    return Labels(colours, usable, False, colours, rounds)


def neighbour_means(vertices: np.ndarray, adj: Adjacency) -> np.ndarray:
    """(n, 3) mean of each vertex's neighbours (isolated vertices: 0)."""
    deg = np.maximum(adj.degree, 1)
    return adj.ring_sum(vertices) / deg[:, None]


def _fallback_cells(vertices: np.ndarray, adj: Adjacency, frame: CellFrame | None = None,
                    axes: np.ndarray | None = None) -> np.ndarray:
    """Cell hash of every vertex's neighbour mean (neighbour-only, so a carrier's own label
    does not move with it) in ``frame`` (default: :func:`cell_frame` of ``vertices``) turned to
    ``axes``, when given."""
    n = len(vertices)
    mu = neighbour_means(vertices, adj)
    # cell size from the vertex count only: the median edge length moves with the carriers
    # and a 0.1 % change of the cell shifts far cells by a whole cell
    frame = cell_frame(vertices) if frame is None else frame
    return frame_cells(mu, frame, CELLS_PER_RADIUS / np.sqrt(max(n, 1)), axes)


def turned_labels(vertices: np.ndarray, adj: Adjacency, labels: Labels, frame: CellFrame | None = None
                  ) -> Iterator[Labels]:
    """``labels`` of a regular mesh with the fallback's cells in each frame the detector also
    tries (:attr:`CellFrame.others` of ``frame``, default :func:`cell_frame` of ``vertices``: a
    rotated file's frame where the mesh's moments leave a sign or an angle to the file's axes);
    nothing for other meshes."""
    if not labels.regular:
        return
    frame = cell_frame(vertices) if frame is None else frame
    for axes in frame.others:
        cells = _fallback_cells(vertices, adj, frame, axes)
        yield replace(labels, labels=combine(labels.connectivity, cells))


def select_carriers(adj: Adjacency, priority: np.ndarray, usable: np.ndarray) -> np.ndarray:
    """Greedy maximal independent set of ``usable`` vertices by decreasing ``priority``.

    Parallel rounds: a live vertex is selected when its priority is strictly larger than every
    live neighbour's; selected vertices and their neighbours then leave.  Equal neighbours never
    win against each other (no index tie-break).

    Returns
    -------
    (k,) int64
        Selected vertex indices, sorted.
    """
    n = len(priority)
    selected = np.zeros(n, bool)
    alive = usable.copy()
    # a vertex that is not alive (unusable, selected or next to a selected one) has priority 0
    # for its neighbours: it never blocks one (a priority of exactly 0 never wins either)
    live = np.where(alive, priority, np.uint64(0))
    todo = np.flatnonzero(alive)
    while todo.size:
        if 2 * todo.size > n:  # most of the mesh: straight from the CSR
            nbmax = adj.ring_max(live)[todo]
        else:
            first, pos = adj.ring_entries(todo)
            has = adj.degree[todo] > 0
            nbmax = np.zeros(todo.size, np.uint64)
            if pos.size:
                nbmax[has] = np.maximum.reduceat(live[adj.indices[pos]], first[has])
        win = todo[priority[todo] > nbmax]
        if not win.size:
            break
        selected[win] = True
        gone = np.concatenate([win, adj.indices[adj.ring_entries(win)[1]]])
        alive[gone] = False
        live[gone] = 0
        todo = todo[alive[todo]]
    return np.flatnonzero(selected)

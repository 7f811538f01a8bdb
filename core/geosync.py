"""Geometric synchronisation: carriers and slots from positions in a pose-invariant frame.

The connectivity labels of :mod:`core.sync` survive cropping, noise and smoothing, but not a
re-triangulation: after a meshoptimizer simplification of 10 % every carrier of the bunny still
exists, in place and reading its bit, but only 4 % keep their label (``core/README.md``, 2b).  This
layer finds carriers again by where they are on the surface:

* **Frame.**  The area-weighted centroid, principal axes and RMS radius ``rho`` of the *surface*
  (exact triangle integrals, so a re-triangulation of the same surface leaves them alone): signs
  from the third moments; when two second moments are within :data:`DEGENERATE` of each other
  (surfaces of revolution, gears, square plates) the angle about the third axis comes from the
  strongest angular harmonic ``m`` of the surface (integrated over its faces), which fixes it up
  to ``2 pi / m``; of those turns the one where the surface's angular density is highest, the
  others that tie with it are detector candidates.
* **Cells.**  A keyed offset grid of spacing ``h`` (a rung of :func:`rung_size`, a few edges) in
  that frame; in every cell the usable vertex nearest to the cell's centre is a carrier, and the
  cell's keyed hash its slot hash.  A simplification that keeps a vertex keeps it nearest (removing
  others cannot bring one closer); a vertex that goes is replaced by one of its old neighbours,
  which reads the bit more often than not (its ring contains the moved carrier).
* **Candidates.**  What the detector cannot know for sure (a sign of a third moment near 0, the
  ``2 pi / m`` ambiguity of a symmetric part, the rung after a simplification lengthened the
  edges) is enumerated by :func:`frame_candidates` and :func:`rung_candidates`; the detector
  decodes the candidate whose votes agree best within slots, a statistic that does not depend on
  the payload (:mod:`core.detection`).

A cropped piece has another frame: its carriers are found by the connectivity layer.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from core.eig3 import eigh3
from core.hashing import combine, derive, mix64
from core.mesh import Adjacency, columns, neighbour_moments
from core.parallel import CHUNK_ROWS, by_chunks, by_rows, joined

#: two sqrt-eigenvalues of the surface's second moment within this ratio are one degenerate pair
#: (the gear: 1.011, whose axes turned 0.2-0.4 degrees under simplification; bunny 1.28: 0.03)
DEGENERATE = 1.1
#: a third moment (skewness) below this is not trusted to fix its axis' sign: both are candidates
SKEW_SURE = 0.05
#: angular harmonics looked at for the angle of a degenerate pair, and the normalised magnitude
#: the strongest must reach (a surface of revolution has none: no geometric carriers then)
MAX_HARMONIC = 64
MIN_HARMONIC = 0.02
ANGLE_BINS = 4096
#: the spectrum integrates the surface, not its vertices: every face is cut into n x n
#: sub-triangles, n <= SUBDIVIDE, that span at most ANGLE_SPAN (radians) about the pair's axis.
#: Vertex weights (a third of the faces' area each) put a CAD sliver's area at its ends: on the
#: counter plate that made lines of the tessellation (m = 55, 110, 62) stronger than the surface's
#: (m = 20) and after quadric simplification or noise the strongest jumped (15, 2, 20); integrated,
#: m = 20 leads (0.065, next 0.044) and its phase moves <= 0.003 degrees under quadric 10-50 %,
#: meshoptimizer 5-10 % and noise 0.3 %, the gear's m = 38 <= 0.0025 (0.05-0.28 with vertex
#: weights).  A fan of 63 slivers keeps a line at m = 63 of 0.034 at 2 degrees, 0.003 at 1 (the
#: fine mesh's: 0.002); the frame costs 38 ms on the counter, 81 ms on the gear (33 at 2 degrees)
ANGLE_SPAN = float(np.radians(1.0))
SUBDIVIDE = 32
#: the detector also tries every harmonic within HARMONIC_CLOSE of the strongest as the one that
#: fixed the angle (measured ratios of the runner-up: counter 0.68, gear 0.57, within 2 % under attacks)
HARMONIC_CLOSE = 0.8
#: of the 2 pi / m turns of the strongest harmonic m, the embedder takes the one where the surface's
#: angular density (:func:`turn_density`) is highest, and the detector tries every turn whose
#: density is within TURN_TIE of the spread (best - median) of the best: the gear's best turn leads
#: the next by 0.039 of a spread of 0.093 (one turn tried, not 38), the counter's five turns of its
#: 5-fold symmetry tie within 0.0003 and lead the rest by 0.20 (five tried, not 20); quadric 50 %,
#: meshoptimizer 10 % and noise 0.3 % changed none of that (noise scales the counter's all alike)
TURN_TIE = 0.15
#: ...and every turn within TURN_NOISE of it (an exactly symmetric part: its turns differ by the
#: quadrature's error alone, 0.001 on a 7-fold plate)
TURN_NOISE = 0.01
#: cell sizes are rungs ``2**(k / 4) / 256`` of rho; the embedder takes the finest rung whose
#: carriers are at most CARRIER_SHARE of the usable vertices (a simplification changes that: the
#: detector tries rungs)...
CARRIER_SHARE = 0.09
#: ...and no finer than the rung of about TARGET_CELLS cells on the surface.  CAD meshes put their
#: vertices on features (the counter plate's pegs, the gear's pins) and leave large faces empty:
#: there the share never binds and this floor decides.  At 8192 cells the counter got 292 carriers
#: (0.7 % of its vertices) and the gear 700 (3.3 %); at 131072, 1754 (4.2 %) and 1777 (8.3 %).
#: The bunny, horse, armadillo and rocker arm are held by the share either way; the dragon
#: (2757 -> 4187), turbine blade (3609 -> 8427) and beetle (1539 -> 1726) get finer rungs
TARGET_CELLS = 131072
#: rungs the detector tries below and above its own estimate.  The carriers a rung gets hardly
#: depend on it where the share binds (Beast's marked file: 2,558 at rung 10, 2,867 at rung 5), so
#: when a simplification halves the vertices, and with them the share's limit, the estimate moves
#: far: quadric 50 % took Beast's from the embedder's rung 9 to 14 and Ogre's from 6 to 11 (3 below,
#: as until 2026-12-06, read neither; 6 below read both, with both methods, and Beast's quadric 30 %
#: with planes).  Never below the area's rung, where large meshes are: they try no more rungs
RUNGS_BELOW, RUNGS_ABOVE = 6, 1
#: valences a geometric carrier may have (a simplification changes valences: looser than core.sync's)
MIN_VALENCE, MAX_VALENCE = 3, 24
#: a vertex competes for its cell within BALL cells of the centre, and the NEAREST such vertices in
#: space are compared in their tangent planes (geometric_carriers)
BALL, NEAREST = 0.35, 4


def in_frame(points: np.ndarray, origin: np.ndarray, axes: np.ndarray) -> np.ndarray:
    """``(points - origin) @ axes.T`` column by column: numpy hands an ``(n, 3) @ (3, 3)`` product to
    BLAS, whose threads made it 10x slower than this (14 ms against 1.3 ms at 100k points on this
    machine with another process on the second core)."""
    p = [np.asarray(points[:, k], np.float64) - origin[k] for k in range(3)]
    out = np.empty((len(points), 3))
    for j in range(3):
        out[:, j] = _along(p, axes[j])
    return out


def _along(p: list[np.ndarray], axis: np.ndarray) -> np.ndarray:
    """The coordinate along ``axis`` of the points whose (centred) coordinate columns are ``p``."""
    return p[0] * axis[0] + p[1] * axis[1] + p[2] * axis[2]


class Rings:
    """The least-variance axes of the 1-rings of a mesh whose positions stay as they are (the
    first eigenvector of :func:`neighbour_moments`' covariance, :func:`~core.eig3.eigh3`), made for
    the vertices asked for and kept: a detection compares the same candidates in their tangent
    planes at every placement and rung it tries (22 choices of geometric carriers in a detection of
    an unmarked 1M-vertex mesh), and a rung search at each rung.  Every vertex's axis is the one a
    call on any set of vertices that contains it gives (both are per vertex).  Only the axes are
    kept (24 bytes a vertex): keeping the whole moments raised the peak of that detection by 115 MB."""

    def __init__(self, vertices: np.ndarray, adj: Adjacency) -> None:
        self.vertices, self.adj = vertices, adj
        self._known = np.zeros(len(vertices), bool)
        self._least = np.empty((len(vertices), 3))

    def least(self, which: np.ndarray) -> np.ndarray:
        """``(k, 3)`` least-variance axis of the neighbours of each vertex of ``which``."""
        which = np.asarray(which, np.int64)
        ask = np.zeros(len(self._known), bool)
        ask[which[~self._known[which]]] = True
        missing = np.flatnonzero(ask)
        if missing.size:
            cols = columns(self.vertices)
            self._least[missing] = by_rows(
                lambda part: (eigh3(neighbour_moments(self.vertices, self.adj, part, cols)[1])[1][:, :, 0],),
                missing)[0]
            self._known[missing] = True
        return self._least[which]

    def forget(self, moved_rings: np.ndarray) -> None:
        """Drop the axes of the vertices of the mask ``moved_rings`` (a neighbour of theirs moved: the
        positions are an array changed in place, as the embedder's are); asked again, they are made
        at the new positions."""
        self._known &= ~np.asarray(moved_rings, bool)


@dataclass(frozen=True)
class SurfaceFrame:
    """Pose-invariant frame of a surface.

    Attributes
    ----------
    centroid : (3,) float64
    axes : (3, 3) float64
        Rows are the frame's axes (right-handed), by decreasing second moment.
    rho : float
        RMS distance of the surface to its centroid (area-weighted).
    area : float
        Area of the surface.
    sqrt_ratios : (2,) float64
        ``sqrt(l1 / l2)``, ``sqrt(l2 / l3)`` of the second moments ``l1 >= l2 >= l3``.
    skew : (3,) float64
        Third moment along each axis over its second moment to the power 3/2.
    degenerate : int
        -1 for three distinct axes, else the index (0 or 1) of the first axis of the degenerate pair.
    harmonic : int
        The angular harmonic that fixed the angle of a degenerate pair (0 when none is needed).
    turns : (t,) float64
        Turns (radians, about the unique axis, from ``axes``) of the degenerate pair the detector
        tries, 0 first (:func:`frame_candidates`); empty without a degenerate pair.
    """

    centroid: np.ndarray
    axes: np.ndarray
    rho: float
    area: float
    sqrt_ratios: np.ndarray
    skew: np.ndarray
    degenerate: int
    harmonic: int
    turns: np.ndarray = field(default_factory=lambda: np.zeros(0))


#: faces per chunk of the frame's integrals (temporaries of a few MB: no page faults on large meshes)
CHUNK = 1 << 17


def _face_integrals(v: np.ndarray, f: np.ndarray
                    ) -> tuple[float, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Exact area, centroid and second moment (about the centroid, per unit area) of the surface,
    every face's area, and every vertex's sum of the areas of its faces.

    The integral of ``x x^T`` over a triangle is ``area / 12 (sum p_i p_i^T + s s^T)`` (``s`` the sum
    of its corners): the corner terms are summed per vertex, weighted by its faces' areas, and the
    ``s s^T`` terms per face, in chunks of faces (temporaries of a few MB: no page faults on large
    meshes, and little memory in a worker thread's malloc arena)."""
    n = len(v)
    q = list(columns(v))
    origin = np.array([float(c.mean()) for c in q])  # a provisional origin keeps the sums small
    q = [c - o for c, o in zip(q, origin, strict=True)]
    areas = np.empty(len(f))

    def chunk(lo: int, hi: int) -> tuple[float, np.ndarray, np.ndarray]:
        ft = np.ascontiguousarray(f[lo:hi].T)
        c = [[np.take(q[j], ft[k]) for j in range(3)] for k in range(3)]
        ux, uy, uz = (c[1][j] - c[0][j] for j in range(3))
        wx, wy, wz = (c[2][j] - c[0][j] for j in range(3))
        cx, cy, cz = uy * wz - uz * wy, uz * wx - ux * wz, ux * wy - uy * wx
        area = 0.5 * np.sqrt(cx * cx + cy * cy + cz * cz)
        areas[lo:hi] = area
        s = [c[0][j] + c[1][j] + c[2][j] for j in range(3)]
        first, second = np.zeros(3), np.zeros((3, 3))
        for i in range(3):
            weighted = area * s[i]
            first[i] = float(weighted.sum()) / 3.0
            for j in range(i, 3):
                second[i, j] = _dot(weighted, s[j])
        return float(area.sum()), first, second

    # the chunks' sums added in chunk order, whichever thread made them
    total, first, second = 0.0, np.zeros(3), np.zeros((3, 3))
    for t, fc, sc in by_chunks(chunk, len(f), CHUNK):
        total, first, second = total + t, first + fc, second + sc
    around = (np.bincount(f[:, 0], areas, minlength=n) + np.bincount(f[:, 1], areas, minlength=n)
              + np.bincount(f[:, 2], areas, minlength=n))
    for i in range(3):
        weighted = around * q[i]
        for j in range(i, 3):
            second[i, j] += _dot(weighted, q[j])
    second = (second + np.triu(second, 1).T) / 12.0
    if not total > 0:
        return 0.0, origin, second, areas, around
    mean = first / total
    return total, origin + mean, second / total - np.outer(mean, mean), areas, around


def _dot(a: np.ndarray, b: np.ndarray) -> float:
    """``a . b`` without BLAS (whose threads are slow beside another process: :func:`in_frame`)."""
    return float(np.einsum("i,i->", a, b))


_SUB_POINTS: dict[int, np.ndarray] = {}


def _sub_points(n: int) -> np.ndarray:
    """Barycentric coordinates ``(u, w)`` (weights of the second and third corner) of the centroids
    of the ``n * n`` congruent sub-triangles of a triangle."""
    if n not in _SUB_POINTS:
        i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
        up = (i + j) <= n - 1
        down = (i + j) <= n - 2
        pts = np.concatenate([np.stack([i[up] + 1 / 3, j[up] + 1 / 3], axis=1),
                              np.stack([i[down] + 2 / 3, j[down] + 2 / 3], axis=1)]) / n
        _SUB_POINTS[n] = pts
    return _SUB_POINTS[n]


#: sample points per chunk of the angular spectrum's quadrature (a few MB of temporaries)
SAMPLE_CHUNK = 1 << 20


def angular_spectrum(vertices: np.ndarray, faces: np.ndarray, areas: np.ndarray, centroid: np.ndarray,
                     ex: np.ndarray, ey: np.ndarray) -> np.ndarray:
    """Angular harmonics ``m = 1 .. MAX_HARMONIC`` of the surface about the axis through
    ``centroid`` normal to ``ex, ey``: ``int r exp(i m theta) dA / int r dA`` with ``theta`` the
    angle from ``ex`` towards ``ey`` and ``r`` the distance to the axis.

    Every face is cut into ``n x n`` sub-triangles spanning at most :data:`ANGLE_SPAN` each
    (``n <= SUBDIVIDE``) and each contributes its area at its centroid; the weights are binned by
    angle (:data:`ANGLE_BINS`) and transformed by one FFT.  Faces are taken in chunks of
    :data:`CHUNK` (a few MB of temporaries: whole-mesh arrays of every corner made 400 MB at 1M
    vertices)."""
    v = np.asarray(vertices, np.float64)
    q = [c - centroid[k] for k, c in enumerate(columns(v))]
    px, py = _along(q, ex), _along(q, ey)
    del q
    faces = np.asarray(faces, np.int64).reshape(-1, 3)
    bins = ANGLE_BINS
    scale = bins / (2.0 * np.pi)

    def chunk(lo: int, hi: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        ft = np.ascontiguousarray(faces[lo:hi].T)
        x = [np.take(px, ft[k]) for k in range(3)]
        y = [np.take(py, ft[k]) for k in range(3)]
        # the angle each edge subtends about the axis: |a x b| / (|a| |b|) is its sine, which is the
        # angle itself to 2 % up to 20 degrees; wider edges (and edges through the axis) get arctan2
        r = [np.sqrt(x[k] * x[k] + y[k] * y[k]) for k in range(3)]
        span = np.zeros(len(x[0]))
        for k in range(3):
            a, b = k, (k + 1) % 3
            cross = np.abs(x[a] * y[b] - y[a] * x[b])
            dot = x[a] * x[b] + y[a] * y[b]
            with np.errstate(divide="ignore", invalid="ignore"):
                sine = cross / (r[a] * r[b])
            wide = ~(sine < 0.34) | (dot <= 0)
            if wide.any():
                sine[wide] = np.arctan2(cross[wide], dot[wide])
            np.maximum(span, sine, out=span)
        n = np.clip(np.ceil(span / ANGLE_SPAN), 1, SUBDIVIDE).astype(np.int64)
        # faces narrower than the span (nearly all on a fine mesh): their area at their centroid
        single = n == 1
        ca = areas[lo:hi]
        many = np.flatnonzero(~single)
        if not many.size:
            cx, cy = (x[0] + x[1] + x[2]) / 3.0, (y[0] + y[1] + y[2]) / 3.0
        else:
            one = np.flatnonzero(single)
            cx = (x[0][one] + x[1][one] + x[2][one]) / 3.0
            cy = (y[0][one] + y[1][one] + y[2][one]) / 3.0
            ca = ca[one]
        b = ((np.arctan2(cy, cx) + np.pi) * scale).astype(np.int64)
        part = np.bincount(np.minimum(b, bins - 1), np.sqrt(cx * cx + cy * cy) * ca, minlength=bins)
        return part, many + lo, n[many]

    hist = np.zeros(bins)
    wide_faces, wide_n = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]
    for part, many, n_many in by_chunks(chunk, len(faces), CHUNK):  # added in chunk order
        hist += part
        wide_faces.append(many)
        wide_n.append(n_many)
    # the wider faces (few: 2 % of the 1M-vertex turbine blade's, near the axis), grouped by n
    wider, n = np.concatenate(wide_faces), np.concatenate(wide_n)
    if wider.size:
        order = np.argsort(n, kind="stable")
        by_n = wider[order]
        counts = np.bincount(n, minlength=SUBDIVIDE + 1)
        ends = np.cumsum(counts)
        for k in map(int, np.flatnonzero(counts)):
            uw = _sub_points(k)
            sel = by_n[ends[k] - counts[k]:ends[k]]
            step = max(1, SAMPLE_CHUNK // len(uw))
            u, w = uw[None, :, 0], uw[None, :, 1]
            for lo in range(0, len(sel), step):
                c = sel[lo:lo + step]
                corner = faces[c]
                x0, x1, x2 = (px[corner[:, j]] for j in range(3))
                y0, y1, y2 = (py[corner[:, j]] for j in range(3))
                sx = x0[:, None] + u * (x1 - x0)[:, None] + w * (x2 - x0)[:, None]
                sy = y0[:, None] + u * (y1 - y0)[:, None] + w * (y2 - y0)[:, None]
                mass = np.sqrt(sx * sx + sy * sy) * (areas[c] / (k * k))[:, None]
                b = ((np.arctan2(sy, sx) + np.pi) * scale).astype(np.int64)
                hist += np.bincount(np.minimum(b, bins - 1).ravel(), mass.ravel(), minlength=bins)
    m = np.arange(1, MAX_HARMONIC + 1)
    norm = float(hist.sum()) or 1.0
    # bin b holds angles about (b + 1/2) 2 pi / bins - pi
    return np.fft.ifft(hist)[m] * bins * np.exp(1j * m * (np.pi / bins - np.pi)) / norm


def turn_density(spectrum: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """The surface's angular density at ``angles`` from its harmonics, less the constant term, with
    Fejer's taper: ``sum_m (1 - m / (M + 1)) |F_m| cos(m theta - arg F_m)``.  The quadrature's own
    lines are at the highest harmonics (a 7-fold plate of 252 sectors: 0.007 at m = 64, 0.004 at
    57, below 1e-4 under 50), and untapered they told its seven turns apart by 0.014."""
    m = np.arange(1, len(spectrum) + 1)
    taper = 1.0 - m / (len(spectrum) + 1.0)
    return ((taper * np.abs(spectrum))[None, :]
            * np.cos(np.outer(angles, m) - np.angle(spectrum)[None, :])).sum(axis=1)


def _turns(spectrum: np.ndarray) -> tuple[int, float, np.ndarray] | None:
    """The harmonic that fixes the angle of a degenerate pair, the embedder's angle, and the turns
    (from that angle) the detector tries: those of the strongest harmonic whose angular density
    ties with the best (:data:`TURN_TIE`), then those of every harmonic within
    :data:`HARMONIC_CLOSE` of it (the detector may see another strongest); None when no harmonic
    reaches :data:`MIN_HARMONIC`."""
    mag = np.abs(spectrum)
    order = np.argsort(-mag, kind="stable")
    if mag[order[0]] < MIN_HARMONIC:
        return None
    chosen: list[float] = []
    angle = 0.0
    harmonic = int(order[0]) + 1
    for idx in order:
        if mag[idx] < HARMONIC_CLOSE * mag[order[0]]:
            break
        m = int(idx) + 1
        turns = float(np.angle(spectrum[idx])) / m + 2.0 * np.pi * np.arange(m) / m
        g = turn_density(spectrum, turns)
        rank = np.argsort(-g, kind="stable")
        best = float(g[rank[0]])
        tie = best - max(TURN_TIE * (best - float(np.median(g))), TURN_NOISE)
        keep = turns[rank[g[rank] >= tie]] if m > 1 else turns
        if not chosen:
            angle = float(keep[0])
        chosen.extend(float(t) for t in keep)
    rel = (np.array(chosen) - angle + np.pi) % (2.0 * np.pi) - np.pi
    rel[0] = 0.0
    # the same turn reached from two harmonics is tried once
    out: list[float] = []
    for t in rel:
        if all(abs((t - u + np.pi) % (2.0 * np.pi) - np.pi) > 1e-9 for u in out):
            out.append(float(t))
    return harmonic, angle, np.array(out)


def surface_frame(vertices: np.ndarray, faces: np.ndarray) -> SurfaceFrame | None:
    """The frame of the surface ``(vertices, faces)``, or ``None`` when it has none (no area, or all
    three second moments alike, or a degenerate pair without an angular harmonic: a sphere, a
    surface of revolution).

    Area, centroid and second moments are exact surface integrals, and so, up to a quadrature
    error that does not depend on the triangulation's sliver angles, are the angular harmonics
    (:func:`angular_spectrum`: the angle of a degenerate pair); the third moments (signs) use the
    vertices weighted by a third of the area of their faces, whose error shrinks with the square
    of the edge length."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64).reshape(-1, 3)
    if len(f) == 0:
        return None
    total, centroid, second, areas, around = _face_integrals(v, f)
    if not total > 0:
        return None
    lam, vec = np.linalg.eigh(second)
    lam, vec = np.maximum(lam[::-1], 0.0), vec[:, ::-1].T.copy()
    if not lam[0] > 0:
        return None
    rho = float(np.sqrt(lam.sum()))
    with np.errstate(divide="ignore", invalid="ignore"):
        ratios = np.sqrt(np.array([lam[0] / lam[1], lam[1] / lam[2]]))
    ratios = np.where(np.isfinite(ratios), ratios, np.inf)
    close = ratios < DEGENERATE
    if close.all():
        return None
    # third moments along each axis (their signs fix the axes'), a vertex weighted by a third of
    # the area of its faces (a vertex of no face weighs nothing)
    q = [c - centroid[k] for k, c in enumerate(columns(v))]
    weight = around / 3.0
    third = np.empty(3)
    for j in range(3):
        y = _along(q, vec[j])
        third[j] = _dot(weight, y * y * y) / total
    del q
    # a flat surface has no spread along its normal: no skew there (1e-300 ** 1.5 is 0: 0 / 0)
    skew = np.where(lam > 0, third / np.where(lam > 0, lam, 1.0) ** 1.5, 0.0)
    axes = vec * np.where(skew >= 0, 1.0, -1.0)[:, None]
    degenerate, harmonic = -1, 0
    if close.any():
        degenerate = int(np.flatnonzero(close)[0])
        pair = [degenerate, degenerate + 1]
        # the unique axis keeps its skew sign; the pair's angle from the strongest harmonic
        ex, ey = axes[pair[0]], axes[pair[1]]
        spectrum = angular_spectrum(v, f, areas, centroid, ex, ey)
        got = _turns(spectrum)
        if got is None:
            return None
        harmonic, angle, turns = got
        e0 = np.cos(angle) * ex + np.sin(angle) * ey
        e1 = -np.sin(angle) * ex + np.cos(angle) * ey
        axes = axes.copy()
        axes[pair[0]], axes[pair[1]] = e0, e1
        if np.linalg.det(axes) < 0:
            axes[pair[1]] = -axes[pair[1]]
            turns = -turns  # the pair's second axis turned over: angles about it change sign
        return SurfaceFrame(centroid, axes, rho, total, ratios, skew, degenerate, harmonic, turns)
    elif np.linalg.det(axes) < 0:
        axes[2] = -axes[2]
    return SurfaceFrame(centroid, axes, rho, total, ratios, skew, degenerate, harmonic)


def frame_candidates(frame: SurfaceFrame) -> list[np.ndarray]:
    """Rotations (rows: axes) the detector tries, the embedder's first: each axis sign that its
    third moment does not fix, and the turns of a degenerate pair (``frame.turns``)."""
    base = frame.axes
    if frame.degenerate >= 0:
        pair = [frame.degenerate, frame.degenerate + 1]
        unique = 2 if frame.degenerate == 0 else 0
        signs = [1.0, -1.0] if abs(frame.skew[unique]) < SKEW_SURE else [1.0]
        out = []
        for sign in signs:
            for t in frame.turns:
                r = base.copy()
                r[pair[0]] = np.cos(t) * base[pair[0]] + np.sin(t) * base[pair[1]]
                # the unique axis turned over mirrors the pair's second axis (right-handed)
                r[pair[1]] = sign * (-np.sin(t) * base[pair[0]] + np.cos(t) * base[pair[1]])
                r[unique] = sign * base[unique]
                out.append(r)
        return out
    # axes 0 and 1 carry their own sign; axis 2 follows (right-handed)
    flips = [(1.0, 1.0)]
    loose = np.abs(frame.skew[:2]) < SKEW_SURE
    if loose[0]:
        flips.append((-1.0, 1.0))
    if loose[1]:
        flips += [(s0, -1.0) for s0, _ in list(flips)]
    out = []
    for s0, s1 in flips:
        r = base.copy()
        r[0] *= s0
        r[1] *= s1
        r[2] *= s0 * s1
        out.append(r)
    return out


def rung_size(k: int) -> float:
    """Cell size of rung ``k``, in units of rho: ``2**(k / 4) / 256``."""
    return float(2.0 ** (k / 4.0) / 256.0)


def _rung_at_least(size: float) -> int:
    return int(np.ceil(4.0 * np.log2(max(size * 256.0, 1e-12)) - 1e-9))


def area_rung(frame: SurfaceFrame) -> int:
    """The finest rung: about :data:`TARGET_CELLS` cells on the surface (its area, which no
    re-triangulation changes, alone decides it, so that large meshes need no search)."""
    return _rung_at_least(np.sqrt(frame.area / frame.rho**2 / TARGET_CELLS))


def choose_rung(vertices: np.ndarray, adj: Adjacency, frame: SurfaceFrame, axes: np.ndarray,
                key: str | bytes, rings: Rings | None = None) -> tuple[int, tuple[np.ndarray, np.ndarray]]:
    """The finest rung, not below :func:`area_rung`, whose carriers are at most
    :data:`CARRIER_SHARE` of the usable vertices (smaller cells put carriers of neighbouring cells
    next to each other), and its :func:`geometric_carriers`.  A simplification leaves fewer
    vertices and so a coarser rung here: the detector tries the finer ones too
    (:func:`rung_candidates`)."""
    lo = area_rung(frame)
    limit = CARRIER_SHARE * int(np.count_nonzero(usable(adj)))
    found: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    rings = Rings(vertices, adj) if rings is None else rings

    def fits(k: int) -> bool:
        if k not in found:
            found[k] = geometric_carriers(vertices, adj, frame, axes, k, key, rings)
        return len(found[k][0]) <= limit

    if fits(lo):
        return lo, found[lo]
    step = 8
    hi = lo + step
    while not fits(hi) and hi < lo + 8 * step:
        lo, hi = hi, hi + step
    while hi - lo > 1:  # fits(hi), not fits(lo)
        mid = (lo + hi) // 2
        lo, hi = (lo, mid) if fits(mid) else (mid, hi)
    return hi, found[hi]


def rung_candidates(first: int, frame: SurfaceFrame) -> list[int]:
    """Rungs the detector tries, most likely first: its own choice, then the finer ones a
    simplification may have come from (half the vertices gone: about 2 rungs), then one coarser;
    never below the area's rung."""
    floor = area_rung(frame)
    out = [first] + [first - j for j in range(1, RUNGS_BELOW + 1) if first - j >= floor]
    return out + [first + j for j in range(1, RUNGS_ABOVE + 1)]


@dataclass(frozen=True)
class Placement:
    """Where the geometric carriers of one mesh are: its frame, one rotation of
    :func:`frame_candidates` (rows: axes) and one cell-size rung."""

    frame: SurfaceFrame
    axes: np.ndarray
    rung: int
    #: :func:`geometric_carriers` at the positions the embedder chose it at (None when unknown)
    chosen: tuple[np.ndarray, np.ndarray] | None = None

    @property
    def count(self) -> int:
        """The carriers there when the embedder chose it (0 when unknown)."""
        return 0 if self.chosen is None else len(self.chosen[0])


def embed_placement(vertices: np.ndarray, faces: np.ndarray, adj: Adjacency,
                    key: str | bytes) -> Placement | None:
    """The embedder's placement of a mesh, or ``None`` when its surface has no frame."""
    return placement_in(surface_frame(vertices, faces), vertices, adj, key)


def placement_in(frame: SurfaceFrame | None, vertices: np.ndarray, adj: Adjacency,
                 key: str | bytes) -> Placement | None:
    """:func:`embed_placement` with the mesh's :func:`surface_frame` already made."""
    if frame is None:
        return None
    rung, chosen = choose_rung(vertices, adj, frame, frame.axes, key)
    return Placement(frame, frame.axes, rung, chosen)


def follow(placement: Placement, vertices: np.ndarray, faces: np.ndarray) -> Placement:
    """``placement`` in the frame of the surface as it is now (the embedder's moves change the
    frame: on the counter plate, moves of vertices of its large flat faces shifted the centroid by
    9e-4 rho and rho by 1e-3, a tenth of a cell of rung 10, and 450 of 739 carriers were other
    vertices in the marked file): the rotation of :func:`frame_candidates` nearest to the old one,
    the same rung; the old placement when the surface lost its frame."""
    frame = surface_frame(vertices, faces)
    if frame is None:
        return placement
    cands = frame_candidates(frame)
    best = max(range(len(cands)), key=lambda j: float(np.trace(cands[j] @ placement.axes.T)))
    return Placement(frame, cands[best], placement.rung)


def detect_placements(vertices: np.ndarray, faces: np.ndarray, adj: Adjacency,
                      key: str | bytes, rings: Rings | None = None) -> list[Placement]:
    """Every placement the detector tries on a mesh, the embedder's own first (empty without a frame)."""
    frame = surface_frame(vertices, faces)
    if frame is None:
        return []
    rungs = rung_candidates(choose_rung(vertices, adj, frame, frame.axes, key, rings)[0], frame)
    return [Placement(frame, axes, k) for k in rungs for axes in frame_candidates(frame)]


def usable(adj: Adjacency) -> np.ndarray:
    """Vertices that may be geometric carriers: manifold, valence in [MIN_VALENCE, MAX_VALENCE]."""
    return (~adj.nonmanifold) & (adj.degree >= MIN_VALENCE) & (adj.degree <= MAX_VALENCE)


def geometric_carriers(vertices: np.ndarray, adj: Adjacency, frame: SurfaceFrame, axes: np.ndarray,
                       rung: int, key: str | bytes, rings: Rings | None = None
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Carriers chosen by position: per cell of the keyed grid, the usable vertex nearest its centre.

    Parameters
    ----------
    vertices : (n, 3) float64
    adj : Adjacency
    frame : SurfaceFrame
    axes : (3, 3) float64
        The rotation to use (one of :func:`frame_candidates`).
    rung : int
        Cell size rung (:func:`rung_size`).
    key : str or bytes
    rings : Rings, optional
        The ring axes of ``vertices``, when the caller keeps them.

    Returns
    -------
    carriers : (k,) int64
        Vertex indices, sorted; no two adjacent (of two adjacent winners the smaller hash leaves).
    cell_hash : (k,) uint64
        Keyed hash of each carrier's cell (its slot hash).

    Notes
    -----
    Only vertices within :data:`BALL` cells of their cell's centre compete (a cell the surface
    passes farther from has no carrier), and of those the :data:`NEAREST` nearest in space; among
    them the nearest *in the vertex's tangent plane* wins (the least-variance axis of its
    neighbours, which its own position does not enter), so that a carrier's move along its
    normal, which is what the embedding does, never changes which vertex is nearest.
    """
    h = rung_size(rung)
    if not len(vertices) or not frame.rho > 0:
        return np.zeros(0, np.int64), np.zeros(0, np.uint64)
    rng = np.random.default_rng(derive(key, f"meshmark-goff{rung}"))
    offset = rng.uniform(0.0, h, 3)
    may = usable(adj)

    def chunk(lo: int, hi: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        # the candidates of a chunk of vertices: their cells, offsets from the centres and squared
        # distances (chunks of the whole mesh's passes stay in the cache, and most vertices leave)
        y = in_frame(vertices[lo:hi], frame.centroid, axes) / frame.rho - offset
        cell = np.floor(y / h)
        rest = y - (cell + 0.5) * h
        d3 = rest[:, 0] ** 2 + rest[:, 1] ** 2 + rest[:, 2] ** 2
        near = np.flatnonzero((d3 < (BALL * h) ** 2) & may[lo:hi])
        return near + lo, cell[near].astype(np.int64), rest[near], d3[near]

    cand, c, rest, d3 = joined(by_chunks(chunk, len(vertices), CHUNK_ROWS))
    if not cand.size:
        return np.zeros(0, np.int64), np.zeros(0, np.uint64)
    salt = np.uint64(derive(key, "meshmark-gcell"))
    ch = combine(combine(mix64(c[:, 0].view(np.uint64) ^ salt), c[:, 1].view(np.uint64)),
                 c[:, 2].view(np.uint64))
    order = np.lexsort((d3, ch))
    hs = ch[order]
    start = np.ones(len(order), bool)
    start[1:] = hs[1:] != hs[:-1]
    rank = np.arange(len(order)) - np.maximum.accumulate(np.where(start, np.arange(len(order)), 0))
    near = order[rank < NEAREST]
    sub, sub_h = cand[near], ch[near]
    least = (Rings(vertices, adj) if rings is None else rings).least(sub)
    normal = in_frame(least, np.zeros(3), axes)  # least-variance axis, in the frame
    r = rest[near]
    along = (r * normal).sum(axis=1)
    dt = d3[near] - along * along
    order = np.lexsort((dt, sub_h))
    hs = sub_h[order]
    first = np.ones(len(order), bool)
    first[1:] = hs[1:] != hs[:-1]
    win, win_h = sub[order[first]], hs[first]
    # two winners of neighbouring cells may be adjacent: the smaller cell hash leaves
    n = len(vertices)
    hv = np.zeros(n, np.uint64)
    is_c = np.zeros(n, bool)
    is_c[win] = True
    hv[win] = win_h
    _, pos = adj.ring_entries(win)
    nb = adj.indices[pos]
    rows = np.repeat(win, adj.degree[win])
    lose = np.zeros(n, bool)
    lose[rows[is_c[nb] & (hv[nb] > hv[rows])]] = True
    keep = ~lose[win]
    win, win_h = win[keep], win_h[keep]
    srt = np.argsort(win)
    return win[srt], win_h[srt]

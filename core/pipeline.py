"""File-level embed / detect / capacity: formats + engine + verification + reports."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import Future
from dataclasses import replace
from functools import partial
from typing import NamedTuple

import numpy as np

from core import capacity_model, gf2
from core.analysis import (
    TIE_BREAK_FROM,
    Analysis,
    analyse_geometric,
    analyse_methods,
    pooled,
    prepare,
    priorities,
    tied_pairs,
    vertex_pool,
)
from core.coding import (
    COMPACT_BELOW,
    COMPACT_BITS,
    COMPACT_BUCKET,
    COMPACT_MAX_PAYLOAD,
    KEY_CODE_BITS,
    MAX_PAYLOAD_BITS,
    codeword_length,
    compact_codeword,
    compact_whitening,
    encode,
)
from core.detection import (
    BOTH,
    CONNECTIVITY,
    GEOMETRY,
    INTERIOR,
    NARROWER,
    TURNED,
    WIDER,
    View,
    agreement,
    compact_slots,
    detect_analyses,
    detect_views,
)
from core.embedding import EmbedStats, Quantize, Selection, SlotRule, embed_parts
from core.errors import CapacityError, DegenerateMeshError, PayloadError
from core.formats import DEFAULT_LIMITS, FORMATS, Limits, MeshDocument, MeshPart, read_mesh, weld
from core.geosync import (
    CARRIER_SHARE,
    Placement,
    Rings,
    SurfaceFrame,
    detect_placements,
    placement_in,
    surface_frame,
)
from core.hashing import derive
from core.mesh import Adjacency, adjacency, bbox_diagonal, columns
from core.options import METHODS, Options
from core.parallel import SPLIT_FROM, beside, by_rows
from core.reports import CapacityReport, DetectResult, EmbeddedFile, EmbedReport, Progress
from core.resample import undo_subdivision
from core.slots import assign_slots, bucketed_slots, own_copy, ranked_by_default
from core.sync import (
    MAX_DEGREE,
    MIN_BOUNDARY_DEGREE,
    MIN_DEGREE,
    CellFrame,
    Labels,
    cell_frame,
    has_step,
    stepped_labels,
    turned_labels,
    vertex_labels,
)
from core.tolerances import TOL, Tolerances
from core.unsmooth import MIN_SCORE, choose_iterations, unsmooth

#: carriers per codeword bit that capacity asks for (skipped carriers and slot collisions)
CAPACITY_MARGIN = 1.5
#: displacement caps tried in turn (multiples of the defaults in core.tolerances.Tolerances; the
#: ceiling ``max_displacement`` is never widened)
CAP_FACTORS = (1.0, 2.0, 4.0)
#: RMS budgets (of the bounding-box diagonal) tried in turn at the default strength: the target,
#: and no budget only for a mesh on which the target does not even read back untouched (coarse
#: models); core/README.md, distortion budget
RMS_BUDGETS = (TOL.rms_budget,)
#: the first round of an embedding aims at this share of the budget (the rounds after it, which
#: read again after rounding and choose the geometric cells again, add a few percent: 2-7 % on
#: the shared meshes), and aims lower, at most BUDGET_RETRIES times, while the result exceeds it;
#: with a geometric layer, whose moves the first round prices at the original frame's carriers and
#: the rounds make once the frame has followed (core.embedding._Mesh.round), at BUDGET_AIM_GEO (at
#: 0.95 five of the engine table's meshes ended at RMS 1.84-1.88e-4, at 1.0 1.89-1.99e-4; core/README.md)
BUDGET_AIM, BUDGET_AIM_GEO, BUDGET_RETRIES = 0.95, 1.0, 3


def _aim(geometric: bool) -> float:
    """The share of the RMS budget the first round aims at: :data:`BUDGET_AIM_GEO` when a
    geometric layer is embedded, else :data:`BUDGET_AIM`."""
    return BUDGET_AIM_GEO if geometric else BUDGET_AIM


def _placed(placements: Sequence[Placement | None]) -> bool:
    """Whether any part has a geometric placement (the file embeds a geometric layer)."""
    return any(p is not None for p in placements)


#: a face has no area when |cross| <= this x (bounding-box diagonal)^2 (collinear corners)
ZERO_AREA = 1e-12


def _no_progress(fraction: float) -> None:
    pass


class Milestones:
    """Where each stage of a call ends, as the fraction of the call done, for the progress a
    caller sees.  The engine's stages are opaque calls, so progress moves between them; the
    fractions are their shares of the run time measured on the shared meshes (binary formats read
    in ~5-10 %, text ones in 25-60 %: reading counts for a quarter)."""

    READ = 0.25
    #: embed: connectivity labels and neighbourhoods of every part
    PREPARED = 0.4
    #: embed: carriers moved (first attempt), then read back after the file's rounding
    MOVED = 0.7
    VERIFIED = 0.85
    #: embed: distortion measured; the file is written last
    MEASURED = 0.92
    #: detect: every part analysed (carriers and statistics); decoding is the rest
    ANALYSED = 0.6


def _rising(report: Progress) -> Progress:
    """``report`` never called with less than before (an embedding's fallbacks each map their own
    stages onto what is left)."""
    done = [0.0]

    def rise(fraction: float) -> None:
        if fraction >= done[0]:
            done[0] = fraction
            report(fraction)

    return rise


def _scaled(report: Progress, start: float, end: float) -> Progress:
    """``report`` for a sub-stage whose own 0..1 maps to ``start``..``end``."""
    return lambda fraction: report(start + (end - start) * fraction)


def _unusable(vertices: np.ndarray, faces: np.ndarray) -> str | None:
    """Why a welded mesh part cannot carry a watermark, or ``None`` when it can."""
    if len(vertices) < 4:
        return "fewer than 4 distinct vertices"
    if len(faces) == 0:
        return "no faces (a point cloud, or every face repeats a vertex)"
    tiny = ZERO_AREA * bbox_diagonal(vertices) ** 2
    # one face with an area is enough: look at the first ones before paying for all of them
    for chunk in (faces[:1024], faces):
        a, b, c = (vertices[chunk[:, k]] for k in range(3))
        u, w = b - a, c - a
        cross = np.stack([u[:, 1] * w[:, 2] - u[:, 2] * w[:, 1], u[:, 2] * w[:, 0] - u[:, 0] * w[:, 2],
                          u[:, 0] * w[:, 1] - u[:, 1] * w[:, 0]], axis=1)
        if np.any(np.linalg.norm(cross, axis=1) > tiny):
            return None
    return f"all {len(faces)} faces have zero area"


def _no_carrier_hint(carriers: int) -> str:
    if carriers:
        return ""
    return (f"; no vertex can carry a bit: a carrier needs {MIN_DEGREE} to {MAX_DEGREE} neighbours "
            f"({MIN_BOUNDARY_DEGREE} on a boundary) in a manifold mesh, and a triangle soup (no shared "
            "vertices) has none")


def _more_carriers_hint(bits: np.ndarray | None) -> str:
    """What a caller refused for too few carriers can change (the strength does not add any)."""
    shorter = "" if bits is None else "a shorter payload (capacity reports the largest that fits) or "
    return f"; use {shorter}a mesh with more vertices (a finer or subdivided version)"


def _usable_parts(doc: MeshDocument) -> list[int]:
    reasons = {i: _unusable(p.vertices, p.faces) for i, p in enumerate(doc.parts)}
    idx = [i for i, why in reasons.items() if why is None]
    if not idx:
        why = "; ".join(sorted({w for w in reasons.values() if w})) or "no mesh"
        raise DegenerateMeshError(f"no triangle mesh in the file can carry a watermark: {why}")
    return idx


def _analyses(doc: MeshDocument, parts: list[int], key: str | bytes, methods: Sequence[str],
              progress: Progress = _no_progress) -> dict[str, list[Analysis]]:
    """Every part analysed under ``key``; ``progress`` by vertices analysed."""
    return _layers(doc, parts, key, methods, progress)[0]


class _Layers(NamedTuple):
    """Every part's connectivity analyses per method, adjacency and labels (:func:`_layers`)."""

    local: dict[str, list[Analysis]]
    adjs: list[Adjacency]
    labels: list[Labels]


def _layers(doc: MeshDocument, parts: list[int], key: str | bytes, methods: Sequence[str],
            progress: Progress = _no_progress) -> _Layers:
    """Every part's connectivity carriers analysed under ``key``, its adjacency and its labels;
    ``progress`` by vertices analysed."""
    out: dict[str, list[Analysis]] = {m: [] for m in methods}
    adjs, labels = [], []
    total, done = sum(len(doc.parts[i].vertices) for i in parts) or 1, 0
    for i in parts:
        v, f = doc.parts[i].vertices, doc.parts[i].faces
        adj = adjacency(f, len(v))
        lab = vertex_labels(v, adj)
        for m, a in analyse_methods(v, f, key, methods, adj=adj, labels=lab).items():
            out[m].append(a)
        adjs.append(adj)
        labels.append(lab)
        done += len(doc.parts[i].vertices)
        progress(done / total)
    return _Layers(out, adjs, labels)


def _relabelled(doc: MeshDocument, parts: list[int], key: str | bytes, layers: _Layers, step: int
                ) -> dict[str, list[Analysis]]:
    """The connectivity view with every part whose labels have
    :func:`~core.sync.stepped_labels` ``step`` steps away analysed at those (the others as they
    are), or empty when no part has them (a cropped piece whose colour refinement stopped a step
    before or after the whole mesh's)."""
    other = [stepped_labels(doc.parts[i].vertices, adj, lab, step)
             for i, adj, lab in zip(parts, layers.adjs, layers.labels, strict=True)]
    if all(w is None for w in other):
        return {}
    out: dict[str, list[Analysis]] = {m: list(a) for m, a in layers.local.items()}
    for k, (i, adj, w) in enumerate(zip(parts, layers.adjs, other, strict=True)):
        if w is None:
            continue
        p = doc.parts[i]
        for m, a in analyse_methods(p.vertices, p.faces, key, list(out), adj=adj, labels=w).items():
            out[m][k] = a
    return out


#: a regular part is searched for its turned frame (:func:`_turned`) while its vertices times the
#: frames tried stay within this (the capsule: 5,204 vertices x 200 frames)
TURN_WORK = 1 << 22


def _turn_frame(vertices: np.ndarray, labels: Labels) -> CellFrame | None:
    """The fallback's frame of a part that :func:`_turned` searches: a regular part whose frame has
    other frames (:attr:`~core.sync.CellFrame.others`), within :data:`TURN_WORK`; else None
    (geometry and connectivity only, so that the false-positive figure counts the view exactly
    when it is made)."""
    if not labels.regular or len(vertices) > TURN_WORK:
        return None
    frame = cell_frame(vertices)
    return frame if frame.others and len(vertices) * len(frame.others) <= TURN_WORK else None


def _turned(doc: MeshDocument, parts: list[int], key: str | bytes, layers: _Layers,
            frames: list[CellFrame | None], lengths: list[int]) -> dict[str, list[Analysis]]:
    """The connectivity view with every part that has a :func:`_turn_frame` (``frames``, per part:
    a regular part whose fallback frame leaves an angle or a sign to the file's axes, a surface of
    revolution, a symmetric part) analysed in the other frame whose carriers' votes agree best
    within their slots (:func:`~core.detection.agreement`, slots ranked where the embedder ranks
    them); empty when no part has such a frame.  A rotated file: the capsule's frame is its axis
    and one of the 100 turns of its segments, which the file's axes chose at embedding."""
    out: dict[str, list[Analysis]] = {m: list(a) for m, a in layers.local.items()}
    methods = list(out)
    for k, (i, adj, lab, frame) in enumerate(zip(parts, layers.adjs, layers.labels, frames, strict=True)):
        if frame is None:
            continue
        v = doc.parts[i].vertices
        # one method's votes choose the frame: both read the offset along e1, and on the capsule
        # either method's chose the embedder's frame for files marked with either (6 of 6)
        pool = vertex_pool(v, adj, lab, methods[:1])[methods[0]]
        best, score = None, -np.inf
        for turned in turned_labels(v, adj, lab, frame):
            chosen = pooled(pool, turned, key, priorities(v, adj, turned, key), adj)
            s = agreement([chosen], lengths, ranked=True)
            if s > score:
                best, score = turned, s
        # (frame.others is not empty: best is a frame)
        for m, a in analyse_methods(v, doc.parts[i].faces, key, methods, adj=adj, labels=best).items():
            out[m][k] = a
    return out if any(f is not None for f in frames) else {}


def _interior(layers: _Layers) -> dict[str, list[Analysis]]:
    """The connectivity view with the carriers within the labels' refinement rounds of a boundary
    muted (a cut changes every label that far from it, and those carriers then read their bits in
    other slots), or empty when none is.  Cropped pieces of 25 % of the rocker arm marked with
    ellipsoids: the carriers within 3 rings of the cut kept none of their labels and read 0.48-0.53
    right, those 4 rings away kept 73 % (core/README.md, section 2, "Carriers next to a cut")."""
    near = [adj.within(adj.boundary, lab.rounds) for adj, lab in zip(layers.adjs, layers.labels, strict=True)]
    out: dict[str, list[Analysis]] = {}
    for m, analyses in layers.local.items():
        out[m] = []
        for a, n in zip(analyses, near, strict=True):
            mute = n[a.carriers]
            if mute.any():
                a = replace(a, muted=mute if a.muted is None else a.muted | mute)
            out[m].append(a)
    return out if any(n.any() for n in near) else {}


def _interior_view(layers: _Layers) -> list[View]:
    """The interior view (:func:`_interior`, made when the others do not read) where a part has a
    boundary: a closed mesh has no cut, and its false-positive figure no such view."""
    return [(INTERIOR, partial(_interior, layers))] if any(adj.boundary.any() for adj in layers.adjs) else []


class _GeometricViews:
    """The geometric carriers a detection reads, made on first use: each part's placements
    (:func:`core.geosync.detect_placements`, none without a frame), then the analyses at the first
    one (the embedder's, on an untouched file) or at the one whose votes agree best within slots
    (:func:`core.detection.agreement`) among all of them.  Parts with fewer than
    :data:`GEOMETRIC_PART_MIN` geometric carriers are left out."""

    def __init__(self, doc: MeshDocument, parts: list[int], adjs: list[Adjacency], key: str | bytes,
                 methods: Sequence[str], lengths: list[int]) -> None:
        self.doc, self.parts, self.adjs, self.key = doc, parts, adjs, key
        self.methods, self.lengths = methods, lengths
        self._places: list[list[Placement]] | None = None
        self._first: dict[str, list[Analysis | None]] | None = None
        # each part's ring moments, kept over the rung search and every placement tried
        self._rings = [Rings(doc.parts[i].vertices, adj) for i, adj in zip(parts, adjs, strict=True)]

    def places(self) -> list[list[Placement]]:
        if self._places is None:
            self._places = [detect_placements(self.doc.parts[i].vertices, self.doc.parts[i].faces, adj,
                                              self.key, rings)
                            for i, adj, rings in zip(self.parts, self.adjs, self._rings, strict=True)]
        return self._places

    def by_part(self, best: bool) -> dict[str, list[Analysis | None]]:
        """Per method, each part's geometric analysis (None for a part without one)."""
        if not best and self._first is not None:
            return self._first
        out: dict[str, list[Analysis | None]] = {m: [] for m in self.methods}
        for i, adj, places, rings in zip(self.parts, self.adjs, self.places(), self._rings, strict=True):
            v = self.doc.parts[i].vertices
            chosen, score = None, -np.inf
            for p in places if best else places[:1]:
                got = analyse_geometric(v, adj, self.key, self.methods, p, rings=rings)
                if len(next(iter(got.values())).carriers) < GEOMETRIC_PART_MIN:
                    continue
                s = max(agreement([a], self.lengths) for a in got.values()) if best else 0.0
                if s > score:
                    chosen, score = got, s
            for m in self.methods:
                out[m].append(None if chosen is None else chosen[m])
        if not best:
            self._first = out
        return out

    def view(self, best: bool) -> dict[str, list[Analysis]]:
        """The geometric analyses of the parts that have them."""
        return {m: [a for a in got if a is not None] for m, got in self.by_part(best).items()}

    def both(self, local: dict[str, list[Analysis]]) -> dict[str, list[Analysis]]:
        """Both layers together at the first placement; a vertex that is a carrier of both counts
        once, as a geometric carrier (its bit is the geometric layer's: the embedder gives it that
        one).  Empty without geometric carriers."""
        first = self.by_part(best=False)
        if not any(a is not None for got in first.values() for a in got):
            return {}
        out: dict[str, list[Analysis]] = {}
        for m in self.methods:
            out[m] = []
            for a, g in zip(local[m], first[m], strict=True):
                out[m].append(a if g is None else replace(a, muted=np.isin(a.carriers, g.carriers)))
            out[m] += [g for g in first[m] if g is not None]
        return out


def _codeword_lengths(expected: np.ndarray | None) -> list[int]:
    """Codeword lengths a detection tries (the expected payload's, else every length's and the key code's)."""
    if expected is not None:
        return [codeword_length(len(expected))]
    return sorted({codeword_length(n) for n in range(1, MAX_PAYLOAD_BITS + 1)} | {codeword_length(None)})


def _reads_back(check: DetectResult, bits: np.ndarray | None) -> bool:
    """The payload was recovered exactly (CRC, or the key-derived code with no bit error)."""
    if bits is not None:
        return check.detected and check.crc_ok
    return check.detected and check.key_derived and check.bit_errors == 0


def _file_diagonal(doc: MeshDocument) -> float:
    """The bounding-box diagonal of all the file's parts (1 for a file of one point): what the
    displacement ceiling, the RMS budget and the reported distortion refer to."""
    return bbox_diagonal(np.concatenate([p.vertices for p in doc.parts])) or 1.0


def _distortion(doc: MeshDocument, new: list[np.ndarray], adjs: dict[int, Adjacency],
                hausdorff: bool = True) -> tuple[int, float, float, float]:
    """Vertices moved, RMS and max displacement, and symmetric vertex Hausdorff distance, all
    relative to the bounding-box diagonal of the input (``adjs``: adjacency of each changed part).

    Hausdorff: for each moved vertex, the distance from its new position to the nearest old vertex
    among itself and its 1-ring, and from its old position to the nearest new one (unmoved
    vertices are in both sets).  Moves are capped well below an edge, so the nearest vertex is in
    that set.
    """
    diag = _file_diagonal(doc)
    d2 = []
    haus = 0.0
    for i, (p, v) in enumerate(zip(doc.parts, new, strict=True)):
        d = _row_norms(v - p.vertices)
        d2.append(d)
        moved = np.flatnonzero(d > 0)
        if not hausdorff or moved.size == 0 or i not in adjs:
            haus = max(haus, float(d.max()) if d.size else 0.0)
            continue
        adj = adjs[i]
        # an isolated moved vertex is nearest to itself
        haus = max(haus, float(d[moved[adj.degree[moved] == 0]].max(initial=0.0)))
        moved = moved[adj.degree[moved] > 0]

        def nearest(part: np.ndarray, adj: Adjacency = adj, old: tuple[np.ndarray, ...] = columns(p.vertices),
                    now: tuple[np.ndarray, ...] = columns(v)) -> tuple[np.ndarray, np.ndarray]:
            # nearest among the 1-ring, per moved vertex (runs of its degree), coordinate by
            # coordinate (1-D gathers: 0.75 of the time of gathering rows at 1M vertices)
            if not part.size:
                return np.zeros(0), np.zeros(0)
            first, pos = adj.ring_entries(part)
            deg = adj.degree[part]
            nb = adj.indices[pos]
            to_old, to_new = np.zeros(len(nb)), np.zeros(len(nb))
            for o, n in zip(old, now, strict=True):
                e = np.repeat(np.take(n, part), deg) - np.take(o, nb)
                to_old += e * e
                e = np.repeat(np.take(o, part), deg) - np.take(n, nb)
                to_new += e * e
            return np.minimum.reduceat(np.sqrt(to_old), first), np.minimum.reduceat(np.sqrt(to_new), first)

        to_old, to_new = by_rows(nearest, moved)
        dm = d[moved]
        haus = max(haus, float(np.minimum(to_old, dm).max(initial=0.0)),
                   float(np.minimum(to_new, dm).max(initial=0.0)))
    d_all = np.concatenate(d2) if d2 else np.zeros(0)
    rms = float(np.sqrt((d_all**2).mean())) / diag if d_all.size else 0.0
    mx = float(d_all.max()) / diag if d_all.size else 0.0
    return int((d_all > 0).sum()), rms, mx, haus / diag


def _row_norms(x: np.ndarray) -> np.ndarray:
    """Euclidean norm of each row of an (n, 3) array (column by column: much faster than axis=1)."""
    return np.sqrt(x[:, 0] ** 2 + x[:, 1] ** 2 + x[:, 2] ** 2)


class _ArrayDoc(MeshDocument):
    """A :class:`MeshDocument` over plain arrays (no file behind it): float64, no rounding."""

    format = "arrays"

    def __init__(self, meshes: list[tuple[np.ndarray, np.ndarray]]) -> None:
        parts = []
        for k, (v, f) in enumerate(meshes):
            v = np.asarray(v, np.float64).reshape(-1, 3)
            f = np.asarray(f, np.int64).reshape(-1, 3)
            if len(f) and (f.min() < 0 or f.max() >= len(v)):
                raise PayloadError("face index out of range")
            if not np.all(np.isfinite(v)):
                raise PayloadError("non-finite vertex coordinate")
            wv, wf, slots = weld(v, f)
            parts.append(MeshPart(f"mesh{k}", wv, wf, slots))
        super().__init__(b"", parts)


def _part_quantizer(doc: MeshDocument, parts: list[int], decimals: int | None) -> Quantize:
    """The engine's quantize hook for the usable ``parts`` of ``doc`` (mesh k is part parts[k])."""
    return lambda k, index, v: doc.quantize_part(parts[k], index, v, decimals)


def _with_parts(doc: MeshDocument, parts: list[int], vs: list[np.ndarray]) -> list[np.ndarray]:
    """Every part's vertices: the embedder's ``vs`` for the usable ``parts``, copies elsewhere."""
    new = [p.vertices.copy() for p in doc.parts]
    for k, i in enumerate(parts):
        new[i] = vs[k]
    return new


def _part_info(doc: MeshDocument, parts: list[int], stats: list[EmbedStats]) -> list[dict[str, object]]:
    """The report's per-part rows (name, vertices, carriers, skipped, moved)."""
    return [{"name": doc.parts[i].name, "vertices": len(doc.parts[i].vertices), "carriers": stats[k].carriers,
             "skipped": stats[k].skipped, "moved": stats[k].moved} for k, i in enumerate(parts)]


def _written(doc: MeshDocument, new: list[np.ndarray], rep: EmbedReport,
             decimals: int | None) -> EmbeddedFile:
    """The file with ``new`` positions, in its own format and encoding, and the report completed
    with what the file itself says (elements skipped, encodings re-encoded)."""
    out = doc.write(new, decimals=decimals) if decimals is not None else doc.write(new)
    rep = replace(rep, skipped_elements=doc.skipped_elements, reencoded=list(doc.reencoded))
    spec = FORMATS[doc.format]
    return EmbeddedFile(out, rep, doc.format, spec.media_type, spec.extension)


def embed_mesh(vertices: np.ndarray, faces: np.ndarray, key: str | bytes, *, payload: str | None = None,
               method: str | None = None, strength: float | None = None) -> tuple[np.ndarray, EmbedReport]:
    """Array-level embedding.

    Parameters
    ----------
    vertices : (n, 3) float ndarray
        Positions; not modified.
    faces : (m, 3) int ndarray
        Triangles into ``vertices``.
    key, payload, method, strength
        As in :class:`~core.options.Options`.

    Returns
    -------
    new_vertices : (n, 3) float64 ndarray
        The positions with the carriers moved (positions that were welded together move together).
    report : EmbedReport
    """
    options = Options(key=key, payload=payload, method=method, strength=strength)
    doc = _ArrayDoc([(vertices, faces)])
    new, rep, _ = _embed_doc(doc, options, _no_progress)
    part = doc.parts[0]
    return new[0][part.slot_to_vertex], rep


def detect_mesh(meshes: list[tuple[np.ndarray, np.ndarray]], key: str | bytes, *, payload: str | None = None,
                method: str | None = None) -> DetectResult:
    """Array-level blind detection over one or several ``(vertices (n, 3), faces (m, 3))`` meshes."""
    options = Options(key=key, payload=payload, method=method)
    return _detect_doc(_ArrayDoc(list(meshes)), options)


def embed(data: bytes, options: Options, *, filename: str | None = None, limits: Limits = DEFAULT_LIMITS,
          progress: Progress | None = None) -> EmbeddedFile:
    """Watermark a mesh file: the same format and encoding, only moved coordinates changed.

    Parameters
    ----------
    data : bytes
        The whole file.
    options : Options
        ``key`` (required), ``payload``, ``method``, ``strength``.
    filename : str, optional
        The client's file name, only to cross-check the extension.
    limits : Limits
        Checked before anything proportional to the file is allocated.
    progress : callable, optional
        Called with the fraction done.

    Raises
    ------
    MeshMarkError
        A subclass for every input the engine refuses (see :mod:`core.errors`).
    """
    options.secret  # noqa: B018 -- no key is a PayloadError before the file is parsed
    report = _no_progress if progress is None else _rising(progress)
    report(0.0)
    doc = read_mesh(data, filename, limits)
    report(Milestones.READ)
    new, rep, dec = _embed_doc(doc, options, report)
    written = _written(doc, new, rep, dec)
    report(1.0)
    return written


def embed_file(data: bytes, key: str | bytes, *, filename: str | None = None, payload: str | None = None,
               method: str | None = None, strength: float | None = None, limits: Limits | None = None,
               progress: Progress | None = None) -> EmbeddedFile:
    """:func:`embed` with the options as keywords."""
    options = Options(key=key, payload=payload, method=method, strength=strength)
    return embed(data, options, filename=filename, limits=limits or DEFAULT_LIMITS, progress=progress)


def _embed_doc(doc: MeshDocument, options: Options, report: Progress, probe: bool = True,
               compact_rounds: int | None = None, reslotted: list[bool] | None = None, reslot: bool = True,
               relax: bool = True, clip: float = TOL.clip_margin, compact_probes: CompactProbes | None = None
               ) -> tuple[list[np.ndarray], EmbedReport, int | None]:
    """Embed into every usable part; ``probe``: a refusal says what would fit instead;
    ``reslot``: when every try fails, try slots other than the embedder's own (ranked again for the
    selection its moves made, then the other assignment); ``reslotted``: True is appended when the
    embedding read back only that way (or with carriers held still, :data:`_STILL`); ``relax``:
    before a refusal, the widest tries once more with carriers cut at the ceiling kept from
    :data:`RELAXED_CLIP` x the strength (``clip``: this pass's); ``compact_probes``: the compact frame's
    probes of earlier embeddings of the same file, key and strength (:func:`_embed_compact`).

    The standard frame first; a payload of at most :data:`~core.coding.COMPACT_MAX_PAYLOAD` bits
    that it cannot carry on a mesh of few carriers gets the compact frame (:func:`_embed_compact`)."""
    key = options.secret
    method, s, bits = options.embed_method, options.margin, options.payload_bits
    parts = _usable_parts(doc)
    codeword = encode(key, bits)
    L = len(codeword)
    decimals = doc.decimals
    # the default strength first keeps the RMS budget; coarse meshes may need more than the
    # default displacement cap: relax it (reported as cap_factor, never past the ceiling) before
    # refusing; text formats may need more printed decimals
    decs = [decimals] if decimals is None else [decimals, decimals + 2, decimals + 4, 17]
    relaxed = clip < TOL.clip_margin  # the last pass: only the widest tries
    budgets = [*RMS_BUDGETS, None] if options.strength is None and not relaxed else [None]
    meshes = [(doc.parts[i].vertices, doc.parts[i].faces) for i in parts]
    diagonal = _file_diagonal(doc)
    prepared, placements, selections = _prepared_placements(meshes, key, L, method)
    # within the RMS budget the geometric layer's moves leave less to the connectivity layer: when
    # the file then does not read, the budget is tried again without the geometric layer before
    # it is given up (the gear with ellipsoids: 7e-4 of the diagonal otherwise)
    layered = (True, False) if _placed(placements) else (True,)
    tries: list[tuple[float | None, float, int | None, bool, SlotRule | None]] = [
        (b, f, d, g, None) for b in budgets for g in (layered if b is not None else (True,))
        for f in ((1.0,) if b is not None else CAP_FACTORS[-1:] if relaxed else CAP_FACTORS) for d in decs]
    # on a mesh of >= TIE_BREAK_FROM vertices the moves can make the selection swap a few carriers
    # with every round, and with ranked slots a label that comes or goes moves every carrier ranked
    # after it to another bit (core/README.md, capacity): the embedding is made again with the slots
    # ranked as in the selection the last one ended with (the detector's own reading), then with the
    # other slot assignment, which the detector reads too; before those, with the carriers whose
    # moves made the selection swap vertices left where they are (_STILL), so that it does not
    if reslot and len(meshes) == 1 and len(meshes[0][0]) >= TIE_BREAK_FROM and not prepared[0][1].regular:
        tries += [(None, CAP_FACTORS[-1], decs[0], True, _STILL)] * STILL_RETRIES
        tries += [(None, CAP_FACTORS[-1], decs[0], True, _AS_FINAL)] * RANK_RETRIES
    if reslot:
        tries.append((None, CAP_FACTORS[-1], decs[0], True, _other_slots))
    report(Milestones.PREPARED)
    # attempt k (a retry is for coarse meshes and rounding) moves progress over the k-th half of
    # what is left between MOVED and VERIFIED: the first attempt gets half, and it never goes back
    span = Milestones.VERIFIED - Milestones.MOVED

    def attempt_start(k: int) -> float:
        return Milestones.MOVED + span * (1 - 0.5**k)

    refusal: tuple[str, int] | None = None
    too_few = False  # too few carriers for the codeword: no embedding was tried, nothing else is
    adjs = {i: prepared[k][0] for k, i in enumerate(parts)}
    # the distortion report of a large file's embedding is made beside its verification (wasted
    # when the verification fails: the next try then has the other core to itself anyway)
    measured: Future[tuple[int, float, float, float]] | None = None
    tables: list[np.ndarray] = []  # the rankings _AS_FINAL tried
    final: list[Analysis] = []
    still: list[np.ndarray] | None = None  # the vertices _STILL leaves where they are
    for attempt, (budget, factor, dec, with_geo, how) in enumerate(tries):
        rule = how
        if how is _STILL:
            if not _moved(final, selections, L):
                continue  # the selection stayed, or slots are hashed: holding changes nothing
            still = _still(final, selections, [adj for adj, _ in prepared], still)
            rule = None
        elif how is _AS_FINAL:
            table = np.unique(np.concatenate([a.slot_hash for a in final]))
            if any(np.array_equal(table, t) for t in tables) or \
                    not ranked_by_default(sum(len(a.carriers) for a in final), L):
                continue  # a ranking tried already, or slots hashed
            tables.append(table)
            rule = _ranked_as(table)
        tol = _capped(factor, clip)
        aim = None if budget is None else _aim(with_geo and _placed(placements)) * budget
        for _ in range(BUDGET_RETRIES + 1):
            vs, stats, final = embed_parts(meshes, key, codeword, method, s, tol=tol, prepared=prepared,
                                           quantize=_part_quantizer(doc, parts, dec), rms_budget=aim,
                                           diagonal=diagonal, slot_rule=rule, selections=selections,
                                           placements=placements if with_geo else [None] * len(meshes),
                                           still=still if how is _STILL else None)
            new = _with_parts(doc, parts, vs)
            if budget is None or aim is None:
                break
            rms = _distortion(doc, new, {}, hausdorff=False)[1]
            if rms <= budget:
                break
            aim *= 0.98 * budget / rms
        carriers = sum(st.carriers for st in stats)
        skipped = sum(st.skipped for st in stats)
        report(attempt_start(attempt))
        if carriers < L:
            too_few = True
            refusal = (f"too little capacity: {carriers} carriers for a {L}-bit codeword "
                       f"({'32-bit key-derived code' if bits is None else f'{len(bits)}-bit payload'} with "
                       f"{'' if bits is None else 'CRC-32 and '}a rate-1/2 convolutional code) "
                       f"at strength {s}"
                       + (_no_carrier_hint(carriers) or _more_carriers_hint(bits)), carriers)
            break
        verify = _scaled(report, attempt_start(attempt), attempt_start(attempt + 1))
        if sum(len(v) for v in vs) >= SPLIT_FROM:
            measured = beside(partial(_distortion, doc, new, adjs))
        if _verified(final, key, method, bits, L, verify):
            if how is not None and reslotted is not None:
                reslotted.append(True)
            break
        if attempt == len(tries) - 1:
            refusal = ("the watermark could not be made readable on this mesh within the displacement "
                       f"ceiling of {TOL.max_displacement:g} of the bounding-box diagonal ({carriers} "
                       f"carriers, {skipped} of them over it, at strength {s:g} with {method})", carriers)
    report(Milestones.VERIFIED)
    if refusal is not None:
        compact = None
        fallback = bits is not None and len(bits) <= COMPACT_MAX_PAYLOAD and refusal[1] < COMPACT_BELOW \
            and not relaxed
        if fallback:
            assert bits is not None
            compact = _embed_compact(meshes, prepared, key, method, s, bits, diagonal,
                                     [(f, d) for f in CAP_FACTORS for d in decs[:1]]
                                     + [(CAP_FACTORS[-1], d) for d in decs[1:]],
                                     lambda dec: _part_quantizer(doc, parts, dec),
                                     COMPACT_ROUNDS if compact_rounds is None else compact_rounds,
                                     compact_probes)
        if compact is None:
            tried = (f"; the compact {COMPACT_BITS}-bit frame (CRC-32, no error correction) did not read "
                     "back either"
                     if fallback else "")
            after = _scaled(report, Milestones.VERIFIED, Milestones.MEASURED)
            if options.method is None:
                # the caller left the method to MeshMark: the other one, before any refusal (the
                # Sink, a random 32-bit payload: planes for 50 of 50 keys, ellipsoids 4; core/README.md)
                for other in _other_methods(method):
                    try:
                        return _embed_doc(doc, replace(options, method=other), after, probe=False,
                                          compact_rounds=compact_rounds, reslotted=reslotted, reslot=reslot,
                                          relax=False, clip=clip, compact_probes=compact_probes)
                    except CapacityError:
                        tried += f"; method={other} did not read back either"
            if relax and not too_few:
                # a payload at the edge of what fits: the carriers the ceiling cuts short kept with a
                # smaller margin (every method again, without a method asked); core/README.md
                try:
                    return _embed_doc(doc, options, after, probe=False, compact_rounds=compact_rounds,
                                      reslotted=reslotted, reslot=reslot, relax=False, clip=RELAXED_CLIP)
                except CapacityError:
                    tried += f"; nor with carriers at the ceiling kept from {RELAXED_CLIP:g} x the strength"
            hint = _what_fits(doc, options) if probe and (fallback or not too_few) else ""
            raise CapacityError(refusal[0] + tried + hint,
                                carriers=refusal[1], needed=L)
        vs, stats, factor, dec = compact
        new, L = _with_parts(doc, parts, vs), COMPACT_BITS
        carriers = sum(st.carriers for st in stats)
        skipped = sum(st.skipped for st in stats)
        measured = None
    moved, rms, mx, haus = _distortion(doc, new, adjs) if measured is None else measured.result()
    geo = [st.geometric for st in stats if st.geometric is not None and len(st.geometric.carriers)]
    layers = [CONNECTIVITY] + ([GEOMETRY] if geo and _reads_back(
        detect_views([(GEOMETRY, {method: geo})], key, bits, confidence=False), bits) else [])
    report(Milestones.MEASURED)
    rep = EmbedReport(method=method, strength=s, payload_bits=KEY_CODE_BITS if bits is None else len(bits),
                      key_derived=bits is None, codeword_bits=L, carriers=carriers,
                      copies=round(carriers / L, 3), skipped=skipped, vertices_moved=moved,
                      rms_displacement=rms, max_displacement=mx, hausdorff=haus, decimals=dec,
                      cap_factor=factor, parts=_part_info(doc, parts, stats), layers=layers,
                      geometric_carriers=sum(len(g.carriers) for g in geo))
    return new, rep, dec


#: re-embeddings with the slots ranked as in the selection the last embedding ended with
RANK_RETRIES = 3
#: an embedding's last pass before a refusal keeps a carrier its cap cuts short when it then reads
#: its bit with this x the strength (``Tolerances.clip_margin``, 0.3, before it): never reached where
#: the embedding succeeds without it, and capacity's trials and the refusals' hints do without it,
#: so that it is a reserve for the payloads at the edge.  Spot with planes, the two 188-bit payloads
#: bench capacity-keys saw refused (key-9, key-31): 0.15 and 0.1 rescue the first, 0.05 and 0.01
#: both (a third, key-9 at 187 bits without a method, is refused at any: its selection moves)
RELAXED_CLIP = 0.05
#: marks those tries in _embed_doc (their slot rule is made from the embedding before)
_AS_FINAL: SlotRule = lambda slot_hashes, length: []  # noqa: E731


def _ranked_as(table: np.ndarray) -> SlotRule:
    """Ranked slots of one mesh as the detector deals them for a selection whose distinct hashes are
    ``table`` (sorted): a carrier's slot is its hash's rank in it, whatever the selection of the
    round being embedded (a hash not in it takes the rank of the next one)."""
    return lambda slot_hashes, length: [np.searchsorted(table, h).astype(np.int64) % length
                                        for h in slot_hashes]


#: re-embeddings with the carriers next to the vertices the last one's selection swapped left alone
STILL_RETRIES = 3
#: marks those tries in _embed_doc
_STILL: SlotRule = lambda slot_hashes, length: []  # noqa: E731


def _still(final: list[Analysis], selections: Sequence[Selection], adjs: Sequence[Adjacency],
           still: list[np.ndarray] | None) -> list[np.ndarray]:
    """``still`` (none, the first time) with, per mesh, the vertices that the selection ``final``
    ended with swapped against the one it started from and their neighbours: a carrier among them
    that is not moved does not change the tie-break of its neighbours, whose swap made every carrier
    ranked after them hold the next bit.  Left at its original position it reads whatever it reads
    there, one wrong carrier at worst (Spot with planes, key-9: of 40 random 187-bit payloads, 6
    were not read after the first try's moves had swapped 4-14 vertices; each read back with 3-8
    carriers held still)."""
    out = [np.zeros(len(adj.degree), bool) for adj in adjs] if still is None else still
    for k, (a, sel, adj) in enumerate(zip(final, selections, adjs, strict=True)):
        swapped = np.setxor1d(a.carriers, sel.analysis.carriers)
        out[k][swapped] = True
        out[k][adj.indices[adj.ring_entries(swapped)[1]]] = True
    return out


def _moved(final: list[Analysis], selections: Sequence[Selection], L: int) -> bool:
    """Whether an embedding with ranked slots ended with a selection other than the one it started
    from (``selections``): the tie-break of a mesh of >= TIE_BREAK_FROM vertices followed its moves,
    and every carrier ranked after a vertex that came or went holds another bit (Spot with planes,
    key-9, 160 bits: the selection moved for 10 of 30 random payloads, and 6 of those were not read
    after the first try; under keys 0, 2 and 3 it never moved)."""
    return ranked_by_default(sum(len(a.carriers) for a in final), L) and any(
        not np.array_equal(a.carriers, s.analysis.carriers) for a, s in zip(final, selections, strict=True))


def _other_slots(slot_hashes: list[np.ndarray], length: int) -> list[np.ndarray]:
    """The slot assignment the embedder does not choose by default (hashed where it ranks, ranked
    where it hashes); the detector reads both (:data:`core.detection.VARIANTS`)."""
    return assign_slots(slot_hashes, length, not ranked_by_default(sum(len(h) for h in slot_hashes), length))


def _capped(factor: float, clip: float = TOL.clip_margin) -> Tolerances:
    """The tolerances with the default displacement caps times ``factor`` (the ceiling stays) and
    ``clip_margin`` ``clip``."""
    return replace(TOL, coarse_move=TOL.coarse_move * factor, max_local_move=TOL.max_local_move * factor,
                   max_move=TOL.max_move * factor, clip_margin=clip)


def _verified(final: list[Analysis], key: str | bytes, method: str, bits: np.ndarray | None, L: int,
              verify: Progress = _no_progress) -> bool:
    """The embedder's last analysis reads the payload back, and so does every part with room for a
    copy of its own (a mesh extracted from the file).  (The geometric layer alone is checked for
    the report, :func:`_embed_doc`: without it the file still reads.)"""
    groups = [final] + [[a] for a in final if len(final) > 1 and own_copy(a.slot_hash, L)]
    for k, group in enumerate(groups):
        if not _reads_back(detect_analyses({method: group}, key, bits, confidence=False), bits):
            return False
        verify((k + 1) / len(groups))
    return True


#: a mesh gets geometric carriers when it has at least this many (a small part of a scene gets none),
#: and a file when they are at least GEOMETRIC_PER_SLOT times the codeword length.  With the
#: convolutional code 4 per slot read back: the counter plate's layer (rung 10, 544 carriers, 3.9
#: per slot) came back after quadric 10-50 % and meshoptimizer 5-10 %, the rocker arm's (802, 5.7
#: per slot), off at 8, after meshoptimizer 5-10 %
GEOMETRIC_PART_MIN = 64
GEOMETRIC_PER_SLOT = 4
#: a file of fewer vertices gets no geometric layer (about CARRIER_SHARE of the usable vertices are
#: carriers, and the shortest codeword is a 1-bit payload's; the 8 per slot this was first derived
#: from are kept, so that small files' embedding stays as it was)
GEOMETRIC_MIN_VERTICES = int(np.ceil(8 * codeword_length(1) / CARRIER_SHARE))
#: ...and the detector looks for one in files of at least this many: a marked file simplified by up
#: to 75 % (the rocker arm's 10,044 vertices simplified by 30 % are 7,030, below the embedder's
#: threshold, and its geometric layer read them, and 50 %, when the detector looked)
GEOMETRIC_DETECT_FROM = GEOMETRIC_MIN_VERTICES // 4


def _prepared_placements(meshes: list[tuple[np.ndarray, np.ndarray]], key: str | bytes, L: int, method: str
                         ) -> tuple[list[tuple[Adjacency, Labels]], list[Placement | None], list[Selection]]:
    """:func:`~core.analysis.prepare` of every mesh, where its geometric carriers are
    (:func:`_placements`), and its connectivity layer's selection (priorities and analysis with
    ``method``, as :func:`~core.embedding.embed_parts` takes them: made once for every try).

    The geometric layer needs no labels and its frame no adjacency: for a file of
    :data:`~core.parallel.SPLIT_FROM` vertices or more a second thread
    (:func:`~core.parallel.beside`) makes the surfaces' frames while this one makes the adjacency,
    then chooses the geometric carriers and reads them while this one makes the labels and the
    selection, and the selection's tied pairs while this one reads the connectivity carriers
    (numpy and scipy release the GIL in the large array operations of all of these).  The
    frame's temporaries are a few MB (chunks of faces) and the choice's about 100 MB at 1M
    vertices, which is all the thread's own malloc arena holds."""
    vs = [np.asarray(v, np.float64) for v, _ in meshes]
    faces = [f for _, f in meshes]
    split = sum(len(v) for v in vs) >= SPLIT_FROM  # (well above GEOMETRIC_MIN_VERTICES)

    def selections(prepared: list[tuple[Adjacency, Labels]],
                   geometric: Sequence[Future[Analysis | None] | None]) -> list[Selection]:
        out = []
        for v, f, (adj, lab), geo in zip(vs, faces, prepared, geometric, strict=True):
            prio = priorities(v, adj, lab, key)
            tied = beside(partial(tied_pairs, prio, adj)) if split and not lab.regular else None
            out.append(Selection(prio, analyse_methods(v, f, key, [method], adj, lab, TOL, prio)[method],
                                 tied, geo))
        return out

    if not split:
        prepared = prepare(vs, faces)
        return (prepared, _placements(meshes, [adj for adj, _ in prepared], key, L),
                selections(prepared, [None] * len(meshes)))
    frames = beside(lambda: [surface_frame(v, f) for v, f in meshes])
    adjs = [adjacency(f, len(v)) for v, f in zip(vs, faces, strict=True)]
    # queued behind the frames on the one worker: it runs while the labels are made here (with
    # each vertex's face, which the connectivity layer's boundaries will orient by)
    placed = beside(lambda: ([adj.vertex_face for adj in adjs],
                             _placements(meshes, adjs, key, L, frames.result()))[1])

    def read(k: int) -> Analysis | None:
        p = placed.result()[k]
        return None if p is None else \
            analyse_geometric(vs[k], adjs[k], key, [method], p, TOL, p.chosen)[method]

    # each placement's carriers read at the original positions, queued behind the placements
    geometric = [beside(partial(read, k)) for k in range(len(meshes))]
    prepared = [(adj, vertex_labels(v, adj)) for v, adj in zip(vs, adjs, strict=True)]
    chosen = selections(prepared, geometric)
    return prepared, placed.result(), chosen


def _placements(meshes: list[tuple[np.ndarray, np.ndarray]], adjs: Sequence[Adjacency], key: str | bytes,
                L: int, frames: Sequence[SurfaceFrame | None] | None = None) -> list[Placement | None]:
    """Where each mesh's geometric carriers are (``frames``: each mesh's
    :func:`~core.geosync.surface_frame`, when the caller made them), or None for a mesh without
    them (no frame, too few carriers, or too few in the whole file for a codeword of ``L`` bits)."""
    if sum(len(v) for v, _ in meshes) < GEOMETRIC_MIN_VERTICES:
        return [None] * len(meshes)
    if frames is None:
        frames = [surface_frame(v, f) for v, f in meshes]
    out: list[Placement | None] = []
    total = 0
    for (v, _), adj, frame in zip(meshes, adjs, frames, strict=True):
        p = placement_in(frame, v, adj, key)
        count = 0 if p is None else p.count
        out.append(p if count >= GEOMETRIC_PART_MIN else None)
        total += count if count >= GEOMETRIC_PART_MIN else 0
    return out if total >= GEOMETRIC_PER_SLOT * L else [None] * len(meshes)


#: embeddings of the compact frame per displacement cap, each with the constraints of the last slot maps
COMPACT_ROUNDS = 64
#: the compact frame's two probes (every carrier asked 0, then 1) by (method, strength, cap factor,
#: decimals): the detector's analyses after each (:func:`_embed_compact`)
CompactProbes = dict[tuple[str, float, float, int | None], tuple[list[Analysis], ...]]
#: slot maps (of the last embeddings) whose constraints a compact codeword meets together
COMPACT_MAPS = 3
#: a slot is held to one value unless its free carriers can outvote the others by this much
COMPACT_VOTE_MARGIN = 0.5


def compact_rule(slot_hashes: list[np.ndarray], length: int) -> list[np.ndarray]:
    """The compact frame's slot assignment, as :func:`~core.embedding.embed_parts` takes it."""
    return bucketed_slots(slot_hashes, length, COMPACT_BUCKET)


def _embed_compact(meshes: list[tuple[np.ndarray, np.ndarray]], prepared: list[tuple[Adjacency, Labels]],
                   key: str | bytes, method: str, s: float, bits: np.ndarray, diagonal: float,
                   tries: list[tuple[float, int | None]], quantizer: Callable[[int | None], Quantize],
                   rounds: int = 64, cached: CompactProbes | None = None
                   ) -> tuple[list[np.ndarray], list[EmbedStats], float, int | None] | None:
    """Embed ``bits`` in the compact frame, choosing its free bits (a wet-paper code).

    Two probe embeddings ask every carrier for 0, then for 1: a carrier that does not read one of
    them is *wet* for it, and a slot whose wet carriers outvote the others can only read one value.
    Those values are linear constraints on the free bits (the codeword is ``b0 XOR D r``); a
    solution (the free unknowns drawn from a keyed generator) is embedded and verified.  On a
    regular mesh the carriers, and with the ranked assignment every later slot, shift a little with
    each embedding, so a failed round solves again with the slots of the last analysis, together
    with those of up to :data:`COMPACT_MAPS` earlier ones while the system stays solvable, up to
    ``rounds`` (:data:`COMPACT_ROUNDS`) times.  ``tries``: (cap factor, decimals) in turn; a try whose probes
    read exactly as an earlier one's (the ceiling, not the cap, limits every move) is skipped.
    ``cached``: the probes' analyses by (method, strength, cap factor, decimals), filled and reused
    (they do not depend on the payload: capacity's trials embed many payloads in one file with one
    key).  ``None`` when no try reads back."""
    L = COMPACT_BITS
    b0, d = compact_codeword(key, bits)
    white = compact_whitening(key)
    d64 = d.astype(np.int64)
    rng = np.random.default_rng(derive(key, "meshmark-wet"))
    seen: list[list[np.ndarray]] = []
    for factor, dec in tries:
        tol, quantize = _capped(factor), quantizer(dec)

        def run(cw: np.ndarray, tol: Tolerances = tol, quantize: Quantize = quantize
                ) -> tuple[list[np.ndarray], list[EmbedStats], list[Analysis]]:
            return embed_parts(meshes, key, cw, method, s, tol=tol, prepared=prepared, quantize=quantize,
                               diagonal=diagonal, slot_rule=compact_rule)

        # reach[v][k]: per vertex of mesh k, whether it reads raw bit v when asked (True where unknown)
        reach: list[list[np.ndarray]] = []
        asked = None if cached is None else cached.get((method, s, factor, dec))
        if asked is None:
            asked = tuple(run(np.full(L, value, np.uint8))[2] for value in (0, 1))
            if cached is not None:
                cached[(method, s, factor, dec)] = asked
        for value, an in enumerate(asked):
            ok = [np.ones(len(v), bool) for v, _ in meshes]
            for k, a in enumerate(an):
                ok[k][a.carriers] = (a.z > 0) if value == 0 else (a.z < 0)
            reach.append(ok)
        probes = [r.copy() for ok in reach for r in ok]
        probed = [[r.copy() for r in ok] for ok in reach]
        if any(len(p) == len(probes) and all(np.array_equal(a, b) for a, b in zip(p, probes, strict=True))
               for p in seen):
            continue
        seen.append(probes)
        held: list[np.ndarray] = []  # the constraints of the slot maps seen so far, latest first
        mean: float | None = None
        for _ in range(rounds):
            slots = compact_slots([a.slot_hash for a in an])
            can0 = np.concatenate([reach[0][k][a.carriers] for k, a in enumerate(an)])
            can1 = np.concatenate([reach[1][k][a.carriers] for k, a in enumerate(an)])
            dry = np.bincount(slots, can0 & can1, minlength=L)
            only0 = np.bincount(slots, can0 & ~can1, minlength=L)
            only1 = np.bincount(slots, can1 & ~can0, minlength=L)
            count = np.bincount(slots, minlength=L)
            # the detector centres the votes on their mean, which the wet carriers bias (most of a
            # coarse mesh's may sit inside their ellipsoids): a slot reads 0 when its vote sum
            # beats count x mean.  The mean of the last embedding, else the probes' estimate
            if mean is None:
                mean = float((can0 & ~can1).sum() - (can1 & ~can0).sum()) / max(len(slots), 1)
            best0 = dry + only0 - only1 - count * mean
            best1 = dry + only1 - only0 + count * mean
            ok0, ok1 = best0 > COMPACT_VOTE_MARGIN, best1 > COMPACT_VOTE_MARGIN
            # the whitened bit a slot is held to (-1: free); an empty slot reads 0 once de-whitened
            forced = np.where(ok0 & ~ok1, 0, np.where(ok1 & ~ok0, 1, -1))
            forced = np.where(~ok0 & ~ok1, np.where(best0 >= best1, 0, 1), forced)
            forced = np.where(count == 0, white.astype(np.int64), forced)
            held.insert(0, forced)
            r = None
            # the carriers and slots shift a little with every embedding (regular meshes): meet the
            # last few slot maps at once when they agree, else fewer
            for depth in range(min(len(held), COMPACT_MAPS), 0, -1):
                stack = np.concatenate(held[:depth])
                rows = np.flatnonzero(stack >= 0)
                dd = np.concatenate([d] * depth)
                bb = np.concatenate([white ^ b0] * depth)
                r = gf2.solve(dd[rows], stack[rows].astype(np.uint8) ^ bb[rows],
                              np.asarray(rng.integers(0, 2, size=d.shape[1], dtype=np.uint8)))
                if r is not None:
                    break
            if r is None:
                if not held[1:]:
                    break  # the probes alone already ask too much
                # what the rounds learnt is too much to meet at once: start again from the probes
                reach, held, mean = [[r.copy() for r in ok] for ok in probed], [], None
                continue
            cw = b0 ^ (d64 @ r % 2).astype(np.uint8) ^ white
            vs, stats, an = run(cw)
            if _verified(an, key, method, bits, L):
                return vs, stats, factor, dec
            votes = np.concatenate([np.where(a.z > 0, 1.0, -1.0) for a in an])
            mean = float(votes.mean()) if votes.size else 0.0
            # a carrier that did not read what its slot asked is wet for that value
            for k, (a, slot) in enumerate(zip(an, compact_rule([a.slot_hash for a in an], L), strict=True)):
                want = cw[slot]
                miss = (a.z > 0) != (want == 0)
                for value in (0, 1):
                    reach[value][k][a.carriers[miss & (want == value)]] = False
    return None


def _other_methods(method: str) -> list[str]:
    """The methods other than ``method``, in :data:`~core.options.METHODS` order."""
    return [m for m in METHODS if m != method]


#: lower strengths a refusal tries (fewer carriers over the ceiling, less margin against attacks)
PROBE_STRENGTHS = (0.05, 0.03)


def _what_fits(doc: MeshDocument, options: Options) -> str:
    """What a refused embedding could use instead: the other method or a lower strength with the
    same payload, else the longest shorter payload that embeds (each tried for real)."""
    method, s = options.embed_method, options.margin
    others = _other_methods(method)
    # without a method asked, the others at this strength were tried before the refusal
    tries = [(m, None if options.strength is None else s) for m in others if options.method is not None]
    tries += [(m, t) for t in PROBE_STRENGTHS if t < s for m in [method, *others]]
    for m, t in tries:
        if _embeds(doc, replace(options, method=m, strength=t)):
            return f"; the same payload reads back with method={m} at strength {s if t is None else t:g}"
    bits = options.payload or ""
    for n in [n for n in (24, 16, 8) if n < len(bits)]:
        for m in [method, *others]:
            if _embeds(doc, replace(options, payload=bits[:n], method=m)):
                return f"; a {n}-bit payload reads back with method={m} (at strength {s:g})"
    return "; no shorter payload, other method or lower strength reads back either: use a finer mesh"


def _embeds(doc: MeshDocument, options: Options, compact_rounds: int | None = None,
            reslotted: list[bool] | None = None, reslot: bool = True,
            compact_probes: CompactProbes | None = None) -> bool:
    """Whether ``options`` embed without the relaxed last pass (what capacity's trials and a
    refusal's hints promise, an embedding has that pass in reserve)."""
    try:
        _embed_doc(doc, options, _no_progress, probe=False, compact_rounds=compact_rounds,
                   reslotted=reslotted, reslot=reslot, relax=False, compact_probes=compact_probes)
    except CapacityError:
        return False
    return True


def detect(data: bytes, options: Options, *, filename: str | None = None, limits: Limits = DEFAULT_LIMITS,
           progress: Progress | None = None) -> DetectResult:
    """Blind detection from the file and the key alone.

    ``options``: ``key`` (required), ``payload`` (expected: adds bit errors and a p-value),
    ``method`` (``None`` tries every method).  The other parameters are those of :func:`embed`.
    "No watermark" is a result (``detected=False``), not an exception.
    """
    options.secret  # noqa: B018 -- no key is a PayloadError before the file is parsed
    report = progress or _no_progress
    report(0.0)
    doc = read_mesh(data, filename, limits)
    report(Milestones.READ)
    res = _detect_doc(doc, options, _scaled(report, Milestones.READ, Milestones.ANALYSED))
    report(1.0)
    return res


def detect_file(data: bytes, key: str | bytes, *, filename: str | None = None, payload: str | None = None,
                method: str | None = None, limits: Limits | None = None,
                progress: Progress | None = None) -> DetectResult:
    """:func:`detect` with the options as keywords."""
    options = Options(key=key, payload=payload, method=method)
    return detect(data, options, filename=filename, limits=limits or DEFAULT_LIMITS, progress=progress)


def _detect_doc(doc: MeshDocument, options: Options, analysed: Progress = _no_progress) -> DetectResult:
    """``analysed`` follows the analysis of the parts (0 to 1); decoding comes after.

    The views, in turn: both layers' carriers together, the connectivity layer alone (a crop moves
    the surface's frame), the geometric layer alone at its best placement (a re-triangulation loses
    the connectivity labels).  When the file does not read and some of its meshes are one
    subdivision step of a coarser mesh (:func:`core.resample.undo_subdivision`), the coarse meshes
    are read as a second file; a detection there reports ``resampled``.  When that does not read
    either, the file is read once more with uniform Laplacian smoothing undone
    (:func:`_unsmoothed`); a detection there reports ``unsmoothed``.  A detection on such a
    further file reports the false-positive figure of the files read summed (the union bound over
    them; each has about the same candidates)."""
    key = options.secret
    parts = _usable_parts(doc)
    layers = _layers(doc, parts, key, options.detect_methods, analysed)
    found = _read_views(doc, parts, key, options, layers=layers)
    if found.detected:
        return found
    files = 1
    coarse = _coarsened(doc, parts)
    if coarse is not None:
        files += 1
        doc2, scheme = coarse
        second = _read_views(doc2, list(range(len(doc2.parts))), key, options)
        if second.detected:
            return replace(second, resampled=scheme,
                           false_positive_probability=min(1.0, files * second.false_positive_probability))
    smooth = _unsmoothed(doc, parts, layers, options)
    if smooth is None:
        return found
    doc3, iterations = smooth
    third = _read_views(doc3, list(range(len(doc3.parts))), key, options)
    if not third.detected:
        return found
    return replace(third, unsmoothed=iterations,
                   false_positive_probability=min(1.0, (files + 1) * third.false_positive_probability))


def _unsmoothed(doc: MeshDocument, parts: list[int], layers: _Layers, options: Options
                ) -> tuple[MeshDocument, int] | None:
    """The usable parts with ``n`` iterations of uniform Laplacian smoothing undone
    (:mod:`core.unsmooth`), ``n`` chosen by the agreement of the connectivity carriers' votes, and
    ``n``; None when no ``n`` makes them agree by :data:`~core.unsmooth.MIN_SCORE` (an unmarked
    file, a wrong key, an attack the inverse does not undo), or when there are no carriers."""
    local, adjs = layers.local, layers.adjs
    if not any(len(a.carriers) for a in next(iter(local.values()))):
        return None
    meshes = [(doc.parts[i].vertices, adj) for i, adj in zip(parts, adjs, strict=True)]
    lengths = _codeword_lengths(options.payload_bits)
    iterations, score = choose_iterations(meshes, local, lengths)
    if score < MIN_SCORE:
        return None
    return _ArrayDoc([(unsmooth(v, adj, iterations), doc.parts[i].faces)
                      for (v, adj), i in zip(meshes, parts, strict=True)]), iterations


def _read_views(doc: MeshDocument, parts: list[int], key: str | bytes, options: Options,
                analysed: Progress = _no_progress,
                layers: _Layers | None = None) -> DetectResult:
    """Detection over the views of :func:`_detect_doc` for one file's usable ``parts``: the
    connectivity layer first (what an untouched file reads, without the cost of the surface's
    frame), then both layers together and the geometric layer alone, made only when it did not
    read.  The false-positive figure counts the geometric views whenever the file is large enough
    to have had geometric carriers before a simplification (:data:`GEOMETRIC_DETECT_FROM`), whether
    or not it has them.  Last, the connectivity layer with the labels of every part one
    refinement step wider, then one narrower, where there is such a step
    (:func:`~core.sync.has_step`, connectivity only, so the figure counts these views exactly when
    they are made; :func:`_relabelled`): cropped pieces of meshes such as the Beast and the Ogre.
    Then, where a part has a boundary, the connectivity layer without the carriers next to it
    (:func:`_interior`: a crop's cut).  Last, where a regular part's fallback frame leaves a sign or
    an angle to the file's axes, the connectivity layer in the other frame that agrees best
    (:func:`_turned`: a rotated surface of revolution).  ``layers``: the parts' :func:`_layers`,
    when the caller has them."""
    methods, expected = options.detect_methods, options.payload_bits
    if layers is None:
        layers = _layers(doc, parts, key, methods, analysed)
    local, adjs = layers.local, layers.adjs
    views: list[View] = [(CONNECTIVITY, local)]
    if sum(len(doc.parts[i].vertices) for i in parts) >= GEOMETRIC_DETECT_FROM:
        geo = _GeometricViews(doc, parts, adjs, key, methods, _codeword_lengths(expected))
        views += [(BOTH, lambda: geo.both(local)), (GEOMETRY, lambda: geo.view(best=True))]
    for layer, step in ((WIDER, 1), (NARROWER, -1)):
        if any(has_step(lab, step) for lab in layers.labels):
            views.append((layer, partial(_relabelled, doc, parts, key, layers, step)))
    views += _interior_view(layers)
    frames = [_turn_frame(doc.parts[i].vertices, lab) for i, lab in zip(parts, layers.labels, strict=True)]
    if any(f is not None for f in frames):
        views.append((TURNED, partial(_turned, doc, parts, key, layers, frames, _codeword_lengths(expected))))
    return detect_views(views, key, expected)


def _coarsened(doc: MeshDocument, parts: list[int]) -> tuple[MeshDocument, str] | None:
    """The usable parts with every subdivided one replaced by its coarse mesh, and the scheme
    (``"midpoint"``, ``"loop"``, or both joined by ``+``), or None when no part is subdivided."""
    meshes, schemes = [], []
    for i in parts:
        p = doc.parts[i]
        undone = undo_subdivision(p.vertices, p.faces)
        if undone is None:
            meshes.append((p.vertices, p.faces))
            continue
        scheme, v, f = undone
        schemes.append(scheme)
        meshes.append((v, f))
    if not schemes:
        return None
    return _ArrayDoc(meshes), "+".join(sorted(set(schemes)))


def _largest_payload(carriers: float) -> int:
    """Largest payload (bits) whose codeword fits in ``carriers`` carriers (0 if none)."""
    for n in range(MAX_PAYLOAD_BITS, 0, -1):
        if codeword_length(n) <= carriers:
            return n
    return 0


#: capacity is measured with this key when none is given: the carriers depend on the key, by about
#: 1 % on the shared meshes (with the caller's key, the count is the one embedding will report)
_CAPACITY_KEY = b"meshmark-capacity-probe"


def capacity(data: bytes, options: Options, *, filename: str | None = None,
             limits: Limits = DEFAULT_LIMITS, progress: Progress | None = None) -> CapacityReport:
    """Carriers and payload room of a mesh file (``options``: ``method``, ``strength`` and,
    optionally, ``key``: with it the carriers are those an embedding with that key will have;
    without it, those of a fixed probe key).  ``max_payload_bits`` is verified: random payloads of
    that length really embed and read back with that key (:func:`_verified_payload`); the file
    returned to no one.  Without a method, what an embedding without one carries
    (:data:`~core.options.AUTO_METHOD`): the figures of :data:`~core.options.DEFAULT_METHOD`, or of the
    other method where that one offers a longer payload."""
    report = progress or _no_progress
    report(0.0)
    doc = read_mesh(data, filename, limits)
    report(Milestones.READ)
    first = options.embed_method
    rep, bound = _capacity_doc(doc, replace(options, method=first), report)
    if options.method is None and rep.max_payload_bits < bound:
        # the trials cut the payload below the carrier count's bound: the other method may carry more
        # (the Duck: ellipsoids 48 bits, planes 76-116; bench/results/capacity_keys.md)
        for other in _other_methods(first):
            alt, _ = _capacity_doc(doc, replace(options, method=other), _no_progress)
            if alt.max_payload_bits > rep.max_payload_bits:
                rep = alt
    report(1.0)
    return rep


def _capacity_doc(doc: MeshDocument, options: Options, report: Progress) -> tuple[CapacityReport, int]:
    """:func:`capacity` of a read file with ``options.method``, and the carrier count's bound on the
    payload (before the trials)."""
    method, s = options.embed_method, options.margin
    parts = _usable_parts(doc)
    carriers = 0
    new = [p.vertices.copy() for p in doc.parts]
    info = []
    rng = np.random.default_rng(0)
    cw = rng.integers(0, 2, codeword_length(None)).astype(np.uint8)
    key = options.key if options.key is not None else _CAPACITY_KEY
    meshes = [(doc.parts[i].vertices, doc.parts[i].faces) for i in parts]
    prepared, placements, selections = _prepared_placements(meshes, key, len(cw), method)
    # the embedding an embed with the key-derived code would make: both layers, the RMS budget at
    # the default strength, so that the expected distortion is the one the embed reports
    diagonal = _file_diagonal(doc)
    aim = _aim(_placed(placements)) * RMS_BUDGETS[0] if options.strength is None else None
    vs, stats, _ = embed_parts(meshes, key, cw, method, s, quantize=_part_quantizer(doc, parts, doc.decimals),
                               prepared=prepared, diagonal=diagonal, rms_budget=aim,
                               placements=placements, selections=selections)
    geometric = 0
    for k, i in enumerate(parts):
        new[i] = vs[k]
        carriers += stats[k].carriers
        geo = stats[k].geometric
        g = 0 if geo is None else len(geo.carriers)
        geometric += g
        info.append({"name": doc.parts[i].name, "vertices": len(doc.parts[i].vertices),
                     "carriers": stats[k].carriers, "geometric_carriers": g})
    max_bits = _largest_payload(carriers / CAPACITY_MARGIN)
    if carriers < COMPACT_BELOW:
        max_bits = max(max_bits, COMPACT_MAX_PAYLOAD)  # the compact frame's, when it embeds
    bound = max_bits
    if carriers < CAPACITY_SURE * codeword_length(max_bits or None):
        held: Callable[[bool], int] | None = None
        # the model needs carriers that stay where they are: no geometric layer (at the shortest
        # codeword, which gets it first), no regular labels
        layer = _placements(meshes, [adj for adj, _ in prepared], key, codeword_length(1))
        if all(p is None for p in layer) and not any(lab.regular for _, lab in prepared):
            r = _reach(meshes, prepared, key, method, s, diagonal, _part_quantizer(doc, parts, doc.decimals))
            held = partial(_held_payload, r, max_bits)
        max_bits = _verified_payload(doc, replace(options, key=key), max_bits, held,
                                     compact=carriers < COMPACT_BELOW)
    report(Milestones.VERIFIED)
    by_copies = {str(c): _largest_payload(carriers / c) for c in (1, 2, 4, 8, 16)}
    _, rms, mx, _ = _distortion(doc, new, {}, hausdorff=False)
    return CapacityReport(method=method, strength=s, carriers=carriers, max_payload_bits=max_bits,
                          copies_of_default=round(carriers / codeword_length(None), 3),
                          codeword_bits_default=codeword_length(None), payload_bits_by_copies=by_copies,
                          expected_rms_displacement=rms, expected_max_displacement=mx, parts=info,
                          geometric_carriers=geometric), bound


#: payload lengths capacity verifies, longest first, below the carrier-count bound
CAPACITY_LADDER = (256, 192, 128, 96, 64, 48, 32, 24, 16, 12, 8, 4, 2, 1)
#: random payloads of a length that must all embed for capacity to offer it (whether a payload fits
#: at the edge depends on its bits: with 4, bench capacity-keys still found 5-8 % of the payloads of
#: the offered lengths refused on the Duck and Spot, and compact lengths refused on the Sink).  At
#: stop 32 (50 keys, 6 small meshes, both methods): 8 trials, 2 of 5,698 trial embeddings refused
#: (the Sink with ellipsoids, key-31, 32 bits; Spot with planes, key-31, 188); 12, 1 of 5,718 (the
#: Spot one); 16, none of 5,656, but 2 keys of the Sink with planes offered 0 bits where a random
#: 32-bit payload embeds (why was not looked into), the Sink with ellipsoids at most 24 bits, and
#: capacity took twice as long (the Sink's max 7.8 -> 19.5 s).  Kept at 8.
CAPACITY_TRIALS = 8
#: copies of the codeword from which capacity trusts the carrier count without embedding (a 1M
#: mesh has ~450 copies of the longest codeword; eight trial embeddings would take ~12 s there)
CAPACITY_SURE = 8
#: compact-frame rounds of capacity's trial embeddings (a real embedding has COMPACT_ROUNDS): fewer
#: rounds can only refuse more, so capacity never offers more than embeds, and a trial that fails
#: costs a quarter (a capacity call on the Sink with ellipsoids took up to 127 s with 64)
CAPACITY_COMPACT_ROUNDS = 16
#: compact-frame rounds of the trials of a rung the trials alone decide on a mesh the model covers
#: (above what its carriers hold whatever the payload).  There the carriers stay where they are, and
#: a payload that embeds needs one round, or a few; many rounds are the edge, where some payloads
#: never read (CesiumMilkTruck with ellipsoids, key-87, 24 bits: 13 of 20 random payloads within 4
#: rounds, 5 in 7, 2 never; keys 0-24 at their offered lengths: 1-3 rounds, a few 5-9; stop 45)
CAPACITY_EDGE_ROUNDS = 4
#: random payloads such a rung's trials embed (each within CAPACITY_EDGE_ROUNDS rounds)
CAPACITY_EDGE_TRIALS = 24


def _exhaustive(n: int) -> bool:
    """Whether capacity's trials of ``n`` bits are every payload of every length up to ``n``."""
    return 2 ** (n + 1) - 2 <= 2 * CAPACITY_TRIALS


def _trial_payloads(rng: np.random.Generator, n: int, count: int = CAPACITY_TRIALS) -> list[str]:
    """The payloads capacity embeds to offer ``n`` bits: ``count`` random ones, or,
    where every payload of every length up to ``n`` is no more than twice that many (``n`` <= 3),
    all of them, so that what capacity offers there is exact (the Sink with ellipsoids, key-36:
    2 bits offered after 8 random trials, and 2 of the 4 payloads refused)."""
    if _exhaustive(n):
        return [format(i, f"0{k}b") for k in range(1, n + 1) for i in range(2**k)]
    return ["".join(map(str, rng.integers(0, 2, n))) for _ in range(count)]


def _reach(meshes: list[tuple[np.ndarray, np.ndarray]], prepared: list[tuple[Adjacency, Labels]],
           key: str | bytes, method: str, s: float, diagonal: float,
           quantize: Quantize) -> capacity_model.Reach:
    """What every carrier reads when asked for 0 and for 1 (:class:`core.capacity_model.Reach`): two
    probe embeddings at the embedder's last try (widest cap, no RMS budget)."""
    asked = []
    for value in (0, 1):
        _, _, an = embed_parts(meshes, key, np.full(1, value, np.uint8), method, s,
                               tol=_capped(CAP_FACTORS[-1]), prepared=prepared, quantize=quantize,
                               diagonal=diagonal, placements=[None] * len(meshes))
        asked.append(an)
    return capacity_model.reach(*asked)


def _held_payload(r: capacity_model.Reach, bound: int, ranked: bool = True) -> int:
    """The longest payload, at most ``bound`` bits, such that the carriers hold the codeword of every
    payload length up to it whatever the payload (:func:`core.capacity_model.holds`, each codeword
    length, shortest first, until one fails); ``ranked=False``: with hashed slots only."""
    held, last = 0, 0
    for n in range(1, bound + 1):
        if codeword_length(n) != last:
            last = codeword_length(n)
            if not capacity_model.holds(r, last, ranked=ranked):
                break
        held = n
    return held


def _verified_payload(doc: MeshDocument, options: Options, bound: int,
                      held: Callable[[bool], int] | None = None, compact: bool = False) -> int:
    """The longest payload, at most ``bound`` bits, that really embeds and reads back with
    ``options`` (key, method, strength): the first of the candidates that embeds
    :data:`CAPACITY_TRIALS` random payloads (0 if none does).  Candidates: ``bound`` and the rungs
    of the ladder below it; with ``held`` (:func:`_held_payload`: every length up to it holds
    whatever the payload), the rungs above it that only the compact frame carries (``compact``: a
    mesh of few carriers, up to :data:`~core.coding.COMPACT_MAX_PAYLOAD` bits), then ``held`` and
    the rungs below it.  A rung above ``held`` is the trials' alone: it needs
    :data:`CAPACITY_EDGE_TRIALS` payloads, each read within :data:`CAPACITY_EDGE_ROUNDS` compact
    rounds.  When a trial reads back only with slots other than the embedder's (the
    selection moved under a payload's moves, :func:`_embed_doc`), ranked slots are not trusted for
    this key: ``held`` is what the hashed slots hold, and the walk goes on from there.  Without
    ``held`` (a file the model does not cover) the trials do not use those other slots: eight
    trials passing through them are no evidence that every payload does (the gear: 72 bits offered
    that way, 1 of 6 payloads refused), and capacity offers what it offered before them.  Trials of
    every payload of a few bits (:func:`_exhaustive`) are embedded as an embedding is, retries and
    compact rounds included, so that what capacity offers there is exact."""
    rng = np.random.default_rng(bound)
    top = held(True) if held is not None else None
    trusted = True

    def ladder(top: int | None) -> list[int]:
        if top is None:
            return [bound] + [n for n in CAPACITY_LADDER if n < bound]
        high = min(bound, COMPACT_MAX_PAYLOAD) if compact else 0
        return [n for n in CAPACITY_LADDER if top < n <= high] + [top] + \
            [n for n in CAPACITY_LADDER if n < top]

    todo = ladder(top)
    probes: CompactProbes = {}  # the compact frame's probes, the same for every trial payload
    # trials alone decide the compact frame's lengths on a mesh of few carriers that the model does
    # not cover (the Sink: regular labels, so every embedding selects slightly other carriers and
    # the compact frame succeeds or not by chance): the highest such length whose trials pass can
    # be refused for a few payloads in a hundred (with ellipsoids, key-31, 32 bits: 2 of 30; 24 and
    # 16 bits: 0 of 40 each), so it is not offered, but the next one down whose trials pass too
    # (exhaustive trials are exact; the capsule's 64 bits, the standard frame's, stay offered)
    spare = held is None and compact
    while todo:
        n = todo.pop(0)
        if n <= 0:
            break
        # a rung above what the model holds, on a mesh it covers: the trials alone decide it
        edge = top is not None and n > top
        payloads = _trial_payloads(rng, n, CAPACITY_EDGE_TRIALS if edge else CAPACITY_TRIALS)
        reslotted: list[bool] = []
        # every payload of a few bits is tried as an embedding tries it (all its compact rounds and
        # retries): what passes is then exactly what embeds (the Sink with planes, key-43: the 1-bit
        # payload "1" needed more than 16 rounds, and 0 bits were offered where 32 embed)
        every = _exhaustive(n)
        rounds = None if every else CAPACITY_EDGE_ROUNDS if edge else CAPACITY_COMPACT_ROUNDS
        reslot = every or held is not None
        ok = all(_embeds(doc, replace(options, payload=p), rounds, reslotted, reslot=reslot,
                         compact_probes=probes) for p in payloads)
        if reslotted and trusted and held is not None:
            trusted = False
            hashed = held(False)
            if top is not None and hashed < top:
                top = hashed
                todo = [m for m in ladder(top) if m <= n]
                continue
        if ok:
            if not (spare and n <= COMPACT_MAX_PAYLOAD and not every):
                return n
            spare = False  # the margin rung given up: the next one down that passes is offered
    return 0


def capacity_file(data: bytes, *, filename: str | None = None, method: str | None = None,
                  strength: float | None = None, limits: Limits | None = None) -> CapacityReport:
    """:func:`capacity` with the options as keywords."""
    options = Options(method=method, strength=strength)
    return capacity(data, options, filename=filename, limits=limits or DEFAULT_LIMITS)

"""Fingerprinting: one random codeword per recipient, embedded as is, scored by correlation.

A copy for a recipient carries that recipient's codeword ``c`` of ``L`` uniformly random bits
(drawn by the caller, kept in a registry) instead of a payload: carrier ``i`` holds bit
``c[slot(i)] ^ w[slot(i)]`` (``w`` the key's whitening, :func:`core.coding.whitening`), with the
hashed slot assignment of :mod:`core.slots` so that a crop keeps every carrier's slot.

Tracing reads the detector's soft per-carrier votes (:func:`core.detection._soft_values`,
centred and de-whitened as :func:`core.detection._votes` does) and sums them per codeword bit,
divided by the square root of the bit's carrier count: ``y`` of shape ``(L,)``, ``y[j] > 0``
leaning to bit 0.  The score of a recipient is the
normalised correlation

    S = sum_j y[j] (1 - 2 c[j]) / ||y||.

Guarantee.  An innocent recipient's codeword is independent of the suspect mesh (it was drawn
at random and only the key holder knows it), so given ``y`` the terms ``1 - 2 c[j]`` are
independent fair signs and Hoeffding's inequality bounds ``P(S >= t) <= exp(-t^2 / 2)`` whatever
was done to the mesh (averaging, noise, another asset, another key).  The false-accusation
probability of a score is that bound times the number of codewords scored and of decoding
variants tried (union bound): accusing at a threshold ``eps`` accuses any innocent with
probability at most ``eps``.  Catching colluders has no such bound: it is measured
(``bench/results/tracing.md``).

Why not Tardos codes: their length for ``c`` colluders and error ``eps`` is about
``100 c^2 ln(1/eps)`` bits under the marking assumption (24,000 for 3 colluders at 1e-12),
ten times what a 10k-vertex mesh carries; averaging is not a marking-assumption attack anyway,
and with soft votes it leaves each colluder about ``1/c`` of the signal, which the correlation
score of random codewords measures directly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from core.analysis import Analysis, analyse, prepare
from core.coding import whitening
from core.detection import _soft_values, _votes
from core.embedding import embed_parts
from core.errors import CapacityError, PayloadError
from core.formats import DEFAULT_LIMITS, Limits, read_mesh
from core.options import Options
from core.pipeline import (
    Milestones,
    _analyses,
    _distortion,
    _no_progress,
    _part_info,
    _part_quantizer,
    _scaled,
    _usable_parts,
    _with_parts,
    _written,
)
from core.reports import EmbeddedFile, EmbedReport, Progress
from core.slots import HASHED_FROM

#: shortest and longest codeword (bits).  A score cannot exceed sqrt(L) and the innocents' bound
#: does not depend on L, while tracing costs (N, L/8) lookups: at 1,024 bits a clean copy can score
#: 32 and the average of three about 13 (measured ratio 0.42 of sqrt(L)), both far above the 7.5 of
#: 1e-9 among 10^3 codewords, and 10^5 registered copies are scored in well under a second
#: (6,005 bits took 2.3-2.9 s)
MIN_CODEWORD_BITS = 64
MAX_CODEWORD_BITS = 1024
#: decoding variants of the votes: the embedder's boundary with hard votes, the adaptive threshold
#: with soft votes (attacks that shift every statistic); both with hashed slots
VARIANTS = (False, True)
#: an embedding must read back at least this score (a lone clean copy accused at 1e-9 among
#: 10^6 codewords and both variants: sqrt(2 ln(2e15)))
MIN_EMBED_SCORE = math.sqrt(2.0 * math.log(2e15))


def codeword_length(carriers: int) -> int:
    """Codeword bits for a mesh with ``carriers`` carriers: as many as keep
    :data:`~core.slots.HASHED_FROM` carriers per bit (the hashed slots that survive crops),
    within [:data:`MIN_CODEWORD_BITS`, :data:`MAX_CODEWORD_BITS`].

    Raises
    ------
    CapacityError
        Fewer than ``HASHED_FROM * MIN_CODEWORD_BITS`` carriers.
    """
    n = carriers // HASHED_FROM
    if n < MIN_CODEWORD_BITS:
        raise CapacityError(f"too little capacity for a fingerprint: {carriers} carriers, at least "
                            f"{HASHED_FROM * MIN_CODEWORD_BITS} needed; use a mesh with more vertices",
                            carriers=carriers, needed=HASHED_FROM * MIN_CODEWORD_BITS)
    return min(n, MAX_CODEWORD_BITS)


def random_codeword(rng: np.random.Generator, length: int) -> np.ndarray:
    """``length`` independent fair bits, (L,) uint8: the innocent's side of the guarantee."""
    return rng.integers(0, 2, length, dtype=np.uint8)


def pack_codeword(bits: np.ndarray) -> bytes:
    return np.packbits(np.asarray(bits, np.uint8)).tobytes()


def unpack_codeword(data: bytes, length: int) -> np.ndarray:
    return np.unpackbits(np.frombuffer(data, np.uint8))[:length]


@dataclass(frozen=True)
class Fingerprinted:
    """A marked copy and the codeword it carries (``score``: what the embedder reads back)."""

    file: EmbeddedFile
    codeword: np.ndarray
    score: float


def embed_codeword(data: bytes, options: Options, *, codeword: np.ndarray | None = None,
                   rng: np.random.Generator | None = None, filename: str | None = None,
                   limits: Limits = DEFAULT_LIMITS, progress: Progress | None = None) -> Fingerprinted:
    """Mark a mesh file with a recipient's codeword instead of a payload.

    Parameters
    ----------
    data : bytes
        The cover file.
    options : Options
        ``key``, ``method``, ``strength`` (no payload).
    codeword : (L,) uint8 ndarray, optional
        The bits to embed (a copy issued before); ``None``: a fresh :func:`random_codeword` of
        :func:`codeword_length` bits drawn from ``rng``.
    rng : numpy.random.Generator, optional
        Required when ``codeword`` is ``None``.

    Raises
    ------
    CapacityError
        Too few carriers, or the copy does not read back with :data:`MIN_EMBED_SCORE`.
    """
    if options.payload is not None:
        raise PayloadError("a fingerprinted copy carries a codeword, not a payload")
    key, method, s = options.secret, options.embed_method, options.margin
    report = progress or _no_progress
    report(0.0)
    doc = read_mesh(data, filename, limits)
    report(Milestones.READ)
    parts = _usable_parts(doc)
    meshes = [(doc.parts[i].vertices, doc.parts[i].faces) for i in parts]
    prepared = prepare([v for v, _ in meshes], [f for _, f in meshes])
    report(Milestones.PREPARED)
    if codeword is None:
        if rng is None:
            raise ValueError("a fresh codeword needs an rng")
        # the carriers do not depend on the bits: count them with a probe codeword first
        carriers = sum(len(analyse(v, f, key, method, adj=adj, labels=lab).carriers)
                       for (v, f), (adj, lab) in zip(meshes, prepared, strict=True))
        codeword = random_codeword(rng, codeword_length(carriers))
    cw = np.asarray(codeword, np.uint8)
    L = len(cw)
    vs, stats, final = embed_parts(meshes, key, cw ^ whitening(key, L), method, s,
                                   quantize=_part_quantizer(doc, parts, doc.decimals), prepared=prepared)
    report(Milestones.VERIFIED)
    carriers = sum(st.carriers for st in stats)
    if carriers < HASHED_FROM * L:
        raise CapacityError(f"too little capacity: {carriers} carriers for a {L}-bit codeword "
                            f"({HASHED_FROM} per bit needed)", carriers=carriers, needed=HASHED_FROM * L)
    y = codeword_votes(final, key, L)
    score = float(correlation_scores(y, np.frombuffer(pack_codeword(cw), np.uint8)[None, :], L)[0])
    if score < MIN_EMBED_SCORE:
        raise CapacityError(f"the fingerprint reads back with score {score:.1f}, below "
                            f"{MIN_EMBED_SCORE:.1f}; try a larger strength (now {s:g})",
                            carriers=carriers, needed=HASHED_FROM * L)
    new = _with_parts(doc, parts, vs)
    moved, rms, mx, haus = _distortion(doc, new, {i: prepared[k][0] for k, i in enumerate(parts)})
    report(Milestones.MEASURED)
    rep = EmbedReport(method=method, strength=s, payload_bits=L, key_derived=False, codeword_bits=L,
                      carriers=carriers, copies=round(carriers / L, 3),
                      skipped=sum(st.skipped for st in stats), vertices_moved=moved, rms_displacement=rms,
                      max_displacement=mx, hausdorff=haus, decimals=doc.decimals, cap_factor=1.0,
                      parts=_part_info(doc, parts, stats))
    written = _written(doc, new, rep, doc.decimals)
    report(1.0)
    return Fingerprinted(written, cw, score)


def codeword_votes(analyses: list[Analysis], key: str | bytes, length: int,
                   variants: tuple[bool, ...] = VARIANTS) -> np.ndarray:
    """Per codeword bit, the carriers' de-whitened soft votes summed and divided by the square root
    of their count, one row per variant.

    Parameters
    ----------
    analyses : list of Analysis
        The detector's view of every part, under the key and the copy's method.
    length : int
        Codeword length ``L``.
    variants : tuple of bool
        ``adaptive`` of each row (:func:`core.detection._soft_values`).

    Returns
    -------
    (V, L) float64 ndarray
        ``> 0`` leans to bit 0; all zeros when there is no carrier.
    """
    out = np.zeros((len(variants), length))
    cache: dict = {}
    # every variant's values kept alive: _votes caches the centred votes under their id()
    values = [_soft_values(analyses, adaptive) for adaptive in variants]
    for r, vals in enumerate(values):
        slots, raw, sign = _votes(analyses, vals, key, length, False, cache)
        if len(slots):
            # each bit's vote sum in units of its own spread (sum / sqrt(n)): on meshes with
            # repeated labels a few bits gather hundreds of carriers and would outweigh the rest
            n = np.maximum(np.bincount(slots, minlength=length), 1)
            out[r] = np.bincount(slots, raw, minlength=length) * sign / np.sqrt(n)
    return out


def read_votes(data: bytes, options: Options, groups: list[tuple[str, int]], *, filename: str | None = None,
               limits: Limits = DEFAULT_LIMITS, progress: Progress | None = None
               ) -> dict[tuple[str, int], np.ndarray]:
    """:func:`codeword_votes` of a suspect file under ``options.key`` for every (method, codeword
    length) asked (the methods share one carrier selection)."""
    report = progress or _no_progress
    report(0.0)
    doc = read_mesh(data, filename, limits)
    report(Milestones.READ)
    methods = sorted({m for m, _ in groups})
    analyses = _analyses(doc, _usable_parts(doc), options.secret, methods,
                         _scaled(report, Milestones.READ, Milestones.ANALYSED))
    out = {(m, L): codeword_votes(analyses[m], options.secret, L) for m, L in sorted(set(groups))}
    report(1.0)
    return out


#: rows scored at once (bounds the memory of the byte-table gather: rows x L/8 float64)
_CHUNK = 16384


def correlation_scores(votes: np.ndarray, codewords: np.ndarray, length: int) -> np.ndarray:
    """Normalised correlation of every codeword with the votes, the best over the variants.

    Parameters
    ----------
    votes : (V, L) or (L,) float64 ndarray
        :func:`codeword_votes`.
    codewords : (N, ceil(L / 8)) uint8 ndarray
        Packed codewords (:func:`pack_codeword`), one row per copy.
    length : int

    Returns
    -------
    (N,) float64 ndarray
        ``S``; 0 where the votes are all zero.

    Notes
    -----
    ``S = (sum(y) - 2 sum_{c_j = 1} y_j) / ||y||``; the second sum is gathered from a table of
    every byte value at every byte position, so 10^5 codewords cost one (N, L/8) lookup.
    """
    y2 = np.atleast_2d(np.asarray(votes, np.float64))
    packed = np.asarray(codewords, np.uint8).reshape(len(codewords), -1)
    nb = -(-length // 8)
    bits = ((np.arange(256)[:, None] >> np.arange(7, -1, -1)) & 1).astype(np.float64)  # (256, 8)
    best = np.full(len(packed), -np.inf)
    for y in y2:
        norm = float(np.sqrt((y * y).sum()))
        if norm == 0.0:
            best = np.maximum(best, 0.0)
            continue
        yp = np.concatenate([y, np.zeros(8 * nb - length)]).reshape(nb, 8)
        table = yp @ bits.T  # (nb, 256): sum of y over the 1 bits of each byte value
        total = float(y.sum())
        scores = np.empty(len(packed))
        cols = np.arange(nb)
        for start in range(0, len(packed), _CHUNK):
            rows = packed[start:start + _CHUNK]
            scores[start:start + len(rows)] = total - 2.0 * table[cols, rows].sum(axis=1)
        best = np.maximum(best, scores / norm)
    return best


def false_accusation(scores: np.ndarray, tests: int) -> np.ndarray:
    """Union bound over ``tests`` codeword-variant pairs of Hoeffding's
    ``P(S >= score) <= exp(-score^2 / 2)`` for an innocent (1 for scores <= 0), clipped to 1."""
    s = np.maximum(np.asarray(scores, np.float64), 0.0)
    return np.minimum(1.0, tests * np.exp(-0.5 * s * s))


def score_threshold(epsilon: float, tests: int) -> float:
    """The score whose :func:`false_accusation` is ``epsilon``."""
    return math.sqrt(2.0 * math.log(tests / epsilon)) if tests > epsilon else 0.0

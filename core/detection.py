"""Blind detection: candidates, soft decoding, calibrated confidence, false-positive figures.

The detector does not know the payload length nor whether the key-derived code was used, so
it tries every candidate: the key-derived 32-bit code and every explicit length 1-256 (or only
the expected payload's length), for each method tried.  The reported
``false_positive_probability`` is the union bound over every candidate tried of the chance that
an unmarked mesh (or a wrong key, which reads random bits) passes that candidate's test.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import numpy as np

from core import conv
from core.analysis import SIGNED_FROM, Analysis
from core.coding import (
    COMPACT_BELOW,
    COMPACT_BITS,
    COMPACT_BUCKET,
    COMPACT_MAX_PAYLOAD,
    CRC_BITS,
    KEY_CODE_BITS,
    MAX_PAYLOAD_BITS,
    Decoded,
    binomial_tail,
    bits_to_str,
    codeword_length,
    compact_lengths,
    compact_mixing,
    compact_unmix,
    compact_whitening,
    crc_bits,
    key_code,
    log_odds,
    message_length,
    ml_messages,
    soft_decode,
    whitening,
)
from core.reports import DetectResult
from core.slots import assign_slots, bucketed_slots, dense_rank, ranked_by_default

#: the key-derived code is accepted with at most this many bit errors out of 32 (P = 7.7e-9)
KEY_CODE_MAX_ERRORS = 1
#: an expected payload is accepted without CRC when its p-value is below this
EXPECTED_P_THRESHOLD = 1e-6


def median(x: np.ndarray) -> float:
    """``float(np.median(x))`` of a 1-D array, bit for bit, in a fraction of its time
    (the detector takes about a thousand medians of a few hundred values per wrong-key detection
    of a small file: 41 -> 16 us each for 501 values, 467 -> 106 us for 20,000)."""
    n = len(x)
    if not n or np.isnan(x).any():
        return float("nan")
    k = n // 2
    if n % 2:
        return float(np.partition(x, k)[k])
    p = np.partition(x, [k - 1, k])
    return float((p[k - 1] + p[k]) / 2)


def adaptive_threshold(z: np.ndarray) -> float:
    """Split of the carriers' statistics into two classes (two-medians), for attacks that shift
    every statistic the same way (noise inflates them, smoothing shrinks them).  Whitening makes
    the two classes about equally large."""
    if len(z) < 8:
        return 0.0
    t = median(z)
    for _ in range(8):
        hi, lo = z[z > t], z[z <= t]
        if not len(hi) or not len(lo):
            break
        t = 0.5 * (median(hi) + median(lo))
    return t


#: how the carriers' statistics become votes: the embedder's boundary with hard votes, the adaptive
#: threshold with clipped soft votes, the adaptive threshold weighted by the carrier's scale, and
#: the same on the signed statistic (:func:`core.analysis.signed_statistic`)
HARD, ADAPTIVE, SCALED, SIGNED = 0, 1, 2, 3
#: ...and the embedder's boundary with hard votes from the carriers nearest their boundaries only
#: (:data:`NEAR_SHARE` of them, by ``|z| s``): under an RMS budget the embedder leaves out the
#: largest moves, so a carrier far from its boundary reads its bit only by chance (the gear marked
#: with ellipsoids: 0.50-0.66 right in the far six tenths, 0.87-0.95 in the near four, 0.70 in all)
#: and a cropped piece has too few carriers to outvote them
NEAR = 4
#: the share of the carriers (nearest their boundaries) that vote in the NEAR variant: crops of the
#: gear (ellipsoids, to 50 %) and of the rocker arm (ellipsoids, to 25 %), 4 each, read 4 + 4 at
#: 0.4, 3 + 3 at 0.3 and at 0.5
NEAR_SHARE = 0.4
#: soft votes are clipped at this many median deviations in the scaled variant
SCALED_CLIP = 3.0


def _soft_values(analyses: list[Analysis], adaptive: int) -> list[np.ndarray]:
    """Per-carrier vote (> 0 reads 0), before de-whitening.

    ``adaptive``: :data:`HARD` (or False): the embedding's own boundary (z = 0) and hard votes;
    :data:`ADAPTIVE` (or True): statistics centred on :func:`adaptive_threshold`, scaled by their
    median deviation and clipped to [-1, 1]; :data:`SCALED`: the same clipped at
    :data:`SCALED_CLIP` and weighted by the carrier's local scale ``s`` over the median one,
    divided by the largest so that votes stay in [-1, 1]. ``z`` is in units of ``s``, so an attack
    that adds the same absolute error to every vertex (quantisation, noise of a fixed amplitude)
    moves the ``z`` of a carrier with a small ring the most: weighting by ``s`` is the matched
    filter for it. :data:`SIGNED`: :data:`SCALED` on the signed statistic
    (:func:`core.analysis.signed_statistic`; an analysis without it reads as :data:`SCALED`).
    """
    out = []
    if adaptive == NEAR:
        for a in analyses:
            d = np.abs(a.z) * a.scale
            live = np.ones(len(d), bool) if a.muted is None else ~a.muted
            keep = live & (d <= np.quantile(d[live], NEAR_SHARE)) if live.any() else live
            x = np.where(a.z > 0, 1.0, -1.0)
            # centred over the voters, so that the centring of every live carrier's vote
            # (:func:`_votes`) leaves the others at 0
            out.append(np.where(keep, x - (x[keep].mean() if keep.any() else 0.0), 0.0))
        return out
    for a in analyses:
        stat = a.signed if adaptive == SIGNED and a.signed is not None else a.z
        live = stat if a.muted is None else stat[~a.muted]
        if adaptive and len(live):
            zc = stat - adaptive_threshold(live)
            w = median(np.abs(zc if a.muted is None else zc[~a.muted])) or 1.0
            if adaptive in (SCALED, SIGNED):
                weight = a.scale / (median(a.scale) or 1.0)
                x = np.clip(zc / w, -SCALED_CLIP, SCALED_CLIP) * weight
                x = x / (float(np.abs(x).max()) or 1.0)
            else:
                x = np.clip(zc / w, -1.0, 1.0)
        else:
            x = np.where(a.z > 0, 1.0, -1.0)
        out.append(x if a.muted is None else np.where(a.muted, 0.0, x))
    return out


def _votes(analyses: list[Analysis], values: list[np.ndarray], key: str | bytes, L: int,
           ranked: bool | None = None, cache: dict | None = None
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-carrier slot and centred raw vote, and the per-slot de-whitening sign, for codeword
    length L (``cache``: slots and centred votes, shared by the candidates of one method).  The
    de-whitened vote of a carrier is ``raw * sign[slot]``."""
    cache = {} if cache is None else cache
    key_slots = ("slots", L, ranked)
    if key_slots not in cache:
        cache[key_slots] = np.concatenate(layer_slots(analyses, L, ranked, cache)) if analyses \
            else np.zeros(0, np.int64)
    s = cache[key_slots]
    if len(s) == 0:
        return np.zeros(0, np.int64), np.zeros(0), np.ones(L)
    # whitening balances 0s and 1s, so the mean raw vote is a bias every carrier shares (noise
    # pushes every carrier outwards, smoothing inwards): remove it before de-whitening, or it
    # turns into agreement within slots that looks like signal
    # keyed by identity, with the list itself kept in the entry: a list freed by the caller cannot
    # lend its id() to the next one (tracing read one variant's cached votes for another that way)
    key_u = ("centred", id(values))
    if key_u not in cache or cache[key_u][0] is not values:
        u = np.concatenate(values)
        muted = [a.muted if a.muted is not None else np.zeros(len(a.z), bool) for a in analyses]
        live = ~np.concatenate(muted) if muted else np.ones(len(u), bool)
        if live.any():
            u = np.where(live, u - u[live].mean(), 0.0)  # muted carriers stay out of every sum
        cache[key_u] = (values, u)
    return s, cache[key_u][1], 1.0 - 2.0 * whitening(key, L)


def layer_slots(analyses: list[Analysis], L: int, ranked: bool | None = None,
                cache: dict | None = None) -> list[np.ndarray]:
    """Slot of every carrier of every analysis: connectivity carriers by
    :func:`~core.slots.assign_slots` over all of them (ranked or hashed), geometric carriers by
    their cell hash modulo ``L``."""
    local = [a.slot_hash for a in analyses if not a.geometric]
    dealt = iter(assign_slots(local, L, ranked, cache) if local else [])
    return [(a.slot_hash % np.uint64(L)).astype(np.int64) if a.geometric else next(dealt) for a in analyses]


def agreement(analyses: list[Analysis], lengths: list[int], ranked: bool = False) -> float:
    """How well the carriers' votes agree within their slots, at the best codeword length of
    ``lengths`` (slots hashed, as geometric carriers are; ``ranked``: ranked where the embedder
    ranks them, :func:`~core.slots.ranked_by_default` over all the carriers, as one part's
    connectivity carriers are), in standard deviations of what random
    votes give: ``sum (S^2 - sum v^2) / (mean v^2 sqrt(2 sum n (n - 1)))`` over the slots, with the
    adaptive soft votes (:data:`ADAPTIVE`) centred on their mean, at lengths where at least
    :data:`MIN_PAIRS` pairs of carriers share a slot.  The raw ratio, hard votes and no
    normalisation, grew with the length for random votes (fewer pairs, a wider spread): among the
    placements of the beetle simplified by 50 % a wrong one won at some long length (0.049 against
    0.038), this reads 8.1 at the embedder's placement and at most 3.2 at the others.  It does not
    change when a slot's votes all change sign, so it says nothing about the decoded bits:
    choosing among candidate placements by it leaves the chance that random bits pass a CRC as it
    was."""
    if not analyses:
        return 0.0
    h = np.concatenate([a.slot_hash for a in analyses])
    if len(h) < 2:
        return 0.0
    votes = np.concatenate(_soft_values(analyses, ADAPTIVE))
    votes = votes - votes.mean()
    var = float((votes * votes).sum()) / len(votes)
    # every length's slots at once: length k's slots are offset by the lengths before it
    ls = np.array(sorted(set(lengths)), np.int64)
    starts = np.concatenate([[0], np.cumsum(ls)[:-1]])
    base = np.broadcast_to(h, (len(ls), len(h)))
    by_rank = np.array([ranked and ranked_by_default(len(h), int(n)) for n in ls])
    if by_rank.any():
        base = np.where(by_rank[:, None], dense_rank(h).astype(np.uint64)[None, :], base)
    slots = ((base % ls[:, None].astype(np.uint64)).astype(np.int64) + starts[:, None]).ravel()
    n = np.bincount(slots, minlength=int(ls.sum())).astype(np.float64)
    pairs = np.add.reduceat(n * (n - 1), starts)
    ok = pairs >= MIN_PAIRS
    if not ok.any() or var <= 0:
        return 0.0
    sums = np.bincount(slots, np.tile(votes, len(ls)), minlength=int(ls.sum()))
    z = _standardised(np.add.reduceat(sums * sums, starts)[ok], pairs[ok], float((votes * votes).sum()), var)
    return max(0.0, float(np.max(z)))


#: fewest pairs of carriers sharing a slot for :func:`agreement` (and :func:`_agreement_z`) to
#: count a codeword length
MIN_PAIRS = 50


#: a codeword length is decoded only when its votes agree within slots by at least this many standard
#: deviations of what random votes give (or when too few slots hold two votes to tell); a length the
#: decoder could read gives at least about sqrt(L / 2) (8 for a 32-bit payload); wrong keys pass
#: 1-3 % of the time (the test's spread is 1.2-1.5 on real meshes, not 1)
MIN_AGREEMENT = 3.0
#: the agreement test is made when at least this share of the carriers have labels of their own
DISTINCT_FOR_TEST = 0.4
#: ...and when the view has at least 1 / HOPELESS carriers per codeword bit
HOPELESS = 4
#: the shortest codeword lengths, decoded first (the 32-bit payload's is the 8th); the others
#: are decoded together after them
DECODE_BATCH = 8


def _agreement_z(slots: np.ndarray, raw: np.ndarray, reps: np.ndarray | None) -> float:
    """Within-slot agreement of the votes of one carrier per label (``reps``: their indices; None
    when labels repeat too much to tell, see :attr:`_MethodDecoder.reps`), in units of its standard
    deviation for random votes: ``sum_j (S_j^2 - sum v^2) / (mean v^2 sqrt(2 sum_j n_j (n_j - 1)))``
    over the slots of those carriers (``inf`` when fewer than 50 pairs share a slot, or without
    ``reps``).  Carriers of one label always share a slot, and repeated labels (regular regions)
    have alike statistics: counting their pairs, wrong keys agreed at 5-7 standard deviations on
    Spot.  Sign flips of whole slots (de-whitening) do not change it, so the decoded bits stay
    independent of it."""
    if reps is None:
        return float("inf")
    s, v = slots[reps], raw[reps]
    z = _within_slots(s, v, int(s.max()) + 1 if len(s) else 1)
    return float("inf") if z is None else z


def _within_slots(slots: np.ndarray, v: np.ndarray, L: int) -> float | None:
    """``sum_j (S_j^2 - sum v^2) / (mean v^2 sqrt(2 sum_j n_j (n_j - 1)))`` of the votes ``v`` in
    ``slots`` (int64, of ``L``): their agreement within slots in standard deviations of random
    votes' (None when fewer than :data:`MIN_PAIRS` pairs share a slot)."""
    n = np.bincount(slots, minlength=L).astype(np.float64)
    pairs = float((n * (n - 1)).sum())
    if pairs < MIN_PAIRS:
        return None
    var = float((v * v).sum()) / len(v)
    if var <= 0:
        return 0.0
    sums = np.bincount(slots, v, minlength=L)
    return float(_standardised(float((sums * sums).sum()), pairs, float((v * v).sum()), var))


def _standardised(squares: np.ndarray | float, pairs: np.ndarray | float, power: float, var: float
                  ) -> np.ndarray | float:
    """``(sum_j S_j^2 - sum v^2) / (mean v^2 sqrt(2 sum_j n_j (n_j - 1)))`` from the slots' summed
    squared sums ``squares`` and pair counts ``pairs`` (one length's, or an array of lengths'),
    ``power = sum v^2`` and ``var = mean v^2``: the within-slot agreement in standard deviations
    of random votes' (:func:`_within_slots`, :func:`agreement`)."""
    return (squares - power) / (var * np.sqrt(2.0 * pairs))


def _slot_sums(slots: np.ndarray, raw: np.ndarray, sign: np.ndarray) -> np.ndarray:
    """Per-slot de-whitened vote sums (the decoder's LLRs up to a scale, which does not change the
    most likely message)."""
    return np.bincount(slots, raw, minlength=len(sign)) * sign


def _posterior(slots: np.ndarray, raw: np.ndarray, sign: np.ndarray, sums: np.ndarray,
               bits: np.ndarray, confidence: bool = True) -> tuple[Decoded, float]:
    """Calibrated decoding: exact per-bit posteriors with LLR ``log((1 - p) / p)`` per vote.

    The carrier error rate ``p`` comes from the votes' agreement *within* slots, which does not
    depend on the decoded codeword: for votes of mean ``m`` (``m = 1 - 2p`` for hard votes),
    ``E[S^2 - sum v^2] = n (n - 1) m^2`` per slot (method of moments).  Fitting ``p`` against the
    decoded codeword instead makes a wrong decoding look reliable.  With about one vote per slot
    (small meshes) there is no within-slot agreement to measure and the codeword fit is used.
    ``confidence`` False (the embedder's check that a payload reads back, which looks at the
    message only): the posteriors are not computed (an empty ``confidence``; the decoder's 2-3
    passes over the trellis in Python were a fifth of a 256-bit capacity's trial embeddings).
    """
    p = _carrier_error_rate(slots, raw, sign, sums, lambda: conv.encode(bits))
    if not confidence:
        return Decoded(np.asarray(bits, np.uint8), np.zeros(0)), p
    dec = soft_decode(log_odds(p) * sums)
    # the confidence of the maximum-likelihood message's own bits (the posteriors' most likely
    # value of a doubtful bit may differ from it)
    conf = np.where(dec.bits == bits, dec.confidence, 1.0 - dec.confidence)
    return Decoded(np.asarray(bits, np.uint8), conf), p


def _carrier_error_rate(slots: np.ndarray, raw: np.ndarray, sign: np.ndarray, sums: np.ndarray,
                        codeword: Callable[[], np.ndarray]) -> float:
    """Carrier error rate ``p`` from the votes' agreement within slots (method of moments, see
    :func:`_posterior`), or, with too few pairs of votes in one slot, from their disagreement with
    the decoded ``codeword()`` (per slot, computed only then)."""
    L = len(sums)
    votes = raw * sign[slots]
    n = np.bincount(slots, minlength=L).astype(np.float64)
    sq = np.bincount(slots, votes * votes, minlength=L)
    pairs = float((n * (n - 1)).sum())
    if pairs >= 50:
        m = min(np.sqrt(max(float((sums * sums - sq).sum()) / pairs, 0.0)), 1.0)
        return (1.0 - m) / 2.0 + 0.5 / (len(slots) + 2.0)
    cw = codeword()
    disagree = float(((1.0 - 2.0 * cw[slots]) * votes < 0).sum()) if len(slots) else 0.0
    return (disagree + 1.0) / (len(slots) + 2.0)


def compact_slots(slot_hashes: list[np.ndarray]) -> np.ndarray:
    """Every carrier's slot in the compact frame, all parts together."""
    out = bucketed_slots(slot_hashes, COMPACT_BITS, COMPACT_BUCKET)
    return np.concatenate(out) if out else np.zeros(0, np.int64)


def _compact_confidence(key: str | bytes, slots: np.ndarray, raw: np.ndarray, sign: np.ndarray,
                        sums: np.ndarray, bits: np.ndarray) -> tuple[np.ndarray, float]:
    """Posterior of each compact frame bit and the carrier error rate.

    Each slot's hard decision is right with ``q = 1 / (1 + exp(-|LLR|))`` (LLR as in
    :func:`_posterior`); a frame bit is the XOR of the slots of its row of the inverse matrix, so it
    is right with ``(1 + prod(2 q - 1)) / 2`` over those slots (the piling-up lemma, independent
    slots).  Every frame bit depends on about half the slots, so one doubtful slot makes every bit
    doubtful: the CRC, not these figures, decides the detection."""
    p = _carrier_error_rate(slots, raw, sign, sums, lambda: bits)
    n = np.bincount(slots, minlength=len(sums))
    # an empty slot reads 0 whatever happens to the mesh (the embedder chose the free bits for it)
    q = np.where(n > 0, 1.0 / (1.0 + np.exp(-np.abs(log_odds(p) * sums))), 1.0)
    _, inv = compact_mixing(key)
    logs = inv.astype(np.float64) @ np.log(np.maximum(2.0 * q - 1.0, 1e-300))
    return np.clip((1.0 + np.exp(logs)) / 2.0, 0.5, 1.0), p


#: decoding variants (votes, slot assignment): the embedder's own, then the ones that survive
#: attacks (global shifts of the statistics; crops that change the carrier count; absolute errors
#: of every vertex, which the scale-weighted votes read; measurements in core/README.md, section 5)
VARIANTS = ((HARD, None), (ADAPTIVE, None), (ADAPTIVE, True), (ADAPTIVE, False), (SCALED, None),
            (SIGNED, None))


def view_variants(layer: str, per_method: dict[str, list[Analysis]] | None) -> list[tuple[int, bool | None]]:
    """The decoding variants a view tries.  Only the connectivity view forces a slot assignment
    (for crops, which change the carrier count and move the surface's frame, so that only it reads
    them: the view of both layers is for attacks that keep every carrier, the geometric one has
    hashed slots only); the geometric view has no signed statistic (its carriers stay on their
    sides), and the signed variant needs :data:`SIGNED_FROM` connectivity carriers (a view made
    lazily, ``per_method`` None, counts it).  With both methods a file with the geometric layer
    tries 12 + 8 + 6 candidates per length, as many as before the signed variant (10 + 10 + 6),
    and 2 more for each relabelled view (:data:`RELABELLED`: the embedder's own variant only), 4
    for the interior view (also :data:`NEAR`: a crop's piece of a mesh marked at its RMS budget)."""
    if layer == INTERIOR:
        return [VARIANTS[0], (NEAR, None)]
    if layer in RELABELLED:
        return [VARIANTS[0]]
    many = layer != GEOMETRY and (per_method is None or any(
        sum(len(a.carriers) for a in analyses if not a.geometric) >= SIGNED_FROM
        for analyses in per_method.values()))
    return [(adaptive, ranked) for adaptive, ranked in VARIANTS
            if (layer == CONNECTIVITY or ranked is None) and (adaptive != SIGNED or many)]


def _same_as_auto(analyses: list[Analysis], L: int, ranked: bool | None) -> bool:
    """A forced slot assignment that equals the automatic one for every part (already tried), or
    that changes nothing (geometric carriers only)."""
    local = [a for a in analyses if not a.geometric]
    if ranked is None:
        return False
    return not local or ranked_by_default(sum(len(a.carriers) for a in local), L) == ranked


def detect_analyses(per_method: dict[str, list[Analysis]], key: str | bytes,
                    expected: np.ndarray | None = None, *, confidence: bool = True) -> DetectResult:
    """:func:`detect_views` with one view: the analyses of every part, for each method tried."""
    return detect_views([(CONNECTIVITY, per_method)], key, expected, confidence=confidence)


#: the layers a detection reads (``DetectResult.layer``): both layers' carriers together, the
#: connectivity layer alone (a crop: the surface's frame moved), the geometric layer alone (a
#: re-triangulation: the connectivity labels are gone)
BOTH, CONNECTIVITY, GEOMETRY = "both", "connectivity", "geometry"
#: the connectivity carriers of a mesh labelled one colour-refinement step wider or narrower
#: (:func:`core.sync.stepped_labels`): read the embedder's way only (hard votes, automatic slots:
#: what read every crop of the Beast and the Ogre that it read at all), and reported as the
#: connectivity layer
WIDER, NARROWER = "wider", "narrower"
#: the connectivity carriers with those near a boundary muted (:func:`core.pipeline._interior`): a
#: crop's cut changes the labels within the refinement's reach of it, so that those carriers read
#: their bits in the wrong slots; read, and reported, as the relabelled views are, and also with
#: the votes of the carriers nearest their boundaries only (:data:`NEAR`)
INTERIOR = "interior"
#: the connectivity carriers of a regular mesh in another frame of its fallback's cells
#: (:func:`core.pipeline._turned`: a rotated surface of revolution); read, and reported, as the
#: relabelled views are
TURNED = "turned"
RELABELLED = (WIDER, NARROWER, INTERIOR, TURNED)


def _reported(layer: str) -> str:
    """The layer a view's answer names: a relabelled view's is the connectivity layer."""
    return CONNECTIVITY if layer in RELABELLED else layer


#: a view: its layer name and, per method, the analyses of every part (or a function that makes
#: them, called only when the views before it did not read)
View = tuple[str, "dict[str, list[Analysis]] | Callable[[], dict[str, list[Analysis]]]"]


def view_candidates(layer: str, per_method: dict[str, list[Analysis]] | None, methods: int,
                    expected: np.ndarray | None) -> tuple[int, float]:
    """Candidates a view tries and the chance that any of them passes on random bits: methods x
    decoding variants x (every explicit length's CRC + zero padding, and the key-code test), plus
    the compact frame's lengths when the view's connectivity carriers are fewer than
    ``COMPACT_BELOW`` (only the connectivity views try it; the relabelled ones when the
    connectivity view's carriers are, ``per_method`` then being those); the variants are
    :func:`view_variants`.  ``per_method``:
    the view's analyses, or None for a view made lazily (it then counts as its layer allows)."""
    n_tries = len(view_variants(layer, per_method)) * methods
    lengths = [len(expected)] if expected is not None else list(range(1, MAX_PAYLOAD_BITS + 1))
    fp_explicit = sum(2.0 ** -(CRC_BITS + (message_length(n) - n - CRC_BITS)) for n in lengths)
    fp_key = binomial_tail(KEY_CODE_MAX_ERRORS, KEY_CODE_BITS) if expected is None else 0.0
    local = _reported(layer) == CONNECTIVITY
    compact = _compact_lengths(per_method, lengths) if local and per_method else []
    return n_tries, n_tries * (fp_explicit + fp_key) + methods * len(compact) * 2.0**-CRC_BITS


def _compact_lengths(per_method: dict[str, list[Analysis]], lengths: list[int]) -> list[int]:
    """The compact frame's lengths, where it can have been embedded: few connectivity carriers."""
    scarce = any(0 < sum(len(a.carriers) for a in analyses if not a.geometric) < COMPACT_BELOW
                 for analyses in per_method.values())
    return [n for n in lengths if n <= COMPACT_MAX_PAYLOAD] if scarce else []


def detect_views(views: list[View], key: str | bytes, expected: np.ndarray | None = None, *,
                 confidence: bool = True) -> DetectResult:
    """Decide from the views in turn; the first that reads the mark answers (``layer``).

    For each method, decoding variants (:data:`VARIANTS`) are tried in order over every explicit
    payload length (CRC test) and the key-derived code (bit errors); the first success of a method
    is its answer.  When several methods succeed (their statistics are correlated: both read the
    offset along ``e1``), :func:`_which_method` answers.
    ``false_positive_probability`` is the union bound over every candidate of every view, whether
    or not it was reached (:func:`view_candidates`; the views share their methods).
    ``confidence`` False: no per-bit posteriors (``bit_confidence`` empty), for a caller that only
    asks whether the message reads (the embedder's checks); every other figure is the same.
    """
    lengths = [len(expected)] if expected is not None else list(range(1, MAX_PAYLOAD_BITS + 1))
    given = next((v for _, v in views if isinstance(v, dict)), {})
    methods = max(len(given), 1)
    # the relabelled views, made lazily, try the compact frame when the connectivity view's carriers are few
    totals = [view_candidates(layer, v if isinstance(v, dict) else given if layer in RELABELLED else None,
                              methods, expected) for layer, v in views]
    n_tries = sum(t for t, _ in totals)
    fpp_total = min(1.0, sum(p for _, p in totals))
    near: list[DetectResult] = []
    for layer, made in views:
        per_method = made if isinstance(made, dict) else made()
        if not any(len(a.carriers) for analyses in per_method.values() for a in analyses):
            continue
        compact = _compact_lengths(given if layer in RELABELLED else per_method, lengths)
        # methods whose analyses are the same objects (the geometric layer reads every method's
        # carriers with one statistic) are decoded once, and a mark read there names no method
        by_analyses: dict[tuple[int, ...], list[str]] = {}
        for method, analyses in per_method.items():
            by_analyses.setdefault(tuple(id(a) for a in analyses), []).append(method)
        decoders = [_MethodDecoder(names[0] if len(names) == 1 else None, per_method[names[0]], key, expected,
                                   lengths, n_tries, fpp_total, compact, confidence)
                    for names in by_analyses.values()]
        # variant by variant across the methods: a method that reads the mark the embedder's way
        # answers before any other is decoded the attack-tolerant ways
        for adaptive, ranked in view_variants(layer, per_method):
            # the key-derived code of every method first (one candidate each), then the explicit
            # lengths, then the compact frame
            for frame in ("key", "explicit", "compact"):
                found = [(d.analyses, hit) for d in decoders
                         if (hit := d.try_variant(adaptive, ranked, frame)) is not None]
                if found:
                    # the method whose carriers sit at an embedder's margin names the mark, whichever
                    # decoded first (an untouched file marked with ellipsoids, a 2-bit payload: the
                    # planes view decoded a variant earlier, 1 of 54 in tests/core/test_engine.py)
                    answer = _which_method(found)
                    # (a turned view's carriers are other vertices than the connectivity view's)
                    answer = replace(answer, method=_marked_with(per_method if layer == TURNED else given,
                                                                 answer.method))
                    return replace(answer, layer=_reported(layer))
        near += [replace(d.near, layer=_reported(layer)) for d in decoders if d.near is not None]
    # informed detection accepted by its p-value but without an exact CRC match
    accepted = [r for r in near if r.detected]
    if accepted:
        return accepted[0]
    closest: DetectResult | None = None
    for r in near:
        if closest is None or (r.bit_errors or 0) < (closest.bit_errors or 0):
            closest = r
    if closest is not None:
        return closest
    method0 = next(iter(given), None)
    analyses0 = [a for a in given.get(method0, []) if not a.geometric] if method0 else []
    carriers0 = int(sum(len(a.carriers) for a in analyses0))
    return DetectResult(detected=False, payload=None, bit_confidence=[], false_positive_probability=1.0,
                        copies=0.0, carriers=carriers0, crc_ok=False, method=method0, key_derived=False,
                        parts=[{"carriers": len(a.carriers)} for a in analyses0])


#: relative width of the window in which the embedder's margin gathers the moved carriers' ``z``
#: (a file's float32 rounding moves them by about 1e-4 of it), and the share of the carriers that
#: must gather there, at least twice another method's, for it to say which method embedded
MARGIN_WINDOW, MARGIN_SHARE = 1e-3, 0.05


def margin_share(analyses: list[Analysis]) -> float:
    """The largest share of the carriers whose ``z`` (> 0) lie within a relative
    :data:`MARGIN_WINDOW` of each other: the embedder moves every carrier that read 0 wrong or too
    close to the same ``z`` (its margin) in its own method's statistic, which another method's
    statistic spreads (marked shared meshes, both methods: 0.09-0.42 in the embedding method's
    statistic, at most 0.019 in the other's)."""
    z = np.concatenate([a.z if a.muted is None else a.z[~a.muted] for a in analyses]) if analyses \
        else np.zeros(0)
    pos = np.sort(z[z > 0])
    if not len(pos):
        return 0.0
    run = np.searchsorted(pos, pos * (1.0 + MARGIN_WINDOW), side="right") - np.arange(len(pos))
    return float(run.max()) / len(z)


#: in the views with geometric carriers (read alike in every method: they decode in a method the
#: file was not marked with, or in all, which then name none), the share of a method's connectivity
#: carriers at its margin that names it instead: at least twice every other method's and at least
#: this (the other method's statistic gathers at most 0.019 on marked shared meshes; the rocker arm
#: marked with planes after meshoptimizer 10 %: 0.044 against 0.0016, and ellipsoids decoded first)
SURVIVING_SHARE = 0.02


def _marked_with(local: dict[str, list[Analysis]], decoded: str | None) -> str | None:
    """The method whose connectivity carriers (``local``, per method) still gather at a margin
    (:data:`SURVIVING_SHARE`), else ``decoded``."""
    if len(local) < 2:
        return decoded
    shares = {m: margin_share([a for a in an if not a.geometric]) for m, an in local.items()}
    best = max(shares, key=lambda m: shares[m])
    rest = max(v for m, v in shares.items() if m != best)
    return best if shares[best] >= SURVIVING_SHARE and shares[best] >= 2.0 * rest else decoded


def _which_method(found: list[tuple[list[Analysis], tuple[float, DetectResult]]]) -> DetectResult:
    """Of the methods that decode in the same variant (both statistics read the offset along
    ``e1``), the one whose carriers gather at an embedder's margin (:func:`margin_share`: an
    untouched file), else the one whose carriers disagree least with the decoded codeword."""
    if len(found) > 1:
        # the connectivity carriers only: the geometric ones are read alike in every method
        shares = [margin_share([a for a in analyses if not a.geometric]) for analyses, _ in found]
        order = np.argsort(shares)[::-1]
        if shares[order[0]] >= MARGIN_SHARE and shares[order[0]] >= 2.0 * shares[order[1]]:
            return found[int(order[0])][1][1]
    return min((hit for _, hit in found), key=lambda item: item[0])[1]


class _MethodDecoder:
    """Candidates of one method (None: the same analyses of several, which a result then does not
    name), decoded one variant at a time (slots and votes cached)."""

    def __init__(self, method: str | None, analyses: list[Analysis], key: str | bytes,
                 expected: np.ndarray | None, lengths: list[int], n_tries: int, fpp_total: float,
                 compact: list[int], confidence: bool = True) -> None:
        self.method, self.analyses, self.key, self.expected = method, analyses, key, expected
        self.confidence = confidence
        self.compact = compact
        self.n_tries, self.fpp_total = n_tries, fpp_total
        self.code = key_code(key)
        self.by_L: dict[int, list[int]] = {}
        for n in lengths:
            self.by_L.setdefault(codeword_length(n), []).append(n)
        self.carriers = int(sum(len(a.carriers) for a in analyses))
        self.parts = [{"carriers": len(a.carriers), "regular_fallback": bool(a.regular)}
                      for a in analyses if not a.geometric]
        self.geometric = int(sum(len(a.carriers) for a in analyses if a.geometric))
        #: with an expected payload, the closest candidate so far
        self.near: DetectResult | None = None
        #: each decoding mode's votes, made when a variant first asks (an untouched file reads hard)
        self.values: dict[int, list[np.ndarray]] = {}
        hashes = np.concatenate([a.slot_hash for a in analyses]) if analyses else np.zeros(0, np.uint64)
        first = np.unique(hashes, return_index=True)[1]
        #: one carrier per label for the agreement test, when labels repeat little enough that a
        #: decodable codeword shows there: its votes agree at about 12 r / n standard deviations
        #: (r of n carriers kept; a 140-bit codeword), so r >= 0.4 n keeps it above 4.8
        self.reps: np.ndarray | None = first if len(first) >= DISTINCT_FOR_TEST * len(hashes) else None
        self.cache: dict = {}

    def _values(self, mode: int) -> list[np.ndarray]:
        if mode not in self.values:
            self.values[mode] = _soft_values(self.analyses, mode)
        return self.values[mode]

    def try_variant(self, adaptive: int, ranked: bool | None, frame: str
                    ) -> tuple[float, DetectResult] | None:
        """The first successful candidate of this variant, with its carrier error rate: the
        key-derived code (``frame="key"``: the paper's default mode, one candidate), the explicit
        payload lengths (``"explicit"``) or the compact frame's (``"compact"``)."""
        if frame == "key":
            return self._key_code(adaptive, ranked)
        return self._explicit(adaptive, ranked) if frame == "explicit" else self._compact(adaptive, ranked)

    def _compact(self, adaptive: int, ranked: bool | None) -> tuple[float, DetectResult] | None:
        """The compact frame: hard decision per slot, the keyed matrix inverted, the CRC of every
        length up to :data:`~core.coding.COMPACT_MAX_PAYLOAD` checked (no error correction)."""
        analyses, L = self.analyses, COMPACT_BITS
        if not self.compact or adaptive != HARD or ranked is not None or self.geometric:
            # the embedder's own reading only: without error correction the frame does not survive
            # what the other variants are for, and each variant tried would add to the false positives
            return None
        if "compact" not in self.cache:
            self.cache["compact"] = compact_slots([a.slot_hash for a in analyses])
        slots = self.cache["compact"]
        if not len(slots):
            return None
        _, raw, _ = _votes(analyses, self._values(adaptive), self.key, L, None, self.cache)
        sign = 1.0 - 2.0 * compact_whitening(self.key)
        sums = np.bincount(slots, raw, minlength=L) * sign
        bits = (sums < 0).astype(np.uint8)
        frame = compact_unmix(self.key, bits)
        for n in compact_lengths(frame, self.compact):
            payload = frame[:n]
            errors = None
            if self.expected is not None:
                errors = int((payload != self.expected).sum())
                if errors:
                    continue
            conf, p_err = _compact_confidence(self.key, slots, raw, sign, sums, bits)
            return p_err, DetectResult(
                detected=True, payload=bits_to_str(payload),
                bit_confidence=[round(float(c), 6) for c in conf[:n]],
                false_positive_probability=self.fpp_total, copies=round(self.carriers / L, 3),
                carriers=self.carriers, crc_ok=True, method=self.method, key_derived=False,
                bit_errors=errors, p_value=None if errors is None else binomial_tail(0, n), parts=self.parts,
                geometric_carriers=self.geometric)
        return None

    def _key_code(self, adaptive: int, ranked: bool | None) -> tuple[float, DetectResult] | None:
        analyses, carriers = self.analyses, self.carriers
        L = codeword_length(None)
        if self.expected is not None or _same_as_auto(analyses, L, ranked):
            return None
        slots, raw, sign = _votes(analyses, self._values(adaptive), self.key, L, ranked, self.cache)
        if not len(slots):
            return None
        sums = _slot_sums(slots, raw, sign)
        msg = ml_messages([sums])[0]
        errors = int((msg[:KEY_CODE_BITS] != self.code).sum())
        if errors > KEY_CODE_MAX_ERRORS:
            return None
        dec, p_err = _posterior(slots, raw, sign, sums, msg, self.confidence)
        return p_err, DetectResult(
            detected=True, payload=bits_to_str(dec.bits[:KEY_CODE_BITS]),
            bit_confidence=[round(float(c), 6) for c in dec.confidence[:KEY_CODE_BITS]],
            false_positive_probability=self.fpp_total, copies=round(carriers / L, 3), carriers=carriers,
            crc_ok=False, method=self.method, key_derived=True, bit_errors=errors,
            p_value=binomial_tail(errors, KEY_CODE_BITS), parts=self.parts, geometric_carriers=self.geometric)

    def _explicit(self, adaptive: int, ranked: bool | None) -> tuple[float, DetectResult] | None:
        analyses, key, carriers, cache = self.analyses, self.key, self.carriers, self.cache
        # the codeword lengths in two batches, the shortest first: each batch's slot sums, then one
        # pass of the decoder over all of them (a short payload is found without the long ones)
        todo = [(L, ns) for L, ns in self.by_L.items()
                if not _same_as_auto(analyses, L, ranked) and HOPELESS * carriers >= L]
        for batch in (todo[:DECODE_BATCH], todo[DECODE_BATCH:]):
            gathered = []
            for L, ns in batch:
                slots, raw, sign = _votes(analyses, self._values(adaptive), key, L, ranked, cache)
                if len(slots):
                    sums = _slot_sums(slots, raw, sign)
                    # an expected payload's one length is always decoded: its bit errors are asked for
                    if self.expected is not None or _agreement_z(slots, raw, self.reps) >= MIN_AGREEMENT:
                        gathered.append((L, ns, slots, raw, sign, sums))
            hit = self._explicit_batch(gathered)
            if hit is not None:
                return hit
        return None

    def _explicit_batch(self, gathered: list) -> tuple[float, DetectResult] | None:
        """Decode the candidate lengths ``gathered`` (codeword length, payload lengths, slots, votes,
        signs, slot sums) and test every payload length's CRC (or expected payload)."""
        expected, carriers, method, parts = self.expected, self.carriers, self.method, self.parts
        n_tries, fpp_total = self.n_tries, self.fpp_total
        messages = ml_messages([g[5] for g in gathered])
        for (L, ns, slots, raw, sign, sums), msg in zip(gathered, messages, strict=True):
            for n in ns:
                payload, crc, pad = msg[:n], msg[n:n + CRC_BITS], msg[n + CRC_BITS:]
                # the padding first: random bits fail it for 3 lengths in 4, without a CRC
                crc_ok = bool(not pad.any() and np.array_equal(crc, crc_bits(payload)))
                errors: int | None = None
                p_value: float | None = None
                if expected is not None:
                    errors = int((payload != expected).sum())
                    p_value = binomial_tail(errors, n)
                    ok = (crc_ok and errors == 0) or p_value * n_tries < EXPECTED_P_THRESHOLD
                    fpp = fpp_total if crc_ok and errors == 0 else min(1.0, n_tries * p_value)
                else:
                    ok, fpp = crc_ok, fpp_total
                near = self.near
                if not ok and (expected is None or (near is not None and near.bit_errors is not None
                                                    and errors is not None and near.bit_errors <= errors)):
                    continue
                dec, p_err = _posterior(slots, raw, sign, sums, msg, self.confidence)
                res = DetectResult(
                    detected=ok, payload=bits_to_str(payload),
                    bit_confidence=[round(float(c), 6) for c in dec.confidence[:n]],
                    false_positive_probability=fpp if ok else 1.0,
                    copies=round(carriers / L, 3), carriers=carriers, crc_ok=crc_ok, method=method,
                    key_derived=False, bit_errors=errors, p_value=p_value, parts=parts,
                    geometric_carriers=self.geometric)
                if ok and (expected is None or (crc_ok and errors == 0)):
                    return p_err, res
                if near is None or (near.bit_errors or 0) > (errors or 0) or (ok and not near.detected):
                    self.near = res
        return None

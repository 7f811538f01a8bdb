"""Blind detection: candidates, soft decoding, calibrated confidence, false-positive figures.

The detector does not know the payload length nor whether the key-derived code was used, so
it tries every candidate: the key-derived 32-bit code and every explicit length 1-256 (or only
the expected payload's length), for each method tried.  The reported
``false_positive_probability`` is the union bound over every candidate tried of the chance that
an unmarked mesh (or a wrong key, which reads random bits) passes that candidate's test.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from core.analysis import Analysis
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
    hamming_encode,
    key_code,
    log_odds,
    ml_bits,
    soft_decode,
    whitening,
)
from core.reports import DetectResult
from core.slots import assign_slots, bucketed_slots, ranked_by_default

#: the key-derived code is accepted with at most this many bit errors out of 32 (P = 7.7e-9)
KEY_CODE_MAX_ERRORS = 1
#: an expected payload is accepted without CRC when its p-value is below this
EXPECTED_P_THRESHOLD = 1e-6


def adaptive_threshold(z: np.ndarray) -> float:
    """Split of the carriers' statistics into two classes (two-medians), for attacks that shift
    every statistic the same way (noise inflates them, smoothing shrinks them).  Whitening makes
    the two classes about equally large."""
    if len(z) < 8:
        return 0.0
    t = float(np.median(z))
    for _ in range(8):
        hi, lo = z[z > t], z[z <= t]
        if not len(hi) or not len(lo):
            break
        t = 0.5 * (float(np.median(hi)) + float(np.median(lo)))
    return t


#: how the carriers' statistics become votes: the embedder's boundary with hard votes, the adaptive
#: threshold with clipped soft votes, and the adaptive threshold weighted by the carrier's scale
HARD, ADAPTIVE, SCALED = 0, 1, 2
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
    filter for it.
    """
    out = []
    for a in analyses:
        if adaptive and len(a.z):
            zc = a.z - adaptive_threshold(a.z)
            w = float(np.median(np.abs(zc))) or 1.0
            if adaptive == SCALED:
                weight = a.scale / (float(np.median(a.scale)) or 1.0)
                x = np.clip(zc / w, -SCALED_CLIP, SCALED_CLIP) * weight
                out.append(x / (float(np.abs(x).max()) or 1.0))
            else:
                out.append(np.clip(zc / w, -1.0, 1.0))
        else:
            out.append(np.where(a.z > 0, 1.0, -1.0))
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
        hashes = [a.slot_hash for a in analyses]
        cache[key_slots] = np.concatenate(assign_slots(hashes, L, ranked, cache)) if analyses \
            else np.zeros(0, np.int64)
    s = cache[key_slots]
    if len(s) == 0:
        return np.zeros(0, np.int64), np.zeros(0), np.ones(L)
    # whitening balances 0s and 1s, so the mean raw vote is a bias every carrier shares (noise
    # pushes every carrier outwards, smoothing inwards): remove it before de-whitening, or it
    # turns into agreement within slots that looks like signal
    key_u = ("centred", id(values))
    if key_u not in cache:
        u = np.concatenate(values)
        cache[key_u] = u - u.mean()
    return s, cache[key_u], 1.0 - 2.0 * whitening(key, L)


def _decode(slots: np.ndarray, raw: np.ndarray, sign: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """ML message bits from the per-slot de-whitened vote sums (the LLR scale does not change the
    argmax)."""
    sums = np.bincount(slots, raw, minlength=len(sign)) * sign
    return ml_bits(sums), sums


def _posterior(slots: np.ndarray, raw: np.ndarray, sign: np.ndarray, sums: np.ndarray,
               bits: np.ndarray) -> tuple[Decoded, float]:
    """Calibrated decoding: exact per-bit posteriors with LLR ``log((1 - p) / p)`` per vote.

    The carrier error rate ``p`` comes from the votes' agreement *within* slots, which does not
    depend on the decoded codeword: for votes of mean ``m`` (``m = 1 - 2p`` for hard votes),
    ``E[S^2 - sum v^2] = n (n - 1) m^2`` per slot (method of moments).  Fitting ``p`` against the
    decoded codeword instead makes a wrong decoding look reliable.  With about one vote per slot
    (small meshes) there is no within-slot agreement to measure and the codeword fit is used.
    """
    p = _carrier_error_rate(slots, raw, sign, sums, lambda: hamming_encode(bits))
    return soft_decode(log_odds(p) * sums), p


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
VARIANTS = ((HARD, None), (ADAPTIVE, None), (ADAPTIVE, True), (ADAPTIVE, False), (SCALED, None))


def _same_as_auto(analyses: list[Analysis], L: int, ranked: bool | None) -> bool:
    """A forced slot assignment that equals the automatic one for every part (already tried)."""
    return ranked is not None and ranked_by_default(sum(len(a.carriers) for a in analyses), L) == ranked


def detect_analyses(per_method: dict[str, list[Analysis]], key: str | bytes,
                    expected: np.ndarray | None = None) -> DetectResult:
    """Decide from the analyses of every part, for each method tried.

    For each method, decoding variants (:data:`VARIANTS`) are tried in order over every explicit
    payload length (CRC test) and the key-derived code (bit errors); the first success of a method
    is its answer.  When several methods succeed (their statistics are correlated: both read the
    offset along ``e1``), the one whose carriers disagree least with the decoded codeword wins.
    """
    n_tries = len(VARIANTS) * len(per_method)
    lengths = [len(expected)] if expected is not None else list(range(1, MAX_PAYLOAD_BITS + 1))
    # chance that one random candidate passes: CRC (+ zero padding) or the key-code test
    fp_explicit = sum(2.0 ** -(CRC_BITS + (codeword_length(n) // 7 * 4 - n - CRC_BITS)) for n in lengths)
    fp_key = binomial_tail(KEY_CODE_MAX_ERRORS, KEY_CODE_BITS) if expected is None else 0.0
    # the compact frame only where it can have been embedded: few carriers
    scarce = any(sum(len(a.carriers) for a in analyses) < COMPACT_BELOW for analyses in per_method.values())
    compact = [n for n in lengths if n <= COMPACT_MAX_PAYLOAD] if scarce else []
    fp_compact = len(compact) * 2.0**-CRC_BITS  # tried in the first variant only, once per method
    fpp_total = min(1.0, n_tries * (fp_explicit + fp_key) + len(per_method) * fp_compact)
    decoders = [_MethodDecoder(method, analyses, key, expected, lengths, n_tries, fpp_total, compact)
                for method, analyses in per_method.items()]
    # variant by variant across the methods: a method that reads the mark the embedder's way
    # answers before any other is decoded the attack-tolerant ways
    for adaptive, ranked in VARIANTS:
        # the key-derived code of every method first (one candidate each), then the explicit
        # lengths, then the compact frame
        for frame in ("key", "explicit", "compact"):
            found = [hit for d in decoders if (hit := d.try_variant(adaptive, ranked, frame)) is not None]
            if found:
                return min(found, key=lambda item: item[0])[1]
    # informed detection accepted by its p-value but without an exact CRC match
    accepted = [d.near for d in decoders if d.near is not None and d.near.detected]
    if accepted:
        return accepted[0]
    closest: DetectResult | None = None
    for d in decoders:
        if d.near is not None and (closest is None or (d.near.bit_errors or 0) < (closest.bit_errors or 0)):
            closest = d.near
    if closest is not None:
        return closest
    method0 = next(iter(per_method), None)
    analyses0 = per_method.get(method0, []) if method0 else []
    carriers0 = int(sum(len(a.carriers) for a in analyses0))
    return DetectResult(detected=False, payload=None, bit_confidence=[], false_positive_probability=1.0,
                        copies=0.0, carriers=carriers0, crc_ok=False, method=method0, key_derived=False,
                        parts=[{"carriers": len(a.carriers)} for a in analyses0])


class _MethodDecoder:
    """Candidates of one method, decoded one variant at a time (slots and votes cached)."""

    def __init__(self, method: str, analyses: list[Analysis], key: str | bytes, expected: np.ndarray | None,
                 lengths: list[int], n_tries: int, fpp_total: float, compact: list[int]) -> None:
        self.method, self.analyses, self.key, self.expected = method, analyses, key, expected
        self.compact = compact
        self.n_tries, self.fpp_total = n_tries, fpp_total
        self.code = key_code(key)
        self.by_L: dict[int, list[int]] = {}
        for n in lengths:
            self.by_L.setdefault(codeword_length(n), []).append(n)
        self.carriers = int(sum(len(a.carriers) for a in analyses))
        self.parts = [{"carriers": len(a.carriers), "regular_fallback": bool(a.regular)}
                      for a in analyses]
        #: with an expected payload, the closest candidate so far
        self.near: DetectResult | None = None
        self.values = {mode: _soft_values(analyses, mode) for mode in (HARD, ADAPTIVE, SCALED)}
        self.cache: dict = {}

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
        if not self.compact or adaptive != HARD or ranked is not None:
            # the embedder's own reading only: without error correction the frame does not survive
            # what the other variants are for, and each variant tried would add to the false positives
            return None
        if "compact" not in self.cache:
            self.cache["compact"] = compact_slots([a.slot_hash for a in analyses])
        slots = self.cache["compact"]
        if not len(slots):
            return None
        _, raw, _ = _votes(analyses, self.values[adaptive], self.key, L, None, self.cache)
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
                bit_errors=errors, p_value=None if errors is None else binomial_tail(0, n), parts=self.parts)
        return None

    def _key_code(self, adaptive: int, ranked: bool | None) -> tuple[float, DetectResult] | None:
        analyses, carriers = self.analyses, self.carriers
        L = codeword_length(None)
        if self.expected is not None or _same_as_auto(analyses, L, ranked):
            return None
        slots, raw, sign = _votes(analyses, self.values[adaptive], self.key, L, ranked, self.cache)
        if not len(slots):
            return None
        msg, sums = _decode(slots, raw, sign)
        errors = int((msg[:KEY_CODE_BITS] != self.code).sum())
        if errors > KEY_CODE_MAX_ERRORS:
            return None
        dec, p_err = _posterior(slots, raw, sign, sums, msg)
        return p_err, DetectResult(
            detected=True, payload=bits_to_str(dec.bits[:KEY_CODE_BITS]),
            bit_confidence=[round(float(c), 6) for c in dec.confidence[:KEY_CODE_BITS]],
            false_positive_probability=self.fpp_total, copies=round(carriers / L, 3), carriers=carriers,
            crc_ok=False, method=self.method, key_derived=True, bit_errors=errors,
            p_value=binomial_tail(errors, KEY_CODE_BITS), parts=self.parts)

    def _explicit(self, adaptive: int, ranked: bool | None) -> tuple[float, DetectResult] | None:
        analyses, key, expected, carriers = self.analyses, self.key, self.expected, self.carriers
        method, parts, cache = self.method, self.parts, self.cache
        n_tries, fpp_total = self.n_tries, self.fpp_total
        for L, ns in self.by_L.items():
            if _same_as_auto(analyses, L, ranked):
                continue
            slots, raw, sign = _votes(analyses, self.values[adaptive], key, L, ranked, cache)
            if len(slots) == 0:
                continue
            msg, sums = _decode(slots, raw, sign)
            for n in ns:
                payload, crc, pad = msg[:n], msg[n:n + CRC_BITS], msg[n + CRC_BITS:]
                crc_ok = bool(np.array_equal(crc, crc_bits(payload)) and not pad.any())
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
                dec, p_err = _posterior(slots, raw, sign, sums, msg)
                res = DetectResult(
                    detected=ok, payload=bits_to_str(payload),
                    bit_confidence=[round(float(c), 6) for c in dec.confidence[:n]],
                    false_positive_probability=fpp if ok else 1.0,
                    copies=round(carriers / L, 3), carriers=carriers, crc_ok=crc_ok, method=method,
                    key_derived=False, bit_errors=errors, p_value=p_value, parts=parts)
                if ok and (expected is None or (crc_ok and errors == 0)):
                    return p_err, res
                if near is None or (near.bit_errors or 0) > (errors or 0) or (ok and not near.detected):
                    self.near = res
        return None

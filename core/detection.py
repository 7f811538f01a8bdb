"""Blind detection: candidates, soft decoding, calibrated confidence, false-positive figures.

The detector does not know the payload length nor whether the key-derived code was used, so
it tries every candidate: the key-derived 32-bit code and every explicit length 1-256 (or only
the expected payload's length), for each method tried.  The reported
``false_positive_probability`` is the union bound over every candidate tried of the chance that
an unmarked mesh (or a wrong key, which reads random bits) passes that candidate's test.
"""

from __future__ import annotations

import numpy as np

from core.api import DetectResult
from core.coding import (
    CRC_BITS,
    KEY_CODE_BITS,
    MAX_PAYLOAD_BITS,
    binomial_tail,
    bits_to_str,
    codeword_length,
    crc_bits,
    hamming_encode,
    key_code,
    log_odds,
    soft_decode,
    whitening,
)
from core.watermark import HASHED_FROM, Analysis, assign_slots_all

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


def _votes(analyses: list[Analysis], key: str | bytes, L: int, adaptive: bool = False,
           ranked: bool | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per-carrier slot and de-whitened soft vote in [-1, 1] (> 0 reads 0) for codeword length L.

    ``adaptive``: statistics are centred on :func:`adaptive_threshold` and scaled by their
    median deviation (soft votes); otherwise the embedding's own boundary (z = 0) and hard votes.
    """
    mask = whitening(key, L)
    slots, votes = [], []
    for a, s in zip(analyses, assign_slots_all(analyses, L, ranked), strict=True):
        if len(a.carriers) == 0:
            continue
        if adaptive:
            zc = a.z - adaptive_threshold(a.z)
            w = float(np.median(np.abs(zc))) or 1.0
            u = np.clip(zc / w, -1.0, 1.0)
        else:
            u = np.where(a.z > 0, 1.0, -1.0)
        vote = u * (1.0 - 2.0 * mask[s])
        slots.append(s)
        votes.append(vote)
    if not slots:
        return np.zeros(0, np.int64), np.zeros(0)
    return np.concatenate(slots), np.concatenate(votes)


def _decode(slots: np.ndarray, votes: np.ndarray, L: int):
    """Two-pass soft decoding: estimate the carrier error rate, then exact posteriors."""
    sums = np.bincount(slots, votes, minlength=L)
    dec = soft_decode(log_odds(0.25) * sums)
    cw = hamming_encode(dec.bits)
    disagree = float(((1.0 - 2.0 * cw[slots]) * votes < 0).sum()) if len(slots) else 0.0
    p = (disagree + 1.0) / (len(slots) + 2.0)
    return soft_decode(log_odds(p) * sums), p


#: decoding variants (adaptive threshold, slot assignment): the embedder's own, then the ones
#: that survive attacks (global shifts of the statistics; crops that change the carrier count)
VARIANTS = ((False, None), (True, None), (False, True), (True, True), (False, False), (True, False))


def _same_as_auto(analyses: list[Analysis], L: int, ranked: bool | None) -> bool:
    """A forced slot assignment that equals the automatic one for every part (already tried)."""
    return ranked is not None and (sum(len(a.carriers) for a in analyses) < HASHED_FROM * L) == ranked


def detect_analyses(per_method: dict[str, list[Analysis]], key: str | bytes,
                    expected: np.ndarray | None = None) -> DetectResult:
    """Decide from the analyses of every part, for each method tried.

    Candidates, in order: for each method, with the embedding's boundary then with the adaptive
    threshold, every explicit payload length (CRC test) and the key-derived code (bit errors).
    """
    n_tries = len(VARIANTS) * len(per_method)
    lengths = [len(expected)] if expected is not None else list(range(1, MAX_PAYLOAD_BITS + 1))
    # chance that one random candidate passes: CRC (+ zero padding) or the key-code test
    fp_explicit = sum(2.0 ** -(CRC_BITS + (codeword_length(n) // 7 * 4 - n - CRC_BITS)) for n in lengths)
    fp_key = binomial_tail(KEY_CODE_MAX_ERRORS, KEY_CODE_BITS) if expected is None else 0.0
    fpp_total = min(1.0, n_tries * (fp_explicit + fp_key))
    code = key_code(key)
    by_L: dict[int, list[int]] = {}
    for n in lengths:
        by_L.setdefault(codeword_length(n), []).append(n)
    best: DetectResult | None = None
    for method, analyses in per_method.items():
        carriers = int(sum(len(a.carriers) for a in analyses))
        parts = [{"carriers": int(len(a.carriers)), "regular_fallback": bool(a.regular)} for a in analyses]
        for adaptive, ranked in VARIANTS:
            for L, ns in by_L.items():
                if _same_as_auto(analyses, L, ranked):
                    continue
                slots, votes = _votes(analyses, key, L, adaptive, ranked)
                if len(slots) == 0:
                    continue
                dec, _ = _decode(slots, votes, L)
                for n in ns:
                    msg = dec.bits
                    payload, crc, pad = msg[:n], msg[n:n + CRC_BITS], msg[n + CRC_BITS:]
                    crc_ok = bool(np.array_equal(crc, crc_bits(payload)) and not pad.any())
                    errors: int | None = None
                    p_value: float | None = None
                    if expected is not None:
                        errors = int((payload != expected).sum())
                        p_value = binomial_tail(errors, n)
                        ok = (crc_ok and errors == 0) or p_value * n_tries < EXPECTED_P_THRESHOLD
                        fpp = min(1.0, n_tries * p_value) if not crc_ok else fpp_total
                    else:
                        ok, fpp = crc_ok, fpp_total
                    if not ok and (expected is None or (best is not None and best.bit_errors is not None
                                                        and errors is not None
                                                        and best.bit_errors <= errors)):
                        continue
                    res = DetectResult(
                        detected=ok, payload=bits_to_str(payload),
                        bit_confidence=[round(float(c), 6) for c in dec.confidence[:n]],
                        false_positive_probability=fpp if ok else 1.0,
                        copies=round(carriers / L, 3), carriers=carriers, crc_ok=crc_ok, method=method,
                        key_derived=False, bit_errors=errors, p_value=p_value, parts=parts)
                    if ok:
                        return res
                    best = res
            if expected is None and not _same_as_auto(analyses, codeword_length(None), ranked):
                L = codeword_length(None)
                slots, votes = _votes(analyses, key, L, adaptive, ranked)
                if len(slots):
                    dec, _ = _decode(slots, votes, L)
                    errors = int((dec.bits[:KEY_CODE_BITS] != code).sum())
                    if errors <= KEY_CODE_MAX_ERRORS:
                        return DetectResult(
                            detected=True, payload=bits_to_str(dec.bits[:KEY_CODE_BITS]),
                            bit_confidence=[round(float(c), 6) for c in dec.confidence[:KEY_CODE_BITS]],
                            false_positive_probability=fpp_total, copies=round(carriers / L, 3),
                            carriers=carriers, crc_ok=False, method=method, key_derived=True,
                            bit_errors=errors, p_value=binomial_tail(errors, KEY_CODE_BITS), parts=parts)
    if best is not None:
        return best
    method0 = next(iter(per_method), None)
    analyses0 = per_method.get(method0, []) if method0 else []
    carriers0 = int(sum(len(a.carriers) for a in analyses0))
    return DetectResult(detected=False, payload=None, bit_confidence=[], false_positive_probability=1.0,
                        copies=0.0, carriers=carriers0, crc_ok=False, method=method0, key_derived=False,
                        parts=[{"carriers": int(len(a.carriers))} for a in analyses0])



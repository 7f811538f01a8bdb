"""core.detection on synthetic carriers (no mesh): decoding, the carrier error-rate estimate, the
acceptance tests and the false-positive figure."""

from __future__ import annotations

import warnings
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from core import detection
from core.analysis import Analysis
from core.coding import codeword_length, encode, key_code
from core.detection import ADAPTIVE, SCALED, _posterior, _soft_values, adaptive_threshold, detect_analyses
from core.slots import assign_slots

KEY = "detection key"


def carriers_reading(word: np.ndarray, k: int, seed: int, flip: float = 0.0) -> Analysis:
    """``k`` carriers whose statistics read ``word`` (whitened), a fraction ``flip`` of them wrong."""
    rng = np.random.default_rng(seed)
    hashes = rng.integers(0, 2**63, k, dtype=np.uint64)
    slots = assign_slots([hashes], len(word))[0]
    z = np.where(word[slots] == 0, 1.0, -1.0) * rng.uniform(0.05, 0.2, k)
    z[rng.random(k) < flip] *= -1
    empty = np.zeros((k, 3))
    return Analysis(np.arange(k), hashes, z, empty, np.zeros((k, 3, 3)), empty, np.ones(k), False)


def test_an_explicit_payload_is_found_with_its_length() -> None:
    payload = np.array([1, 0, 1, 1, 0, 0, 1, 0, 1, 1], np.uint8)
    result = detect_analyses({"planes": [carriers_reading(encode(KEY, payload), 600, 1)]}, KEY)
    assert result.detected and result.crc_ok and result.payload == "1011001011"
    assert result.method == "planes" and not result.key_derived and len(result.bit_confidence) == 10
    assert result.false_positive_probability < 1e-6


def test_the_key_derived_code_and_the_expected_payload() -> None:
    found = detect_analyses({"ellipsoids": [carriers_reading(encode(KEY, None), 300, 2)]}, KEY)
    assert found.detected and found.key_derived and found.bit_errors == 0
    assert found.payload == "".join(map(str, key_code(KEY)))
    payload = np.ones(16, np.uint8)
    checked = detect_analyses({"planes": [carriers_reading(encode(KEY, payload), 600, 3)]}, KEY, payload)
    assert checked.detected and checked.bit_errors == 0 and checked.p_value == 2.0**-16


TEN = np.array([1, 0, 1, 1, 0, 0, 1, 0, 1, 1], np.uint8)


@pytest.mark.parametrize(("payload", "expected", "flip"),
                         [(None, False, 0.0), (TEN, False, 0.0), (TEN, True, 0.0), (TEN, True, 0.45)])
def test_without_confidences_the_same_answer(payload: np.ndarray | None, expected: bool, flip: float) -> None:
    """The embedder's check asks for no per-bit posteriors: every other figure is the detection's
    (the key-derived code, an explicit payload, an expected one, and the closest candidate of an
    expected payload that does not read)."""
    analyses = [carriers_reading(encode(KEY, payload), 400, 5, flip)]
    full = detect_analyses({"planes": analyses}, KEY, payload if expected else None)
    bare = detect_analyses({"planes": analyses}, KEY, payload if expected else None, confidence=False)
    assert full.bit_confidence and bare.bit_confidence == []
    assert full.detected == (flip == 0.0)
    assert replace(bare, bit_confidence=full.bit_confidence) == full


def test_the_code_absorbs_wrong_carriers() -> None:
    payload = np.array([0, 1] * 16, np.uint8)
    noisy = carriers_reading(encode(KEY, payload), 1200, 4, flip=0.15)
    assert detect_analyses({"planes": [noisy]}, KEY).payload == bits(payload)


def test_a_wrong_key_reads_nothing() -> None:
    analyses = [carriers_reading(encode(KEY, np.ones(8, np.uint8)), 600, 5)]
    result = detect_analyses({"planes": analyses}, "another key")
    assert not result.detected and result.payload is None and result.false_positive_probability == 1.0


@pytest.mark.parametrize("flip", [0.05, 0.2, 0.35])
def test_the_carrier_error_rate_comes_from_agreement_within_slots(flip: float) -> None:
    """Votes of one slot agree as often as the error rate allows; the estimate does not depend on
    which codeword is decoded."""
    rng = np.random.default_rng(6)
    length, k = 76, 7600
    slots = rng.integers(0, length, k)
    truth = 1.0 - 2.0 * rng.integers(0, 2, length)
    raw = truth[slots] * np.where(rng.random(k) < flip, -1.0, 1.0)
    sign = np.ones(length)
    sums = np.bincount(slots, raw, minlength=length)
    _, p = _posterior(slots, raw, sign, sums, np.zeros(32, np.uint8))
    assert p == pytest.approx(flip, abs=0.03)


def test_adaptive_threshold_splits_two_shifted_classes() -> None:
    z = np.r_[np.full(20, -1.0), np.full(20, 3.0)]
    assert adaptive_threshold(z) == 1.0
    assert adaptive_threshold(np.array([5.0, 6.0])) == 0.0  # too few to split


def bits(values: np.ndarray) -> str:
    return "".join(map(str, values.tolist()))


def test_scale_weighted_votes_read_absolute_errors(monkeypatch: pytest.MonkeyPatch) -> None:
    """Carriers whose rings differ in size by 100x, under an error of the same absolute size on
    every vertex (quantisation, fixed-amplitude noise) on top of one relative to the ring: ``z`` is
    in units of the ring, so small rings carry most of the error. The scale-weighted variant reads
    payloads that the unweighted ones lose (15 of 20 against 5 when measured), and never a wrong one."""
    payload = np.array([int(c) for c in "1011001110001111"], np.uint8)
    word = encode(KEY, payload)

    def found(seed: int) -> bool:
        rng = np.random.default_rng(seed)
        k = 3000
        hashes = rng.integers(0, 2**63, k, dtype=np.uint64)
        slots = assign_slots([hashes], len(word))[0]
        s = np.exp(rng.uniform(np.log(0.1), np.log(10.0), k))
        z = (np.where(word[slots] == 0, 1.0, -1.0) * 0.07 + rng.normal(0.0, 0.2, k)
                 + rng.normal(0.0, 0.3, k) / s)
        empty = np.zeros((k, 3))
        a = Analysis(np.arange(k), hashes, z, empty, np.zeros((k, 3, 3)), empty, s, False)
        res = detect_analyses({"planes": [a]}, KEY)
        assert not res.detected or res.payload == "1011001110001111"
        return res.detected

    with_scaled = sum(found(seed) for seed in range(20))
    monkeypatch.setattr(detection, "VARIANTS", detection.VARIANTS[:4])
    without = sum(found(seed) for seed in range(20))
    assert with_scaled > without


def test_scaled_votes_are_bounded_and_weighted() -> None:
    z = np.array([0.1, 0.1, -0.1, -0.1, 0.1, -0.1, 0.1, -0.1, 5.0])
    s = np.array([1.0, 4.0, 1.0, 4.0, 1.0, 1.0, 1.0, 1.0, 1.0])
    a = Analysis(np.arange(9), np.zeros(9, np.uint64), z, np.zeros((9, 3)), np.zeros((9, 3, 3)),
                 np.zeros((9, 3)), s, False)
    (v,) = _soft_values([a], SCALED)
    assert np.abs(v).max() == pytest.approx(1.0)
    assert v[1] == pytest.approx(4 * v[0]) and v[3] == pytest.approx(4 * v[2])
    (plain,) = _soft_values([a], ADAPTIVE)
    assert plain[1] == pytest.approx(plain[0])


def compact_carriers(payload: np.ndarray, k: int, seed: int) -> Analysis:
    """``k`` carriers whose statistics read ``payload`` in the compact frame: the free bits make
    the empty slots (which read 0) agree, as the embedder's constraints do."""
    from core import gf2
    from core.coding import COMPACT_BITS, COMPACT_BUCKET, compact_codeword, compact_whitening
    from core.slots import bucketed_slots

    rng = np.random.default_rng(seed)
    hashes = rng.integers(0, 2**64 - 1, k, dtype=np.uint64, endpoint=True)
    slots = bucketed_slots([hashes], COMPACT_BITS, COMPACT_BUCKET)[0]
    b0, d = compact_codeword(KEY, payload)
    empty_slots = np.flatnonzero(np.bincount(slots, minlength=COMPACT_BITS) == 0)
    free = gf2.solve(d[empty_slots], b0[empty_slots], rng.integers(0, 2, d.shape[1]).astype(np.uint8))
    assert free is not None
    word = b0 ^ (d.astype(np.int64) @ free % 2).astype(np.uint8) ^ compact_whitening(KEY)
    z = np.where(word[slots] == 0, 1.0, -1.0) * rng.uniform(0.05, 0.2, k)
    empty = np.zeros((k, 3))
    return Analysis(np.arange(k), hashes, z, empty, np.zeros((k, 3, 3)), empty, np.ones(k), False)


def test_the_compact_frame_is_found_below_1024_carriers_and_counted_in_the_false_positives() -> None:
    payload = np.random.default_rng(5).integers(0, 2, 32).astype(np.uint8)
    found = detect_analyses({"planes": [compact_carriers(payload, 120, 1)]}, KEY)
    assert found.detected and found.crc_ok and found.payload == "".join(map(str, payload))
    assert len(found.bit_confidence) == 32 and min(found.bit_confidence) > 0.5
    # one method: 5 variants x (256 standard lengths + key code) + 48 compact lengths, ~2^-32 each
    # (the signed variant needs 1024 carriers)
    assert found.false_positive_probability == pytest.approx(1.893e-7, rel=1e-3)
    checked = detect_analyses({"planes": [compact_carriers(payload, 120, 1)]}, KEY, payload)
    assert checked.detected and checked.bit_errors == 0
    # a wrong key reads nothing; many carriers: the compact frame is not tried (nor counted)
    assert not detect_analyses({"planes": [compact_carriers(payload, 120, 1)]}, "another key").detected
    many = detect_analyses({"planes": [carriers_reading(encode(KEY, payload), 1100, 4)]}, KEY)
    # 6 variants (the signed one too) x (256 standard lengths + key code), no compact frame
    assert many.detected and many.false_positive_probability == pytest.approx(2.137e-7, rel=1e-3)


def test_cached_votes_follow_the_values_not_their_id() -> None:
    """``_votes`` caches centred votes per list of values; a list freed by its caller can hand its
    id() to the next one (tracing once read the hard votes' cache for the adaptive ones): an entry
    whose list is not the one asked for is computed again."""
    from core.detection import _votes

    rng = np.random.default_rng(9)
    k = 200
    hashes = rng.integers(0, 2**63, k, dtype=np.uint64)
    empty = np.zeros((k, 3))
    z = rng.normal(size=k)
    a = Analysis(np.arange(k), hashes, z, empty, np.zeros((k, 3, 3)), empty, np.ones(k), False)
    old, new = [np.ones(k)], [np.arange(k, dtype=np.float64)]
    cache: dict = {("centred", id(new)): (old, np.zeros(k))}  # what an id() reused after a free leaves
    _, raw, _ = _votes([a], new, KEY, 76, None, cache)
    assert np.allclose(raw, new[0] - new[0].mean())


@settings(max_examples=200, deadline=None)
@given(st.lists(st.one_of(st.floats(-1e6, 1e6), st.just(float("nan"))), min_size=0, max_size=60),
       st.integers(0, 3))
def test_median_is_numpys_bit_for_bit(values: list[float], decimals: int) -> None:
    """``detection.median`` replaces ``np.median`` on the detector's hot path: the same float,
    ties, NaN and empty input included."""
    x = np.round(np.array(values, np.float64), decimals)
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        want = float(np.median(x))
    got = detection.median(x)
    assert (np.isnan(got) and np.isnan(want)) or got == want


@pytest.mark.parametrize("k", [1100, 900])
def test_the_signed_variant_reads_the_signed_statistic_from_1024_carriers(k: int) -> None:
    """Carriers whose unsigned statistic says nothing and whose signed one reads the codeword: the
    signed variant decodes them from SIGNED_FROM carriers on, and is neither tried nor counted in
    the false positives below."""
    payload = np.random.default_rng(7).integers(0, 2, 32).astype(np.uint8)
    a = carriers_reading(encode(KEY, payload), k, 9)
    noise = np.random.default_rng(10).normal(0.0, 0.1, k)
    mixed = replace(a, z=noise, signed=a.z)
    res = detect_analyses({"planes": [mixed]}, KEY)
    plain = detect_analyses({"planes": [replace(a, z=noise)]}, KEY)  # no signed statistic
    assert not plain.detected
    if k >= detection.SIGNED_FROM:
        assert res.detected and res.payload == "".join(map(str, payload))
        assert res.false_positive_probability == pytest.approx(6 / 5 * 1.781e-7, rel=1e-3)
    else:
        assert not res.detected


def test_the_method_whose_carriers_gather_at_a_margin_answers() -> None:
    """Two methods decode the same untouched file: the one in whose statistic the moved carriers
    sit at one margin answers, even where the other's carriers disagree less with the codeword;
    without such a gathering the lower disagreement decides."""
    payload = np.random.default_rng(3).integers(0, 2, 32).astype(np.uint8)
    word = encode(KEY, payload)
    spread = carriers_reading(word, 1100, 5)  # |z| uniform in [0.05, 0.2]: no margin
    gathered = carriers_reading(word, 1100, 5, flip=0.02)
    at_margin = np.abs(gathered.z) < 0.12
    gathered.z[at_margin] = np.sign(gathered.z[at_margin]) * 0.07  # moved to the margin
    assert detection.margin_share([gathered]) > 0.1 > 0.02 > detection.margin_share([spread])
    res = detect_analyses({"planes": [spread], "ellipsoids": [gathered]}, KEY)
    assert res.detected and res.method == "ellipsoids"
    noisier = carriers_reading(word, 1100, 6, flip=0.02)
    res = detect_analyses({"planes": [spread], "ellipsoids": [noisier]}, KEY)
    assert res.detected and res.method == "planes"


def _geometric_reading(k: int, length: int, seed: int, marked: bool) -> Analysis:
    """``k`` geometric carriers (slot = hash mod ``length``) reading a random word, 40 % of them
    wrong but close to their boundary (as an attack leaves them), or random votes (``marked``
    False)."""
    rng = np.random.default_rng(seed)
    hashes = rng.integers(0, 2**63, k, dtype=np.uint64)
    word = rng.integers(0, 2, length)
    sign = np.where(word[(hashes % np.uint64(length)).astype(np.int64)] == 0, 1.0, -1.0) if marked \
        else rng.choice([-1.0, 1.0], k)
    z = sign * rng.uniform(0.02, 0.2, k)
    wrong = rng.random(k) < 0.4
    z[wrong] = -sign[wrong] * rng.uniform(0.0, 0.05, int(wrong.sum()))
    empty = np.zeros((k, 3))
    return Analysis(np.arange(k), hashes, z, empty, np.zeros((k, 3, 3)), empty, np.ones(k), False, True)


@pytest.mark.parametrize("seed", range(6))
def test_agreement_tells_a_weak_mark_from_random_votes_over_every_length(seed: int) -> None:
    """The placement a detection reads is the one whose votes agree best within slots at any of
    the 256 lengths: random votes must not win at some long length, where few carriers share a slot
    (the raw hard-vote ratio did in 6 of 10 such draws, as on the beetle simplified by 50 %)."""
    lengths = sorted({codeword_length(n) for n in range(1, 257)})
    marked = detection.agreement([_geometric_reading(800, codeword_length(32), seed, True)], lengths)
    random = detection.agreement([_geometric_reading(800, codeword_length(32), seed + 100, False)], lengths)
    assert marked > 2 * random


def test_the_near_variant_reads_the_carriers_nearest_their_boundaries_only() -> None:
    """Half the carriers read the codeword at small ``|z| s``, the other half (far from their
    boundaries, as the moves an RMS budget leaves out) at random: every vote reads the codeword
    badly, the NEAR variant's votes (the nearest 0.4, centred, the others 0) read it exactly."""
    payload = np.array([1, 0, 1, 1, 0, 0, 1, 0, 1, 1, 0, 1], np.uint8)
    word = encode(KEY, payload)
    a = carriers_reading(word, 1400, 5)
    rng = np.random.default_rng(6)
    far = rng.random(len(a.z)) < 0.5
    z = np.where(far, rng.choice([-1.0, 1.0], len(a.z)) * rng.uniform(2.0, 4.0, len(a.z)), a.z)
    a = replace(a, z=z, scale=rng.uniform(0.5, 1.5, len(z)))
    (votes,) = _soft_values([a], detection.NEAR)
    d = np.abs(z) * a.scale
    voters = votes != 0
    assert voters.sum() == round(detection.NEAR_SHARE * len(z))
    assert d[voters].max() <= d[~voters].min() and not (far & voters).any()
    assert abs(votes.sum()) < 1e-9
    slots = assign_slots([a.slot_hash], len(word))[0]
    assert np.all((votes[voters] > 0) == (word[slots[voters]] == 0))
    # the interior view tries the variant (a view with boundaries: a crop)
    assert (detection.NEAR, None) in detection.view_variants(detection.INTERIOR, None)
    assert (detection.NEAR, None) not in detection.view_variants(detection.CONNECTIVITY, None)

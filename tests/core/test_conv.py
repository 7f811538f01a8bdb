"""core.conv: the rate-1/2 convolutional code, its batched Viterbi decoder and exact posteriors."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from core import conv


def test_the_encoder_is_the_standard_k7_code() -> None:
    """A single 1 gives the two generators' impulse responses, interleaved: 171 and 133 (octal)
    read from the oldest tap, then 6 zero tail steps end the trellis in state 0."""
    out = conv.encode(np.array([1], np.uint8)).reshape(-1, 2)
    assert len(out) == 1 + conv.TAIL
    g0 = int("".join(map(str, out[:, 0][::-1])), 2)
    g1 = int("".join(map(str, out[:, 1][::-1])), 2)
    assert (g0, g1) == (0o171, 0o133)
    assert conv.encode(np.zeros(5, np.uint8)).sum() == 0


def test_the_encoder_is_linear() -> None:
    rng = np.random.default_rng(0)
    a, b = rng.integers(0, 2, (2, 40)).astype(np.uint8)
    assert np.array_equal(conv.encode(a ^ b), conv.encode(a) ^ conv.encode(b))


@settings(max_examples=60, deadline=None)
@given(st.lists(st.lists(st.integers(0, 1), min_size=1, max_size=90), min_size=1, max_size=6),
       st.integers(0, 2**32 - 1))
def test_viterbi_corrects_what_the_free_distance_allows(messages: list[list[int]], seed: int) -> None:
    """Several trellises of different lengths decoded together: each message comes back exactly
    from hard votes with up to 4 flipped coded bits (free distance 10), wherever they are."""
    rng = np.random.default_rng(seed)
    llrs, truth = [], []
    for m in messages:
        bits = np.array(m, np.uint8)
        code = conv.encode(bits)
        flip = rng.choice(len(code), size=min(4, len(code)), replace=False)
        # spread the flips: two within one constraint span are what distance 10 covers at most
        code[flip[: 1 + len(code) // 40]] ^= 1
        llrs.append(1.0 - 2.0 * code)
        truth.append(bits)
    for got, want in zip(conv.viterbi(llrs), truth, strict=True):
        assert np.array_equal(got, want)


def test_posteriors_agree_with_viterbi_and_are_calibrated() -> None:
    """On clean input the posteriors give the message with certainty; on noisy input the bits
    reported with confidence c are right about c of the time (bins of 300 frames)."""
    rng = np.random.default_rng(1)
    m = rng.integers(0, 2, 64).astype(np.uint8)
    bits, conf = conv.posteriors(6.0 * (1.0 - 2.0 * conv.encode(m)))
    assert np.array_equal(bits, m) and (conf > 0.999).all()
    hits, confs = [], []
    for _ in range(300):
        m = rng.integers(0, 2, 64).astype(np.uint8)
        y = (1.0 - 2.0 * conv.encode(m)) + 0.9 * rng.standard_normal(conv.coded_length(64))
        bits, conf = conv.posteriors(2.0 * y / 0.81)
        hits.append(bits == m)
        confs.append(conf)
    hit, c = np.concatenate(hits), np.concatenate(confs)
    for lo, hi in ((0.5, 0.9), (0.9, 0.99), (0.99, 1.01)):
        sel = (c >= lo) & (c < hi)
        assert sel.sum() > 200
        assert abs(hit[sel].mean() - c[sel].mean()) < 0.05


def test_a_frame_reads_at_a_slot_snr_hamming_could_not() -> None:
    """The reason for the code: 8,000 carriers of per-carrier signal 0.18 (slot SNR 1.5 for a
    64-bit message) give the message back in at least 95 of 100 frames."""
    rng = np.random.default_rng(2)
    ok = 0
    for _ in range(100):
        m = rng.integers(0, 2, 64).astype(np.uint8)
        code = conv.encode(m)
        n = 8000 // len(code)
        sums = (1.0 - 2.0 * code) * 0.18 * n + np.sqrt(n) * rng.standard_normal(len(code))
        ok += np.array_equal(conv.viterbi([sums])[0], m)
    assert ok >= 95


@settings(max_examples=40, deadline=None)
@given(st.lists(st.integers(1, 9), min_size=1, max_size=7), st.integers(0, 2**32 - 1))
def test_viterbi_is_maximum_likelihood_in_a_batch_of_mixed_lengths(lengths: list[int], seed: int) -> None:
    """Against exhaustive search: every trellis of a batch of different lengths (they are aligned at
    their ends, each started in state 0 at its own step) gets the message whose codeword correlates
    best with its noisy LLRs."""
    rng = np.random.default_rng(seed)
    llrs = [rng.normal(0.0, 1.0, conv.coded_length(n)) for n in lengths]
    for n, y, got in zip(lengths, llrs, conv.viterbi(llrs), strict=True):
        every = (np.arange(2**n)[:, None] >> np.arange(n)[None, :]) & 1
        scores = [float(y @ (1.0 - 2.0 * conv.encode(m))) for m in every]
        assert np.array_equal(got, every[int(np.argmax(scores))])


@settings(max_examples=60, deadline=None)
@given(st.lists(st.integers(0, 120), min_size=1, max_size=9), st.integers(0, 2**32 - 1), st.booleans())
def test_a_batch_decodes_every_trellis_as_it_decodes_alone(lengths: list[int], seed: int, ties: bool) -> None:
    """The batch's trellises are computed longest first, each from the step it starts at, and traced
    back one by one: whatever the order of the lengths (repeats and empty messages included) and
    with tied metrics (small integer LLRs, zeros), each gets exactly the message it gets alone."""
    rng = np.random.default_rng(seed)
    if ties:
        llrs = [rng.integers(-2, 3, conv.coded_length(n)).astype(np.float64) for n in lengths]
    else:
        llrs = [rng.normal(0.0, 1.0, conv.coded_length(n)) for n in lengths]
    for n, y, got in zip(lengths, llrs, conv.viterbi(llrs), strict=True):
        alone = conv.viterbi([y])[0]
        assert got.dtype == np.uint8 and got.shape == (n,)
        assert np.array_equal(got, alone)

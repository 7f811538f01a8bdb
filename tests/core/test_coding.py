"""core.coding: CRC-32 framing, the convolutional code, keyed whitening, soft decoding, tail probabilities."""

from __future__ import annotations

import zlib

import numpy as np
import pytest

from core import coding
from core.coding import KEY_CODE_BITS


def test_lengths_of_the_frames() -> None:
    """Payload + CRC-32, zero-padded to a nibble, + 6 tail bits, at rate 1/2."""
    assert coding.codeword_length(None) == 2 * (KEY_CODE_BITS + 6) == 76
    lengths = [coding.codeword_length(n) for n in (1, 4, 5, 32, 256)]
    assert lengths == [2 * 42, 2 * 42, 2 * 46, 2 * 70, 2 * 294]
    assert [coding.message_length(n) for n in (1, 4, 5, 256)] == [36, 36, 40, 288]


def test_the_message_is_payload_crc_and_zero_padding() -> None:
    payload = np.array([1, 0, 1, 1, 1], np.uint8)
    msg = coding.message(payload)
    assert len(msg) == coding.message_length(5) == 40
    assert msg[:5].tolist() == payload.tolist()
    assert msg[5:37].tolist() == coding.crc_bits(payload).tolist()
    assert not msg[37:].any()


def test_crc_covers_the_length_and_the_bits() -> None:
    bits = np.array([1, 0, 1], np.uint8)
    expected = zlib.crc32(bytes([2, 0b10100000]))
    assert int(coding.bits_to_str(coding.crc_bits(bits)), 2) == expected
    assert not np.array_equal(coding.crc_bits(bits), coding.crc_bits(np.array([1, 0, 1, 0], np.uint8)))


def test_whitened_codeword_decodes_to_the_key_code() -> None:
    word = coding.encode("key", None)
    plain = word ^ coding.whitening("key", len(word))
    assert coding.ml_messages([1.0 - 2.0 * plain])[0].tolist() == coding.key_code("key").tolist()
    assert not np.array_equal(coding.whitening("key", 76), coding.whitening("other", 76))
    assert not coding.whitening("key", 76).flags.writeable
    code = coding.key_code("k")
    assert coding.bits_to_str(code) == coding.bits_to_str(coding.key_code(b"k")) and len(code) == 32


def test_soft_decoding_reports_how_sure_it_is() -> None:
    sure = coding.soft_decode(np.full(coding.codeword_length(None), 5.0))
    assert sure.bits.tolist() == [0] * KEY_CODE_BITS and (sure.confidence > 0.999).all()
    unsure = coding.soft_decode(np.zeros(coding.codeword_length(None)))
    assert np.allclose(unsure.confidence, 0.5)


def test_tail_probabilities_and_log_odds() -> None:
    assert [coding.binomial_tail(k, 2) for k in (0, 1, 2)] == [0.25, 0.75, 1.0]
    assert coding.binomial_tail(1, 32) == pytest.approx(33 / 2**32)
    assert coding.log_odds(0.5) == 0.0 and coding.log_odds(0.0) == coding.log_odds(1e-6) > 0


def test_the_compact_frame_carries_its_payload_whatever_the_free_bits() -> None:
    """Any choice of the free bits gives a codeword that reads back as the payload, with the CRC
    holding for its own length only; the keyed matrix is invertible."""
    from core.coding import (
        COMPACT_BITS,
        COMPACT_DATA,
        compact_codeword,
        compact_lengths,
        compact_mixing,
        compact_unmix,
    )

    t, inv = compact_mixing("compact key")
    assert np.array_equal(t.astype(np.int64) @ inv % 2, np.eye(COMPACT_BITS, dtype=np.int64))
    rng = np.random.default_rng(3)
    for n in (1, 17, 32, 48):
        payload = rng.integers(0, 2, n).astype(np.uint8)
        b0, d = compact_codeword("compact key", payload)
        assert d.shape == (COMPACT_BITS, COMPACT_DATA - n)
        for _ in range(3):
            r = rng.integers(0, 2, d.shape[1])
            frame = compact_unmix("compact key", b0 ^ (d.astype(np.int64) @ r % 2).astype(np.uint8))
            assert np.array_equal(frame[:n], payload) and np.array_equal(frame[n:COMPACT_DATA], r)
            assert compact_lengths(frame, list(range(1, 49))) == [n]
        # another key reads something else
        other = compact_unmix("another key", b0)
        assert compact_lengths(other, list(range(1, 49))) == []

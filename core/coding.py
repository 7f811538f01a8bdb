"""Payload framing: key-derived code, CRC-32, convolutional code, keyed whitening, soft decoding.

Frames
------
* key-derived (the paper's mode): a 32-bit code derived from the key, convolutionally coded
  (:mod:`core.conv`, rate 1/2, 6 tail bits) -> 76 bits.  The detector knows the code from the key
  and counts bit errors.
* explicit payload of 1-256 bits: ``payload + CRC-32(length, payload)``, zero-padded to a
  multiple of 4 (so that four lengths share a codeword length), convolutionally coded.  The CRC
  and the padding make a random match ~2**-32 per candidate.
* compact, for payloads of 1-:data:`COMPACT_MAX_PAYLOAD` bits on meshes with few carriers: the
  frame ``payload + free bits + CRC-32`` of :data:`COMPACT_BITS` bits times a keyed invertible
  matrix, without the convolutional code.  The embedder chooses the free bits so that the carriers
  it cannot move
  across their boundary already read what the codeword asks of them (a wet-paper code); every
  codeword bit depends on the free bits through the matrix, so any few dozen such carriers can be
  met.  The detector inverts the matrix and checks the CRC: 2**-32 per length tried.

The codeword is XORed with a keyed pseudo-random mask (whitening), so that without the key
the carriers' bits look like noise.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass
from functools import lru_cache
from math import comb, log

import numpy as np

from core import conv, gf2
from core.hashing import derive, derive_bytes

MAX_PAYLOAD_BITS = 256
KEY_CODE_BITS = 32
CRC_BITS = 32

#: the bit positions of a 32-bit word, most significant first
_WORD_SHIFTS = np.arange(31, -1, -1, dtype=np.uint64)


def _word_bits(v: int) -> np.ndarray:
    """The 32 bits of ``v`` (0 <= v < 2**32), most significant first, uint8 (one shift of an
    array: a detection checks the CRC of every payload length of every decoded candidate)."""
    return ((np.uint64(v) >> _WORD_SHIFTS) & np.uint64(1)).astype(np.uint8)


def bits_to_str(bits: np.ndarray) -> str:
    return "".join("1" if b else "0" for b in np.asarray(bits).ravel())


def key_code(key: str | bytes) -> np.ndarray:
    """The 32-bit code derived from the key (used when no payload is given)."""
    v = derive(key, "meshmark-code") & 0xFFFFFFFF
    return _word_bits(v)


def crc_bits(bits: np.ndarray) -> np.ndarray:
    """CRC-32 over the payload length and bits, as 32 bits."""
    data = bytes([len(bits) - 1]) + np.packbits(bits).tobytes()
    v = zlib.crc32(data)
    return _word_bits(v)


def message_length(n_payload: int | None) -> int:
    """Bits the code carries for a payload of ``n_payload`` bits: payload + CRC-32, zero-padded to a
    multiple of 4 (``None``: the 32-bit key-derived code)."""
    if n_payload is None:
        return KEY_CODE_BITS
    return 4 * -(-(n_payload + CRC_BITS) // 4)


def message(payload: np.ndarray) -> np.ndarray:
    """The coded message of ``payload``: the payload, its CRC-32 and the zero padding."""
    body = np.concatenate([np.asarray(payload, np.uint8), crc_bits(payload)])
    return np.concatenate([body, np.zeros(message_length(len(payload)) - len(body), np.uint8)])


def codeword_length(n_payload: int | None) -> int:
    """Codeword bits for a payload of ``n_payload`` bits (``None``: the key-derived code)."""
    return conv.coded_length(message_length(n_payload))


@lru_cache(maxsize=1024)
def whitening(key: str | bytes, length: int) -> np.ndarray:
    """Keyed mask XORed onto a codeword of ``length`` bits (read-only array)."""
    raw = derive_bytes(key, f"meshmark-wht{length}", -(-length // 8))
    mask = np.unpackbits(np.frombuffer(raw, np.uint8))[:length]
    mask.flags.writeable = False
    return mask


def encode(key: str | bytes, payload: np.ndarray | None) -> np.ndarray:
    """Whitened codeword for ``payload`` (``None``: the key-derived 32-bit code)."""
    cw = conv.encode(key_code(key) if payload is None else message(payload))
    return cw ^ whitening(key, len(cw))


#: compact frame: codeword bits, the longest payload, and the bits before the CRC (payload + free)
COMPACT_BITS = 128
COMPACT_MAX_PAYLOAD = 48
COMPACT_DATA = COMPACT_BITS - CRC_BITS
#: the compact frame is embedded, and tried by the detector, only below this many carriers (8
#: copies of its codeword: above, the standard frame has room to spare)
COMPACT_BELOW = 8 * COMPACT_BITS
#: slots per hash bucket of the compact frame (:func:`core.slots.bucketed_slots`)
COMPACT_BUCKET = 8


def compact_crc(n: int, data: np.ndarray) -> np.ndarray:
    """CRC-32 over a compact frame's payload length ``n`` and its data bits (payload + free)."""
    raw = b"\xc7" + bytes([n - 1]) + np.packbits(data).tobytes()
    v = zlib.crc32(raw)
    return _word_bits(v)


@lru_cache(maxsize=256)
def compact_mixing(key: str | bytes) -> tuple[np.ndarray, np.ndarray]:
    """The keyed invertible ``(COMPACT_BITS, COMPACT_BITS)`` 0/1 matrix ``T`` of the compact frame
    (codeword = ``T frame`` XOR whitening) and its inverse, both read-only."""
    rng = np.random.default_rng(derive(key, "meshmark-mix"))
    while True:  # a random square matrix over GF(2) is invertible with probability ~0.29
        t = rng.integers(0, 2, (COMPACT_BITS, COMPACT_BITS)).astype(np.uint8)
        inv = gf2.inverse(t)
        if inv is not None:
            break
    t.flags.writeable = False
    inv.flags.writeable = False
    return t, inv


def compact_whitening(key: str | bytes) -> np.ndarray:
    """The compact codeword's keyed mask (not the standard one of the same length)."""
    return whitening(b"meshmark-compact\0" + (key.encode() if isinstance(key, str) else key), COMPACT_BITS)


def compact_frame(payload: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The frame of ``payload`` as an affine function of its free bits ``r``:
    ``frame(r) = f0 XOR F r`` (mod 2).

    Returns
    -------
    f0 : (COMPACT_BITS,) uint8 ndarray
        The frame with every free bit 0.
    F : (COMPACT_BITS, COMPACT_DATA - n) uint8 ndarray
        Column ``j``: what setting free bit ``j`` changes (the bit itself and the CRC's share).
    """
    n = len(payload)
    m = COMPACT_DATA - n
    data = np.concatenate([np.asarray(payload, np.uint8), np.zeros(m, np.uint8)])
    f0 = np.concatenate([data, compact_crc(n, data)])
    cols = np.zeros((COMPACT_BITS, m), np.uint8)
    for j in range(m):  # a CRC is affine in its input: each free bit adds a fixed pattern
        d = data.copy()
        d[n + j] = 1
        cols[:, j] = np.concatenate([d, compact_crc(n, d)]) ^ f0
    return f0, cols


def compact_codeword(key: str | bytes, payload: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The de-whitened compact codeword of ``payload`` as ``b0 XOR D r`` over its free bits ``r``:
    returns ``(b0, D)``; the embedder's (whitened) codeword is ``b XOR compact_whitening(key)``."""
    t, _ = compact_mixing(key)
    f0, cols = compact_frame(payload)
    return (t.astype(np.int64) @ f0 % 2).astype(np.uint8), (t.astype(np.int64) @ cols % 2).astype(np.uint8)


def compact_unmix(key: str | bytes, bits: np.ndarray) -> np.ndarray:
    """The frame of a de-whitened compact codeword."""
    _, inv = compact_mixing(key)
    return (inv.astype(np.int64) @ np.asarray(bits, np.int64) % 2).astype(np.uint8)


def compact_lengths(frame: np.ndarray, lengths: list[int]) -> list[int]:
    """The payload lengths among ``lengths`` whose CRC holds in a compact ``frame``."""
    data, crc = frame[:COMPACT_DATA], frame[COMPACT_DATA:]
    return [n for n in lengths if np.array_equal(compact_crc(n, data), crc)]


@dataclass(frozen=True)
class Decoded:
    """Soft-decoded message bits (before the CRC split) with per-bit posterior confidence."""

    bits: np.ndarray        # (n,) uint8
    confidence: np.ndarray  # (n,) float64 in [0.5, 1]


def ml_messages(llrs: list[np.ndarray]) -> list[np.ndarray]:
    """Maximum-likelihood messages of several codewords' per-slot LLRs (0 for an empty slot):
    :func:`core.conv.viterbi`, every candidate length in one pass."""
    return conv.viterbi(llrs)


def soft_decode(llr: np.ndarray) -> Decoded:
    """Exact per-bit posteriors of one codeword's calibrated per-slot log-likelihood ratios
    (``log P(bit=0)/P(bit=1)`` of every de-whitened slot, 0 for an empty one): the most probable
    message bits and the probability of each (:func:`core.conv.posteriors`)."""
    bits, conf = conv.posteriors(llr)
    return Decoded(bits, conf)


def binomial_tail(errors: int, n: int) -> float:
    """P(X <= errors) for X ~ Binomial(n, 1/2): chance that random bits match this well."""
    return float(sum(comb(n, k) for k in range(errors + 1)) / 2.0**n)


def log_odds(p: float) -> float:
    p = min(max(p, 1e-6), 1 - 1e-6)
    return log((1 - p) / p)

"""Keyed, vectorised 64-bit hashing (splitmix64 finaliser) and key derivation."""

from __future__ import annotations

import hashlib

import numpy as np

_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)


def mix64(x: np.ndarray) -> np.ndarray:
    """Bijective avalanche mix of uint64 values (splitmix64 finaliser), element-wise."""
    with np.errstate(over="ignore"):
        z = np.asarray(x, dtype=np.uint64) + _GOLDEN
        z = (z ^ (z >> np.uint64(30))) * _M1
        z = (z ^ (z >> np.uint64(27))) * _M2
        return z ^ (z >> np.uint64(31))


def combine(a: np.ndarray, b: np.ndarray | int) -> np.ndarray:
    """Order-dependent hash of two uint64 arrays (or an array and a scalar)."""
    with np.errstate(over="ignore"):
        return mix64(np.asarray(a, dtype=np.uint64) ^ mix64(np.asarray(b, dtype=np.uint64) + _M1))


def key_bytes(key: str | bytes) -> bytes:
    """The key as bytes (str keys are UTF-8 encoded)."""
    return key.encode("utf-8") if isinstance(key, str) else bytes(key)


def derive(key: str | bytes, purpose: str) -> int:
    """A 64-bit integer derived from the key for one purpose (domain-separated BLAKE2b)."""
    h = hashlib.blake2b(key_bytes(key), digest_size=8, person=purpose.encode()[:16].ljust(16, b"\0"))
    return int.from_bytes(h.digest(), "little")


def derive_bytes(key: str | bytes, purpose: str, n: int) -> bytes:
    """``n`` pseudo-random bytes derived from the key for one purpose (BLAKE2b in counter mode)."""
    out = bytearray()
    counter = 0
    while len(out) < n:
        h = hashlib.blake2b(key_bytes(key) + counter.to_bytes(8, "little"), digest_size=64,
                            person=purpose.encode()[:16].ljust(16, b"\0"))
        out += h.digest()
        counter += 1
    return bytes(out[:n])


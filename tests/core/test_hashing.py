"""core.hashing: splitmix64 on whole arrays, and key derivation."""

from __future__ import annotations

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from core.hashing import combine, derive, derive_bytes, finalise64, key_bytes, mix64

GOLDEN = 0x9E3779B97F4A7C15
MASK = 2**64 - 1


def splitmix64(x: int) -> int:
    """The reference, one integer at a time (Steele, Lea and Flood 2014)."""
    z = (x + GOLDEN) & MASK
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & MASK
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & MASK
    return z ^ (z >> 31)


def test_mix64_is_splitmix64() -> None:
    # the generator's first three outputs from state 0, as published
    states = np.array([0, GOLDEN, 2 * GOLDEN & MASK], np.uint64)
    assert [int(v) for v in mix64(states)] == [0xE220A8397B1DCDAF, 0x6E789E6AA1B965F4, 0x06C45D188009454F]


@given(st.lists(st.integers(0, MASK), min_size=1, max_size=50))
def test_mix64_matches_the_reference_element_by_element(values: list[int]) -> None:
    assert [int(v) for v in mix64(np.array(values, np.uint64))] == [splitmix64(v) for v in values]


def test_finalise64_works_in_place_and_is_a_bijection() -> None:
    x = np.arange(1 << 16, dtype=np.uint64)
    y = finalise64(x)
    assert y is x  # in place
    assert np.unique(y).size == 1 << 16
    assert int(finalise64(np.array([0], np.uint64))[0]) == 0  # the finaliser alone fixes 0


def test_combine_depends_on_the_order() -> None:
    a, b = np.array([1, 2], np.uint64), np.array([2, 1], np.uint64)
    assert not np.array_equal(combine(a, b), combine(b, a))
    assert np.array_equal(combine(a, 7), combine(a, np.array([7, 7], np.uint64)))


def test_derivation_is_per_key_and_purpose() -> None:
    assert derive("k", "p") == derive(b"k", "p")
    assert len({derive("k", "p"), derive("k", "q"), derive("K", "p")}) == 3
    assert key_bytes("clé") == "clé".encode()
    long = derive_bytes("k", "p", 200)
    assert len(long) == 200 and derive_bytes("k", "p", 10) == long[:10]
    assert derive_bytes("k", "q", 10) != long[:10]


def test_a_large_array_is_finalised_in_chunks_as_a_whole_array_pass_does() -> None:
    from core.hashing import CHUNK, _finalise

    x = np.random.default_rng(5).integers(0, 2**63, 3 * CHUNK + 17, dtype=np.uint64)
    whole = _finalise(x.copy())
    chunked = finalise64(x.copy())
    assert np.array_equal(chunked, whole)
    assert np.array_equal(mix64(x), _finalise(x + np.uint64(0x9E3779B97F4A7C15)))
    # not contiguous: one pass over the strided view, in place
    y = x.copy()
    finalise64(y[::2])
    assert np.array_equal(y[::2], whole[::2]) and np.array_equal(y[1::2], x[1::2])

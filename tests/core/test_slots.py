"""core.slots: which codeword bit each carrier holds."""

from __future__ import annotations

import numpy as np

from core.slots import HASHED_FROM, OWN_RANKING_FROM, assign_slots, dense_rank, own_copy, ranked_by_default


def test_many_carriers_take_hash_mod_length() -> None:
    hashes = [np.array([7, 8, 9, 2**64 - 1], np.uint64), np.array([14], np.uint64)]
    slots = assign_slots(hashes, 7, ranked=False)
    assert [s.tolist() for s in slots] == [[0, 1, 2, (2**64 - 1) % 7], [0]]


def test_few_carriers_deal_every_slot_once() -> None:
    """L carriers with distinct hashes cover the L slots, in the order of their hashes."""
    hashes = [np.array([50, 10, 40], np.uint64), np.array([30, 20], np.uint64)]
    slots = assign_slots(hashes, 5, ranked=True)
    assert [s.tolist() for s in slots] == [[4, 0, 3], [2, 1]]
    # the order of the parts does not change any carrier's slot
    assert [s.tolist() for s in assign_slots(hashes[::-1], 5, ranked=True)] == [[2, 1], [4, 0, 3]]


def test_equal_hashes_share_a_slot() -> None:
    assert dense_rank(np.array([9, 3, 9, 5], np.uint64)).tolist() == [2, 0, 2, 1]
    slots = assign_slots([np.array([9, 3, 9, 5], np.uint64)], 2, ranked=True)
    assert slots[0].tolist() == [0, 0, 0, 1]


def test_the_embedders_choice_and_a_part_ranked_on_its_own() -> None:
    length = 4
    assert ranked_by_default(HASHED_FROM * length - 1, length)
    assert not ranked_by_default(HASHED_FROM * length, length)
    big = np.arange(100, 100 + int(OWN_RANKING_FROM * length), dtype=np.uint64)  # 6 distinct hashes
    small = np.array([1, 2], np.uint64)
    assert own_copy(big, length) and not own_copy(small, length)
    assert not own_copy(np.full(10, 5, np.uint64), length)  # many carriers, one distinct label
    slots = assign_slots([big, small], length, ranked=True)
    assert slots[0].tolist() == [0, 1, 2, 3, 0, 1]  # ranked alone: decodes when extracted
    assert slots[1].tolist() == [0, 1]  # the small part is ranked with the other small ones


def test_a_cache_serves_every_length() -> None:
    hashes = [np.array([50, 10, 40, 30, 20], np.uint64)]
    cache: dict[object, object] = {}
    for length in (2, 3, 5):
        assert np.array_equal(assign_slots(hashes, length, True, cache)[0],
                              assign_slots(hashes, length, True)[0])


def test_bucketed_slots_move_only_within_the_bucket_of_a_carrier_that_comes_or_goes() -> None:
    from core.slots import bucketed_slots

    rng = np.random.default_rng(11)
    h = rng.integers(0, 2**64 - 1, 120, dtype=np.uint64, endpoint=True)  # keyed hashes use all 64 bits
    (full,) = bucketed_slots([h], 128, 8)
    assert full.min() >= 0 and full.max() < 128
    assert np.unique(full).size >= 0.75 * 120  # buckets fill unevenly, but most slots are used
    (fewer,) = bucketed_slots([h[1:]], 128, 8)
    moved = np.flatnonzero(full[1:] != fewer)
    assert moved.size and set(full[1:][moved] // 8) == {full[0] // 8}
    # parts are ranked together: splitting the array changes nothing
    a, b = bucketed_slots([h[:50], h[50:]], 128, 8)
    assert np.array_equal(np.concatenate([a, b]), full)

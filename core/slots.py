"""Which codeword bit each carrier holds (its *slot*), from the carriers' keyed label hashes.

Many carriers (at least :data:`HASHED_FROM` per slot over the file): ``slot = hash mod L``,
purely local, so a cropped piece or one mesh of the file still decodes.  Few carriers: the
carriers are ranked by hash and deal the slots in turn (dense ranks, so equal hashes share a
slot; the rank does not depend on the order of the parts), which covers every slot as soon as
there are ``L`` carriers, as the paper's small models need.  In a file of several meshes, a mesh
with at least :data:`OWN_RANKING_FROM` ``x L`` distinct hashes is ranked on its own, so that it
decodes when extracted; the smaller ones are ranked together.

The embedder uses :func:`ranked_by_default`; the detector also tries the other assignment, since
cropping changes the number of carriers.
"""

from __future__ import annotations

from typing import Any

import numpy as np

#: carriers per slot from which slots are assigned by hash rather than by rank
HASHED_FROM = 4
#: carriers per slot from which one part of a multi-mesh file is ranked on its own
OWN_RANKING_FROM = 1.5


def ranked_by_default(carriers: int, length: int) -> bool:
    """The embedder's choice: rank when there are fewer than :data:`HASHED_FROM` carriers per slot."""
    return carriers < HASHED_FROM * length


def assign_slots(slot_hashes: list[np.ndarray], length: int, ranked: bool | None = None,
                 cache: dict[Any, Any] | None = None) -> list[np.ndarray]:
    """Codeword slot of every carrier of every part.

    Parameters
    ----------
    slot_hashes : list of (k_i,) uint64 ndarray
        Keyed label hash of each carrier, one array per mesh part.
    length : int
        Codeword length ``L``.
    ranked : bool, optional
        Force the ranked (``True``) or hashed (``False``) assignment; ``None``:
        :func:`ranked_by_default` over all parts.
    cache : dict, optional
        Reused across calls on the same ``slot_hashes`` (the ranks do not depend on ``length``).

    Returns
    -------
    list of (k_i,) int64 ndarray
        Slots in ``[0, length)``.
    """
    cache = {} if cache is None else cache
    if ranked is None:
        ranked = ranked_by_default(sum(len(h) for h in slot_hashes), length)
    if not ranked:
        return [(h % np.uint64(length)).astype(np.int64) for h in slot_hashes]
    if "distinct" not in cache:
        cache["distinct"] = [np.unique(h).size for h in slot_hashes]
    distinct = cache["distinct"]
    out = [np.zeros(0, np.int64) for _ in slot_hashes]
    small = []
    for k, h in enumerate(slot_hashes):
        if len(h) >= OWN_RANKING_FROM * length and distinct[k] >= OWN_RANKING_FROM * length:
            if ("own", k) not in cache:
                cache[("own", k)] = dense_rank(h)
            out[k] = cache[("own", k)] % length
        elif len(h):
            small.append(k)
    if small:
        group = ("joint", tuple(small))
        if group not in cache:
            cache[group] = dense_rank(np.concatenate([slot_hashes[k] for k in small]))
        slots = cache[group] % length
        bounds = np.cumsum([len(slot_hashes[k]) for k in small])[:-1]
        for k, part in zip(small, np.split(slots, bounds), strict=True):
            out[k] = part
    return out


def bucketed_slots(slot_hashes: list[np.ndarray], length: int, per_bucket: int) -> list[np.ndarray]:
    """Slots of the compact frame: the high bits of a carrier's hash pick one of
    ``length // per_bucket`` buckets, its dense rank among the bucket's hashes its slot there
    (mod ``per_bucket``).

    A carrier that appears or disappears (a regular mesh selects slightly different carriers after
    every move) shifts the slots of its own bucket only, where a rank over all carriers shifts
    every later one; buckets fill unevenly, so some slots stay empty (about 13 % at 8 slots per
    bucket and one carrier per slot, against 36 % with hashed slots and ~0 ranked).

    Returns
    -------
    list of (k_i,) int64 ndarray
        Slots in ``[0, length)``, one array per part (parts are ranked together).
    """
    h = np.concatenate(slot_hashes) if slot_hashes else np.zeros(0, np.uint64)
    buckets = length // per_bucket
    b = ((h >> np.uint64(32)) * np.uint64(buckets)) >> np.uint64(32)
    order = np.lexsort((h, b))
    hs, bs = h[order], b[order]
    new = np.ones(len(hs), bool)
    new[1:] = (hs[1:] != hs[:-1]) | (bs[1:] != bs[:-1])
    dense = np.cumsum(new) - 1
    start = np.ones(len(hs), bool)
    start[1:] = bs[1:] != bs[:-1]
    base = np.maximum.accumulate(np.where(start, dense, 0)) if len(hs) else dense
    slots = np.empty(len(h), np.int64)
    slots[order] = bs.astype(np.int64) * per_bucket + (dense - base) % per_bucket
    return np.split(slots, np.cumsum([len(x) for x in slot_hashes])[:-1]) if slot_hashes else []


def own_copy(slot_hash: np.ndarray, length: int) -> bool:
    """A part has room for a copy of its own: enough *distinct* hashes (symmetric parts repeat
    labels, and equal labels share a slot)."""
    need = OWN_RANKING_FROM * length
    return len(slot_hash) >= need and np.unique(slot_hash).size >= need


def dense_rank(values: np.ndarray) -> np.ndarray:
    """Rank of each value among the distinct values (equal values share a rank), int64."""
    _, rank = np.unique(values, return_inverse=True)
    return rank.ravel().astype(np.int64)

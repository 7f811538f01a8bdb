"""Which codeword lengths a mesh's carriers hold whatever the payload: capacity's margin.

Whether a payload embeds on a coarse mesh depends on its bits (core/README.md, "Capacity says what
embeds"): within the displacement ceiling some carriers cannot cross their boundary (*wet*
carriers), so they read their own side whatever the codeword asks; a slot whose wet carriers
outvote the others reads wrong when it is asked the value they cannot hold (a *fragile* slot), and
which value each slot is asked is the payload's.  A payload fails when the fragile slots it asks
wrong are more, or closer together, than the convolutional code corrects.

What each carrier reads when asked 0 and when asked 1 does not depend on the payload (carriers are
an independent set: one carrier's move changes no other carrier's boundary), and two probe
embeddings measure it (:class:`Reach`).  The slots of a codeword length do not depend on the
payload either, so for every length the decoder can be run on what the carriers would read for any
codeword, without embedding it: :func:`holds` asks whether the detector's first two variants decode
random codewords in which every fragile slot is asked the value it cannot hold with probability
:data:`STRESS` (a payload asks it with probability 1/2), a margin over the payload-dependent edge.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core import conv
from core.analysis import Analysis
from core.detection import adaptive_threshold, median
from core.slots import assign_slots, ranked_by_default

#: share of the fragile slots asked the value they cannot hold in the stressed codewords (a payload's
#: codeword asks it half the time); bench capacity-keys, core/README.md
STRESS = 0.75
#: stressed codewords decoded per codeword length
SAMPLES = 32


@dataclass(frozen=True)
class Reach:
    """What every connectivity carrier reads when the embedder asks it for 0 and for 1.

    ``hashes``: the carriers' slot hashes, one array per part (what the slot assignment takes);
    ``z0``, ``z1``: their statistics (> 0 reads 0) after an embedding that asked every carrier for 0,
    for 1, all parts concatenated."""

    hashes: list[np.ndarray]
    z0: np.ndarray
    z1: np.ndarray

    @property
    def carriers(self) -> int:
        return len(self.z0)


def reach(asked0: list[Analysis], asked1: list[Analysis]) -> Reach:
    """:class:`Reach` from the detector's view after the two probe embeddings (every carrier asked
    for 0, then 1).  A carrier of the first that the second does not select (the tie-break of a
    large mesh follows the moves) counts as reading 0 when asked 1: wet for 1."""
    z1s = []
    for a, b in zip(asked0, asked1, strict=True):
        z1 = np.full(len(a.carriers), 1.0)
        _, ia, ib = np.intersect1d(a.carriers, b.carriers, assume_unique=True, return_indices=True)
        z1[ia] = b.z[ib]
        z1s.append(z1)
    z0 = np.concatenate([a.z for a in asked0]) if asked0 else np.zeros(0)
    return Reach([a.slot_hash for a in asked0], z0, np.concatenate(z1s) if z1s else np.zeros(0))


def _adaptive(z: np.ndarray) -> np.ndarray:
    """The detector's adaptive votes (:func:`core.detection._soft_values`, one part, no muted carrier)."""
    zc = z - adaptive_threshold(z)
    return np.clip(zc / (median(np.abs(zc)) or 1.0), -1.0, 1.0)


def _decodes(slots: np.ndarray, L: int, asked: np.ndarray, r: Reach,
             adaptive: tuple[bool, ...]) -> np.ndarray:
    """Per stressed codeword (rows of ``asked``: the raw bit each slot is asked), whether one of the
    vote variants ``adaptive`` (False: hard votes at the embedder's boundary, True: adaptive) decodes
    it.  By the code's linearity the decoder reads the de-whitened slot sums relative to the truth,
    and succeeds when it returns the zero message."""
    t = len(asked)
    per = asked[:, slots]
    z = np.where(per == 0, r.z0, r.z1)
    sign = np.where(asked == 0, 1.0, -1.0)
    rows = (np.arange(t)[:, None] * L + slots).ravel()
    ok = np.zeros(t, bool)
    for soft in adaptive:
        votes = np.stack([_adaptive(row) for row in z]) if soft else np.where(z > 0, 1.0, -1.0)
        votes = votes - votes.mean(axis=1, keepdims=True)
        sums = np.bincount(rows, votes.ravel(), minlength=t * L).reshape(t, L) * sign
        # ties count against the truth
        decoded = conv.viterbi(list(sums - 1e-9))
        ok |= np.array([not m.any() for m in decoded])
    return ok


def holds(r: Reach, L: int, seed: int = 0, stress: float = STRESS, samples: int = SAMPLES,
          ranked: bool = True) -> bool:
    """Whether every one of ``samples`` stressed codewords of length ``L`` decodes, with the
    embedder's slot assignment (hard or adaptive votes) or with the other one, which it tries last
    (adaptive votes: the detector reads the forced assignment with those only).  ``ranked=False``:
    with hashed slots only (a selection that moves under the embedding shifts ranked slots)."""
    if r.carriers < L:
        return False
    rng = np.random.default_rng([seed, L])
    default = ranked_by_default(r.carriers, L)
    tries = ((default, (False, True)), (not default, (True,)))
    for rank, adaptive in tries if ranked else [t for t in tries if not t[0]]:
        slots = np.concatenate(assign_slots(r.hashes, L, rank))
        count = np.bincount(slots, minlength=L)
        h0, h1 = np.where(r.z0 > 0, 1.0, -1.0), np.where(r.z1 > 0, 1.0, -1.0)
        m = 0.5 * float(h0.mean() + h1.mean())
        # the value a slot cannot hold (hard votes centred on the mean of a balanced codeword), -1: none
        wrong0 = np.bincount(slots, h0, minlength=L) - count * m <= 0
        wrong1 = -(np.bincount(slots, h1, minlength=L) - count * m) <= 0
        fragile = np.where(wrong0 & ~wrong1, 0, np.where(wrong1 & ~wrong0, 1, -1))
        asked = rng.integers(0, 2, (samples, L))
        biased = np.where(rng.random((samples, L)) < stress, fragile, 1 - fragile)
        asked = np.where(fragile >= 0, biased, asked)
        if _decodes(slots, L, asked, r, adaptive).all():
            return True
    return False

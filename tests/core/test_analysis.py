"""core.analysis: the statistic of each method on hand-made boundaries, and the view of a mesh."""

from __future__ import annotations

import numpy as np
import pytest

from core.analysis import TIE_BREAK_FROM, analyse, analyse_methods, statistic
from core.tolerances import TOL
from tests.core.meshes import irregular_sphere, similarity

#: one carrier at distance 0.2 from its neighbours' mean along e1, Sigma = diag(0.01, 1, 1), s = 1
V, MU = np.array([[0.2, 0.0, 0.0]]), np.zeros((1, 3))
AXES, LAM, SCALE = np.eye(3)[None], np.array([[0.01, 1.0, 1.0]]), np.ones(1)


def test_planes_statistic_is_the_distance_beyond_the_planes() -> None:
    # tau = max(sqrt(0.01), plane_floor * s) = 0.1
    assert statistic("planes", V, MU, AXES, LAM, SCALE) == pytest.approx([0.2 - 0.1])
    # a flat ring (l1 = 0): the floor keeps a margin of plane_floor * s
    assert statistic("planes", V, MU, AXES, np.array([[0.0, 1, 1]]), SCALE) == pytest.approx(
        [0.2 - TOL.plane_floor])


def test_ellipsoid_statistic_is_the_distance_to_the_ellipsoid_along_e1() -> None:
    # Mahalanobis radius 0.2 / 0.1 = 2; (2 - K) * sqrt(l1) / s
    assert statistic("ellipsoids", V, MU, AXES, LAM, SCALE) == pytest.approx([(2 - TOL.radius) * 0.1])
    inside = statistic("ellipsoids", V * 0.1, MU, AXES, LAM, SCALE)
    assert inside[0] < 0  # reads bit 1


def test_both_methods_share_the_carriers() -> None:
    v, f = irregular_sphere(1500, 2)
    views = analyse_methods(v, f, "key", ["ellipsoids", "planes"])
    e, p = views["ellipsoids"], views["planes"]
    assert np.array_equal(e.carriers, p.carriers) and np.array_equal(e.slot_hash, p.slot_hash)
    assert np.allclose(e.lam, p.lam + TOL.alpha * (p.scale**2)[:, None])
    assert 0.15 * len(v) < len(p.carriers) < 0.3 * len(v)
    with pytest.raises(ValueError, match="method"):
        analyse_methods(v, f, "key", ["spheres"])


def test_a_similarity_transform_changes_no_statistic() -> None:
    v, f = irregular_sphere(1500, 4)
    before = analyse(v, f, "key", "ellipsoids")
    v2, f2 = similarity(v, f, np.random.default_rng(5))
    after = analyse(v2, f2, "key", "ellipsoids")
    order = np.argsort(before.slot_hash), np.argsort(after.slot_hash)
    assert np.array_equal(before.slot_hash[order[0]], after.slot_hash[order[1]])
    assert np.allclose(before.z[order[0]], after.z[order[1]], atol=1e-9)


def test_another_key_chooses_other_carriers() -> None:
    v, f = irregular_sphere(1500, 6)
    a, b = analyse(v, f, "one", "planes"), analyse(v, f, "two", "planes")
    assert not np.array_equal(a.carriers, b.carriers)


@pytest.mark.parametrize("method", ["ellipsoids", "planes"])
def test_reanalysed_equals_a_fresh_analysis_after_moves(method: str) -> None:
    # the embedder's state: an analysis at the original positions whose moved carriers were read
    # again where they went; then some non-carriers move too (geometric carriers next to them) and
    # the priorities of a few neighbours overtake their carrier's (what the tie-break's moves do):
    # the selection made again must be analyse's, array for array
    from core.analysis import prepare, priorities, reanalysed
    from core.embedding import _restate

    v0, f = irregular_sphere(6000, 5)
    (adj, labels), = prepare([v0], [f])
    prev = analyse(v0, f, "key", method, adj=adj, labels=labels)
    rng = np.random.default_rng(3)
    v = v0.copy()
    carriers = rng.choice(len(prev.carriers), len(prev.carriers) // 2, replace=False)
    v[prev.carriers[carriers]] += rng.normal(0, 2e-3, (len(carriers), 3))
    _restate(prev, v, carriers, method, TOL)
    others = np.setdiff1d(np.arange(len(v)), prev.carriers)
    others = rng.choice(others, 200, replace=False)
    v[others] += rng.normal(0, 2e-3, (200, 3))
    moved = np.any(v != v0, axis=1)
    prio = priorities(v, adj, labels, "key")
    for c in rng.choice(prev.carriers, 40, replace=False):
        prio[adj.indices[adj.indptr[c]]] = prio[c] + np.uint64(1)
    got = reanalysed(prev, v, adj, labels, "key", method, prio, moved)
    want = analyse(v, f, "key", method, adj=adj, labels=labels, prio=prio)
    assert not np.array_equal(got.carriers, prev.carriers)  # the selection did change
    for name in ("carriers", "slot_hash", "z", "mu", "axes", "lam", "scale", "signed"):
        assert np.array_equal(getattr(got, name), getattr(want, name)), name


def test_tied_pairs_decide_the_order_of_priorities_that_differ_in_their_tie_break() -> None:
    # priorities of the same labels at other positions differ only in their low TIE_BITS: only
    # neighbours of equal label hashes can be ordered differently, whatever the low bits
    from core.analysis import prepare, same_order, tied_pairs
    from core.sync import TIE_BITS

    v, f = irregular_sphere(3000, 4)
    (adj, _), = prepare([v], [f])
    rng = np.random.default_rng(2)
    low = np.uint64((1 << TIE_BITS) - 1)
    outcomes = set()
    for trial in range(40):
        high = rng.integers(0, 6, len(v)).astype(np.uint64) << np.uint64(TIE_BITS)  # many ties
        before = high | rng.integers(0, 1 << TIE_BITS, len(v)).astype(np.uint64)
        after = before.copy()
        change = rng.random(len(v)) < (0.001 if trial % 2 else 0.2)
        fresh = rng.integers(0, 1 << TIE_BITS, int(change.sum())).astype(np.uint64)
        after[change] = high[change] | (fresh & low)
        want = same_order(before, after, adj)
        assert same_order(before, after, adj, tied_pairs(before, adj)) == want
        outcomes.add(want)
    assert outcomes == {True, False}


def _grid_with_coarse_columns(nx: int, ny: int, coarse_from: int, step: float = 6.0
                              ) -> tuple[np.ndarray, np.ndarray]:
    """A bumpy height-field grid whose columns from ``coarse_from`` on are ``step`` times wider."""
    xs = np.cumsum(np.where(np.arange(nx) < coarse_from, 1.0, step))
    gx, gy = np.meshgrid(xs, np.arange(ny, dtype=float), indexing="ij")
    rng = np.random.default_rng(3)
    v = np.column_stack([gx.ravel(), gy.ravel(), 0.05 * rng.standard_normal(nx * ny)])
    i = np.arange(nx - 1)[:, None] * ny + np.arange(ny - 1)[None, :]
    a, b, c, d = i.ravel(), i.ravel() + ny, i.ravel() + ny + 1, i.ravel() + 1
    return v, np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])


@pytest.mark.parametrize(("nx", "coarse_carriers"), [(60, False), (40, True)])
def test_rings_too_coarse_for_the_budget_carry_nothing_on_large_meshes(nx: int,
                                                                       coarse_carriers: bool) -> None:
    """Rings about 3 x the median scale: no carrier on a mesh of >= TIE_BREAK_FROM vertices (the
    embedder cannot afford their moves; TOL.max_scale), carriers below that size (max_scale_small)."""
    ny, coarse_from = 40, 3 * nx // 4
    v, f = _grid_with_coarse_columns(nx, ny, coarse_from)
    assert (len(v) >= TIE_BREAK_FROM) != coarse_carriers
    a = analyse(v, f, "k", "planes")
    inner_coarse = v[a.carriers, 0] > v[(coarse_from + 1) * ny, 0]
    ratio = a.scale / np.median(a.scale)
    assert bool(inner_coarse.any()) == coarse_carriers
    assert ratio.max() <= (TOL.max_scale_small if coarse_carriers else TOL.max_scale)
    if coarse_carriers:
        assert ratio[inner_coarse].min() > TOL.max_scale  # they are the ones the large mesh drops

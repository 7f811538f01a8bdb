"""core.analysis: the statistic of each method on hand-made boundaries, and the view of a mesh."""

from __future__ import annotations

import numpy as np
import pytest

from core.analysis import analyse, analyse_methods, statistic
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

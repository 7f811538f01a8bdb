"""core.gf2: exact answers on small matrices, then random systems."""

from __future__ import annotations

import numpy as np

from core import gf2


def test_inverse_of_a_known_matrix_and_of_a_singular_one() -> None:
    a = np.array([[1, 1, 0], [0, 1, 1], [0, 0, 1]], np.uint8)
    inv = gf2.inverse(a)
    assert inv is not None
    assert np.array_equal(inv, [[1, 1, 1], [0, 1, 1], [0, 0, 1]])
    assert gf2.inverse(np.array([[1, 1], [1, 1]], np.uint8)) is None
    assert gf2.rank(np.array([[1, 1, 0], [0, 1, 1], [1, 0, 1]], np.uint8)) == 2


def test_solve_meets_every_equation_or_says_there_is_no_solution() -> None:
    a = np.array([[1, 1, 0], [1, 1, 0]], np.uint8)
    assert gf2.solve(a, np.array([1, 0], np.uint8)) is None
    x = gf2.solve(a, np.array([1, 1], np.uint8), np.array([0, 0, 1], np.uint8))
    assert x is not None and (x[0] ^ x[1]) == 1 and x[2] == 1  # the free unknown keeps its value
    rng = np.random.default_rng(7)
    for _ in range(100):
        k, m = (int(v) for v in rng.integers(1, 60, 2))
        a = rng.integers(0, 2, (k, m)).astype(np.uint8)
        b = (a.astype(np.int64) @ rng.integers(0, 2, m) % 2).astype(np.uint8)
        x = gf2.solve(a, b, rng.integers(0, 2, m).astype(np.uint8))
        assert x is not None and np.array_equal(a.astype(np.int64) @ x % 2, b)

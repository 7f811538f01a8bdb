"""weld(): the hashed fast path gives exactly what sorting the 24-byte rows gives."""

from __future__ import annotations

import numpy as np
import pytest

from core.formats import base
from core.formats.base import weld


def _cases(n: int = 300) -> list[tuple[np.ndarray, np.ndarray]]:
    rng = np.random.default_rng(11)
    out = []
    for _ in range(n):
        k = int(rng.integers(0, 60))
        m = max(1, k // 2)
        pool = rng.integers(-2, 3, (m, 3)).astype(float) * rng.choice([1.0, 0.5, 1e-300, 1e300])
        pos = pool[rng.integers(0, m, k)]
        if k and rng.random() < 0.3:
            pos[rng.integers(0, k)] *= -0.0  # -0.0 welds with +0.0
        tri = rng.integers(0, max(k, 1), (int(rng.integers(0, 40)), 3)) if k else np.zeros((0, 3), int)
        out.append((pos, tri))
    return out


def _exact(monkeypatch: pytest.MonkeyPatch, pos: np.ndarray, tri: np.ndarray) -> tuple[np.ndarray, ...]:
    with monkeypatch.context() as m:
        m.setattr(base, "_unique_rows", lambda p: None)  # always the row-sorting path
        return weld(pos, tri)


def _same(a: tuple[np.ndarray, ...], b: tuple[np.ndarray, ...]) -> bool:
    return all(x.dtype == y.dtype and np.array_equal(x, y) for x, y in zip(a, b, strict=True))


def test_fast_path_matches_row_sort(monkeypatch: pytest.MonkeyPatch) -> None:
    for pos, tri in _cases():
        assert _same(weld(pos, tri), _exact(monkeypatch, pos, tri))


def test_hash_collisions_fall_back_to_row_sort(monkeypatch: pytest.MonkeyPatch) -> None:
    for pos, tri in _cases(60):
        want = _exact(monkeypatch, pos, tri)
        with monkeypatch.context() as m:
            m.setattr(base, "finalise64", lambda x: x * np.uint64(0))  # every row hashes to 0
            assert _same(weld(pos, tri), want)


def test_copy_keeps_the_inputs_untouched() -> None:
    pos = np.array([[-0.0, 1, 2], [0, 1, 2], [3, 4, 5], [6, 7, 8]])
    tri = np.array([[1, 2, 3]])
    before = pos.copy()
    vertices, faces, slots = weld(pos, tri)
    assert np.array_equal(pos.view(np.uint64), before.view(np.uint64))  # -0.0 still there
    assert not np.may_share_memory(vertices, pos) and not np.may_share_memory(faces, tri)
    assert slots.tolist() == [0, 0, 1, 2] and faces.tolist() == [[0, 1, 2]]
    # copy=False (readers): same result, the arrays may be reused
    fresh = np.array([[1.0, 2, 3], [4, 5, 6], [7, 8, 9]])
    v2, f2, _ = weld(fresh, np.array([[0, 1, 2]]), copy=False)
    assert np.shares_memory(v2, fresh) and f2.tolist() == [[0, 1, 2]]


def _grid(n: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """An n x n grid of vertices in the plane, two triangles per cell."""
    x, y = np.meshgrid(np.arange(n, dtype=float), np.arange(n, dtype=float))
    pos = np.stack([x.ravel(), y.ravel(), np.zeros(n * n)], 1)
    i = (np.arange(n - 1)[:, None] * n + np.arange(n - 1)[None, :]).ravel()
    tri = np.concatenate([np.stack([i, i + 1, i + n + 1], 1), np.stack([i, i + n + 1, i + n], 1)])
    return pos, tri


def _edge_use(faces: np.ndarray) -> np.ndarray:
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    return np.unique(e, axis=0, return_counts=True)[1]


def test_neighbours_made_to_coincide_stay_apart() -> None:
    """Two vertices with common neighbours that a rounding put on one position (8-bit
    quantisation does this to neighbours two rings apart) are not welded: welding them made edges
    of four faces and changed every label around them."""
    pos, tri = _grid()
    a, c = 14, 16  # two apart on one row: common neighbours 15 and others
    pos[c] = pos[a]
    v, f, s2v = weld(pos, tri)
    assert s2v[a] != s2v[c]
    assert _edge_use(f).max() <= 2
    assert len(np.unique(f)) == len(pos)
    # the two kept apart are the welded vertex of their position and one more, not two new ones
    # beside a vertex left with no slot (an isolated vertex, which moved the tie-break's centroid)
    assert len(v) == len(pos) and np.bincount(s2v, minlength=len(v)).min() == 1


def test_every_welded_vertex_keeps_a_slot() -> None:
    """Quantised to a coarse grid (many neighbours on one position), every welded vertex is still
    some slot's: the mesh has no vertex the file does not have."""
    pos, tri = _grid(12)
    rng = np.random.default_rng(5)
    for step in (1.0, 2.0, 3.0):
        q = np.round((pos + rng.uniform(-0.3, 0.3, pos.shape) * [1, 1, 0]) / step) * step
        v, _f, s2v = weld(q, tri)
        assert np.bincount(s2v, minlength=len(v)).min() >= 1
        assert len(v) <= len(pos)
    for p, t in _cases():
        v, _f, s2v = weld(p, t)
        assert np.bincount(s2v, minlength=len(v)).min(initial=1) >= 1


def test_seam_copies_are_still_welded() -> None:
    """A seam (the grid cut along a column, each side with its own copies of the cut vertices,
    as a UV seam or an STL soup stores them) welds back to the uncut grid."""
    pos, tri = _grid()
    n = 6
    cut = np.arange(n) * n + 3  # column 3
    copies = len(pos) + np.arange(n)
    pos2 = np.concatenate([pos, pos[cut]])
    tri2 = tri.copy()
    right = pos[tri].mean(axis=1)[:, 0] > 3  # faces right of the cut use the copies
    remap = np.arange(len(pos))
    remap[cut] = copies
    tri2[right] = remap[tri[right]]
    _v, f, s2v = weld(pos2, tri2)
    np.testing.assert_array_equal(s2v[copies], s2v[cut])
    assert len(np.unique(f)) == len(pos)
    assert _edge_use(f).max() <= 2

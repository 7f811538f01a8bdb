"""core.parallel: work split over two threads gives what one thread gives, and a process that
cannot start a thread still gets its answer."""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np

import core.embedding as embedding
import core.parallel as parallel
import core.pipeline as pipeline
from core.pipeline import embed_mesh
from tests.core.meshes import irregular_sphere


def _mesh() -> tuple[np.ndarray, np.ndarray]:
    v, f = irregular_sphere(30000, 2)
    v = v * np.array([1.0, 0.7, 0.5])  # a frame of three distinct axes: a geometric layer
    v[:, 0] += 0.2 * v[:, 1] ** 2
    return v, f


def test_no_thread_to_start_gives_the_same_file(monkeypatch) -> None:
    # every split on (stage one's thread, rows, chunks, the check beside the settle) against a
    # process where starting a thread fails (RLIMIT_AS reached): the same positions, bit for bit
    v, f = _mesh()
    for module, name in ((parallel, "SPLIT_FROM"), (embedding, "SPLIT_FROM"), (pipeline, "SPLIT_FROM")):
        monkeypatch.setattr(module, name, 1000)
    monkeypatch.setattr(parallel, "CHUNK_ROWS", 4096)
    threaded, rep = embed_mesh(v, f, "k", method="ellipsoids")
    assert rep.geometric_carriers > 0
    started = []

    def refuse(self, fn, *args, **kwargs):  # what ThreadPoolExecutor.submit raises then
        started.append(1)
        raise RuntimeError("can't start new thread")

    monkeypatch.setattr(ThreadPoolExecutor, "submit", refuse)
    alone, _ = embed_mesh(v, f, "k", method="ellipsoids")
    assert len(started) > 10  # every kind of split was asked for
    assert np.array_equal(threaded, alone)


def test_a_product_in_two_row_halves_is_the_whole_product(monkeypatch) -> None:
    # the unsmoothing's recurrence multiplies by the walk matrix in two row halves from SPLIT_FROM
    # rows, the second in the rows' worker: the same product bit for bit, and the worker is used
    from core import unsmooth
    from core.mesh import adjacency

    v, f = irregular_sphere(6000, 4)
    walk = unsmooth.walk_matrix(adjacency(f, len(v)))
    x = np.random.default_rng(7).normal(size=(len(v), 3))
    monkeypatch.setattr(parallel, "SPLIT_FROM", 1000)
    seen: set[str] = set()
    real = parallel.row_block

    def spy(matrix, lo, hi):
        block = real(matrix, lo, hi)

        class Seen:
            def __matmul__(self, y):
                seen.add(threading.current_thread().name[:13])
                return block @ y
        return Seen()

    monkeypatch.setattr(parallel, "row_block", spy)
    assert np.array_equal(parallel.halves_product(walk)(x), walk @ x)
    assert seen == {"MainThread", "meshmark-rows"}
    # and the recurrence through it gives what one thread gives
    some = np.arange(0, len(v), 7)
    split = unsmooth.unsmooth_at(v, walk, [10, 30], some)
    monkeypatch.setattr(parallel, "SPLIT_FROM", 10**9)
    assert np.array_equal(split, unsmooth.unsmooth_at(v, walk, [10, 30], some))

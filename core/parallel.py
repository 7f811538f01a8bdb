"""Per-row numpy work split over two threads.

Much of the engine's time on a large mesh goes to computations made row by row over a set of
vertices (each carrier's ring moments, eigenvectors and orientation): the result for a row does
not depend on the other rows, so the rows can be cut into chunks, every other one computed in a
worker thread while the caller computes the rest (numpy releases the GIL in its large array
loops), and the results concatenated in order: the same arrays, bit for bit, in about 0.6 of the
time on two cores (``core/README.md``, speed).  Chunks of :data:`CHUNK_ROWS` keep the temporaries
small, and with them the worker thread's own malloc arena.  Below :data:`SPLIT_FROM` rows
everything stays in the caller's thread: a small mesh gains nothing, and a service worker capped
in address space (``RLIMIT_AS``) is not asked for a thread's stack and arena.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from typing import TypeVar

import numpy as np
import scipy.sparse as sp

#: rows from which a computation is split over two threads
SPLIT_FROM = 50_000
#: rows per chunk
CHUNK_ROWS = 1 << 15

_pool: ThreadPoolExecutor | None = None
_beside: ThreadPoolExecutor | None = None
_lock = threading.Lock()
_NAME = "meshmark-rows"
T = TypeVar("T")


def submit(pool: ThreadPoolExecutor, fn: Callable[[], T]) -> Future[T]:
    """``pool.submit(fn)``, or ``fn`` made here and now when no thread can be started (a service
    worker near its address-space limit: a thread's stack and malloc arena are mapped at once):
    the result is the same either way, only later."""
    try:
        return pool.submit(fn)
    except RuntimeError:  # "can't start new thread"
        done: Future[T] = Future()
        done.set_result(fn())
        return done


def _worker(name: str) -> ThreadPoolExecutor:
    global _pool, _beside
    with _lock:
        if name == _NAME:
            _pool = _pool or ThreadPoolExecutor(1, thread_name_prefix=_NAME)
            return _pool
        _beside = _beside or ThreadPoolExecutor(1, thread_name_prefix=name)
        return _beside


def beside(fn: Callable[[], T]) -> Future[T]:
    """Run ``fn`` in a thread of its own (not the rows' worker, which ``fn`` may use) while the
    caller goes on: for a computation independent of what the caller does meanwhile."""
    return submit(_worker("meshmark-beside"), fn)


def by_chunks(fn: Callable[[int, int], T], total: int, size: int, split_from: int | None = None) -> list[T]:
    """``[fn(lo, hi) for each chunk lo:hi of range(total)]``, chunks of ``size``; from
    ``split_from`` (default :data:`SPLIT_FROM`) every other chunk in the worker thread.  The
    results come in chunk order, so sums of them made in that order are the same bit for bit."""
    bounds = [(lo, min(lo + size, total)) for lo in range(0, total, size)]
    if total < (SPLIT_FROM if split_from is None else split_from) or len(bounds) < 2 \
            or threading.current_thread().name.startswith(_NAME):
        return [fn(lo, hi) for lo, hi in bounds]
    theirs = submit(_worker(_NAME), lambda: [fn(lo, hi) for lo, hi in bounds[1::2]])
    mine = [fn(lo, hi) for lo, hi in bounds[0::2]]
    done = theirs.result()
    return [mine[i // 2] if i % 2 == 0 else done[i // 2] for i in range(len(bounds))]


def by_rows(fn: Callable[[np.ndarray], tuple[np.ndarray, ...]], rows: np.ndarray) -> tuple[np.ndarray, ...]:
    """``fn(rows)`` for a function whose every output row depends on its own input row only:
    from :data:`SPLIT_FROM` rows, in chunks of :data:`CHUNK_ROWS`, every other one in the worker
    thread."""
    rows = np.asarray(rows)
    if len(rows) < SPLIT_FROM:
        return fn(rows)
    return joined(by_chunks(lambda lo, hi: fn(rows[lo:hi]), len(rows), CHUNK_ROWS))


def joined(parts: list[tuple[np.ndarray, ...]]) -> tuple[np.ndarray, ...]:
    """Chunks' tuples of arrays joined into one tuple of arrays, in chunk order."""
    return tuple(np.concatenate(p) for p in zip(*parts, strict=True))


def row_block(matrix: sp.csr_matrix, lo: int, hi: int) -> sp.csr_matrix:
    """Rows ``lo:hi`` of a CSR ``matrix``, sharing its arrays: a product per row block, each in its
    own thread (scipy's sparse product releases the GIL), gives the whole product's rows bit for
    bit."""
    ip = matrix.indptr[lo:hi + 1]
    return sp.csr_matrix((matrix.data[ip[0]:ip[-1]], matrix.indices[ip[0]:ip[-1]], ip - ip[0]),
                         shape=(hi - lo, matrix.shape[1]), copy=False)


def halves_product(matrix: sp.csr_matrix) -> Callable[[np.ndarray], np.ndarray]:
    """``x -> matrix @ x`` for a CSR ``matrix`` used many times: from :data:`SPLIT_FROM` rows in
    two row halves (:func:`row_block`, made once), the second in the rows' worker; the same
    product bit for bit."""
    n = matrix.shape[0]
    if n < SPLIT_FROM:
        return lambda x: matrix @ x
    half = -(-n // 2)
    blocks = {(lo, hi): row_block(matrix, lo, hi) for lo, hi in ((0, half), (half, n))}
    return lambda x: np.concatenate(by_chunks(lambda lo, hi: blocks[lo, hi] @ x, n, half))

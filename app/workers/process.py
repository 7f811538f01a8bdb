"""One set-up for every process that runs the engine, in either jobs backend: the pool's workers
and the Celery worker's children.

* one BLAS/OpenMP thread per process (the processes are the parallelism), set before numpy loads;
* the engine and every format reader imported before the processes fork (:data:`PRELOAD`), so
  that a fresh process's first task is not charged for the imports against its time limit;
* a lower CPU priority than the server process (:data:`NICENESS`): when the workers saturate the
  CPU, the HTTP process still answers first (429s, health checks, uploads);
* glibc malloc keeping freed memory (:func:`core.allocator.tune_malloc`) and an address-space cap.
"""

from __future__ import annotations

import contextlib
import importlib
import os
import resource

from core.allocator import tune_malloc

#: imported once before the worker processes fork
PRELOAD = ("numpy", "scipy.sparse", "scipy.spatial", "app.workers.tasks")
#: CPU priority of an engine process, relative to the server process
NICENESS = 10
_BLAS_THREADS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def one_blas_thread() -> None:
    """One BLAS/OpenMP thread per process unless the environment says otherwise (call it before
    the engine processes start)."""
    for var in _BLAS_THREADS:
        os.environ.setdefault(var, "1")


def preload() -> None:
    """Import :data:`PRELOAD` into this process."""
    for module in PRELOAD:
        importlib.import_module(module)


def init_engine_process(memory_mb: int) -> None:
    """In a fresh engine process: lower the priority, tune malloc, cap the address space at
    ``memory_mb`` MiB (0: no cap)."""
    with contextlib.suppress(OSError):  # not allowed here: run at the server's priority
        os.nice(NICENESS)
    tune_malloc()
    if memory_mb > 0:
        limit = memory_mb * 1024 * 1024
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))

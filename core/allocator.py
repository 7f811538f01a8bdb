"""glibc malloc settings for a process that runs the engine on large meshes.

The engine's arrays for a 1M-vertex mesh are tens of MiB each; glibc serves blocks over its mmap
threshold (at most 32 MiB) with fresh ``mmap`` calls and unmaps them on ``free``, so every such
array faults its pages in again from the kernel, which also zeroes them.  Measured on a
1M-vertex detection in a fresh process on the benchmark machine: 1.4 s of user time plus 1.2 s
of system time (page faults on transparent huge pages); with mmap turned off, so that freed
memory goes back to the heap and is reused by the next array, the system time drops to 0.2 s on
the first call and to ~0 afterwards (bench/results/speed.md).  The cost: a process keeps up to
``keep_mb`` of freed heap; service workers are capped (``RLIMIT_AS``) and recycled, so that
memory stays bounded.
"""

from __future__ import annotations

import ctypes

_M_TRIM_THRESHOLD = -1
_M_MMAP_MAX = -4

#: freed heap kept by a process before it is trimmed back to the kernel
KEEP_MB = 1024


def tune_malloc(keep_mb: int = KEEP_MB) -> bool:
    """Serve every allocation from the heap and keep up to ``keep_mb`` MiB of it when freed.

    Returns ``False`` where this is not glibc (nothing changes).
    """
    try:
        mallopt = ctypes.CDLL("libc.so.6").mallopt
    except (OSError, AttributeError):
        return False
    ok = mallopt(_M_MMAP_MAX, 0) == 1
    ok &= mallopt(_M_TRIM_THRESHOLD, int(keep_mb) * 1024 * 1024) == 1
    return bool(ok)

"""glibc malloc settings for a process that runs the engine on large meshes.

The engine's arrays for a 1M-vertex mesh are tens of MiB each; glibc serves blocks over its mmap
threshold (at most 32 MiB) with fresh ``mmap`` calls and unmaps them on ``free``, so every such
array faults its pages in again from the kernel, which also zeroes them: on a large mesh that
system time rivals the computation itself.  With mmap turned off, freed memory goes back to the
heap and is reused by the next array, so a second call faults almost nothing (the figures are in
``core/README.md`` and ``bench/results/speed.md``).  The cost: a process keeps up to ``keep_mb``
of freed heap; service workers are capped (``RLIMIT_AS``) and recycled, so that memory stays
bounded.
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

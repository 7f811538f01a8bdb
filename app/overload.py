"""The API process's own resources, bounded by settings rather than by callers: the bytes of
uploads being received (all requests together) and the process's resident memory.

Both are checked before work is taken on; beyond them a request gets ``busy`` (429 with
``Retry-After``) instead of pushing the process into swap or the out-of-memory killer.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os

import psutil

from app.problems import BUSY, ProblemError

#: glibc's mallopt parameter: allocations from this size up get their own mapping
_M_MMAP_THRESHOLD = -3


def resident_bytes() -> int | None:
    """Resident memory of this process (psutil, as elsewhere in the service), None where unknown."""
    try:
        return int(psutil.Process(os.getpid()).memory_info().rss)
    except psutil.Error:
        return None


def map_large_allocations(threshold: int = 1 << 20) -> bool:
    """Have glibc give every allocation of ``threshold`` bytes or more its own memory mapping,
    returned to the system when freed.

    By default glibc raises that threshold after the first large free (up to 32 MiB), so the
    uploads and results of a burst of jobs stay in the heap and the process keeps the burst's peak
    for good (measured: 20 jobs of 30 MB left the API process at 700 MB after they were deleted).
    Returns whether the setting was applied (glibc only)."""
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name) if name else None
        return bool(libc is not None and libc.mallopt(_M_MMAP_THRESHOLD, threshold))
    except (OSError, AttributeError):
        return False


class UploadBudget:
    """Bytes of request bodies received by requests still in progress, against ``limit``.

    :class:`app.middleware.BodyLimitMiddleware` takes each chunk as it arrives and gives a
    request's bytes back when it ends; a chunk beyond the budget ends its request with ``busy``.
    """

    def __init__(self, limit: int) -> None:
        self.limit, self.in_flight = limit, 0

    def take(self, n: int) -> bool:
        if self.in_flight + n > self.limit:
            return False
        self.in_flight += n
        return True

    def give_back(self, n: int) -> None:
        self.in_flight -= n

    def refusal(self) -> ProblemError:
        return ProblemError(BUSY, f"uploads being received use the server's {self.limit:,}-byte budget; "
                            "retry later", headers={"Retry-After": "2"})


class MemoryGuard:
    """Refuses new work while the API process's resident memory is above ``limit`` bytes (0: never)."""

    def __init__(self, limit: int) -> None:
        self.limit = limit

    def refusal(self) -> ProblemError | None:
        if not self.limit:
            return None
        used = resident_bytes()
        if used is None or used <= self.limit:
            return None
        return ProblemError(BUSY, f"the server is using its memory budget ({self.limit // (1 << 20):,} MiB); "
                            "retry later", headers={"Retry-After": "5"})

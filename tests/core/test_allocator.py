"""core.allocator: freed large arrays are reused from the heap instead of faulted in again."""

from __future__ import annotations

import platform
import subprocess
import sys

import pytest

CHILD = """
import resource, sys
import numpy as np
from core.allocator import tune_malloc
if sys.argv[1] == "tuned":
    assert tune_malloc()
def faults():
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt
a = np.ones(8_000_000); del a          # 64 MB: above glibc's largest mmap threshold
before = faults()
for _ in range(5):
    a = np.ones(8_000_000); del a
print(faults() - before)
"""


def _faults(mode: str) -> int:
    out = subprocess.run([sys.executable, "-c", CHILD, mode], capture_output=True, text=True, check=True)
    return int(out.stdout.strip())


@pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc",
                    reason="mallopt is glibc's")
def test_large_arrays_reuse_freed_heap() -> None:
    tuned, default = _faults("tuned"), _faults("default")
    # default glibc maps and unmaps each 64 MB array: every page faults in again (>= 15,000 4 KiB
    # pages per array, or huge pages); tuned, the second and later arrays reuse the freed heap
    assert tuned * 10 < default
    assert tuned < 1000

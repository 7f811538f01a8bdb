"""bench identical: fingerprints made with numpy's kernels capped at AVX2, whatever the host."""

from __future__ import annotations

from bench import identical


def test_fingerprint_processes_use_no_kernel_above_avx2() -> None:
    with identical._portable_processes(1) as pool:
        used = pool.submit(identical.kernels).result()
    assert not [k for k in used if "512" in k or k == "X86_V4"]
    # the pool keeps exactly this process's kernels up to AVX2, and this process keeps all of its own
    # (the variable is only for the pool's processes)
    here = identical.kernels()
    assert set(used) == set(here) - set(identical._beyond_avx2())


def test_differences_name_the_field() -> None:
    old = {"m": {"a": [1, 2], "b": {"c": "x"}}}
    new = {"m": {"a": [1, 3], "b": {"c": "x"}, "d": 1}}
    assert identical.differences(old, new) == ["m/a[1]: 2 -> 3", "m/d: new (now 1)"]
    assert identical.differences(old, old) == []

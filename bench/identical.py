"""Byte-identity of the engine's answers: a fingerprint of everything it returns, compared with a
committed baseline, so that a refactoring can show it changed no output.

    .venv/bin/python -m bench identical --write bench/results/identical_baseline.json
    .venv/bin/python -m bench identical --check bench/results/identical_baseline.json

For every shared mesh file (all of ``$MESHMARK_TEST_MESHES``) and both methods, with one fixed key
and the default strength:

* ``capacity``: the capacity report;
* ``unmarked``: the detection report of the original file (method given);
* for the key-derived code (no payload) and a fixed 32-bit payload: the embedded file's sha256 and
  the embed report, or the exact error class and message when the embedding is refused; then the
  blind detection report of the marked file, with the method given and with ``method=None``.

Per mesh, ``unmarked_any`` is the detection of the original with ``method=None``.  Reports are
kept whole (JSON, floats as ``repr``), so ``--check`` names the mesh, the case and the field
that differ.  Only the public file-level functions of :mod:`core.api` are called, on file bytes.

The fingerprints are made in fresh processes with numpy's kernels above AVX2 switched off
(``NPY_DISABLE_CPU_FEATURES``): numpy's AVX-512 kernels round some float64 results differently
in the last bit, and the engine's outputs follow (54 differences over the 18 shared meshes between
this host with and without them, the same code).  With them off, a baseline written on one x86-64
host with AVX2 is checked on another: the one written at ``3759ee1`` on a host without AVX-512
matched that code here, on an AMD EPYC with AVX-512, in all 72 embeddings, 176 detections and 36
capacity reports.  The baseline records the kernels its processes used (``kernels``), and a check
names both sets when they differ.
"""

from __future__ import annotations

import hashlib
import json
import multiprocessing
import os
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager
from functools import partial
from pathlib import Path
from typing import Any

from bench.common import METHODS, environment, meshes_dir

KEY = "meshmark-identity-key"
PAYLOAD = "10110011100011110000101011001010"
#: the two embedding cases: the key-derived code and an explicit 32-bit payload
PAYLOADS: dict[str, str | None] = {"key_code": None, "payload32": PAYLOAD}


def mesh_files() -> list[str]:
    """Every mesh file of the shared set (everything but the README), by name."""
    return sorted(p.name for p in meshes_dir().iterdir() if p.is_file() and p.suffix.lower() != ".md")


def _outcome(call: Callable[[], Any]) -> dict[str, Any]:
    """The report of ``call()`` as plain JSON data, or the class and message of what it raised."""
    try:
        value = call()
    except Exception as exc:  # the error is part of the behaviour being fingerprinted
        return {"error": f"{type(exc).__module__}.{type(exc).__qualname__}", "message": str(exc)}
    return json.loads(json.dumps(value.to_dict(), allow_nan=False))


def fingerprint_method(name: str, method: str) -> dict[str, Any]:
    """Every fingerprint of one mesh file under one method."""
    from core.api import capacity_file, detect_file, embed_file

    data = (meshes_dir() / name).read_bytes()
    out: dict[str, Any] = {
        "capacity": _outcome(lambda: capacity_file(data, filename=name, method=method)),
        "unmarked": _outcome(lambda: detect_file(data, KEY, filename=name, method=method)),
    }
    for case, payload in PAYLOADS.items():
        try:
            embedded = embed_file(data, KEY, filename=name, payload=payload, method=method)
        except Exception as exc:
            out[case] = {"embed": {"error": f"{type(exc).__module__}.{type(exc).__qualname__}",
                                   "message": str(exc)}}
            continue
        marked = embedded.data
        out[case] = {
            "embed": {"sha256": hashlib.sha256(marked).hexdigest(), "bytes": len(marked),
                      "format": embedded.format, "media_type": embedded.media_type,
                      "extension": embedded.extension,
                      "report": json.loads(json.dumps(embedded.report.to_dict(), allow_nan=False))},
            "detect": _outcome(partial(detect_file, marked, KEY, filename=name, method=method)),
            "detect_any": _outcome(partial(detect_file, marked, KEY, filename=name, method=None)),
        }
    return out


def fingerprint_any(name: str) -> dict[str, Any]:
    from core.api import detect_file

    data = (meshes_dir() / name).read_bytes()
    return _outcome(lambda: detect_file(data, KEY, filename=name, method=None))


def kernels() -> list[str]:
    """The dispatched CPU features numpy uses in this process (none known for another numpy layout)."""
    try:
        from numpy._core._multiarray_umath import __cpu_dispatch__, __cpu_features__
    except ImportError:
        return []
    return sorted(f for f in __cpu_dispatch__ if __cpu_features__.get(f))


def _beyond_avx2() -> list[str]:
    """Those of :func:`kernels` above AVX2 (x86-64-v3): the AVX-512 groups."""
    return [f for f in kernels() if "512" in f or f == "X86_V4"]


@contextmanager
def _portable_processes(jobs: int) -> Iterator[ProcessPoolExecutor]:
    """A pool of fresh (spawned) processes whose numpy uses no kernel above AVX2."""
    before = os.environ.get("NPY_DISABLE_CPU_FEATURES")
    off = _beyond_avx2()
    if off:
        os.environ["NPY_DISABLE_CPU_FEATURES"] = ",".join(off)
    try:
        spawn = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(max_workers=max(1, jobs), mp_context=spawn) as pool:
            yield pool
    finally:
        if before is None:
            os.environ.pop("NPY_DISABLE_CPU_FEATURES", None)
        else:
            os.environ["NPY_DISABLE_CPU_FEATURES"] = before


def fingerprints(names: list[str], jobs: int) -> tuple[dict[str, Any], list[str]]:
    """``{mesh: {method: {...}, "unmarked_any": {...}}}`` for ``names``, in ``jobs`` processes, and
    the numpy kernels those processes used."""
    # largest files first, so that the pool is not left waiting on one big mesh at the end
    order = sorted(names, key=lambda n: -(meshes_dir() / n).stat().st_size)
    with _portable_processes(jobs) as pool:
        used = pool.submit(kernels)
        per_method = {(n, m): pool.submit(fingerprint_method, n, m) for n in order for m in METHODS}
        any_method = {n: pool.submit(fingerprint_any, n) for n in order}
        results = {n: {**{m: per_method[n, m].result() for m in METHODS},
                       "unmarked_any": any_method[n].result()} for n in sorted(names)}
        return results, used.result()


def differences(old: Any, new: Any, where: str = "") -> list[str]:
    """Every place where ``new`` differs from ``old``, as ``path: old -> new`` lines."""
    if isinstance(old, dict) and isinstance(new, dict):
        out = []
        for k in sorted(set(old) | set(new), key=str):
            path = f"{where}/{k}" if where else str(k)
            if k not in new:
                out.append(f"{path}: missing (was {_short(old[k])})")
            elif k not in old:
                out.append(f"{path}: new (now {_short(new[k])})")
            else:
                out += differences(old[k], new[k], path)
        return out
    if isinstance(old, list) and isinstance(new, list) and len(old) == len(new):
        pairs = enumerate(zip(old, new, strict=True))
        return [d for i, (a, b) in pairs for d in differences(a, b, f"{where}[{i}]")]
    if type(old) is not type(new) or old != new:
        return [f"{where}: {_short(old)} -> {_short(new)}"]
    return []


def _short(value: Any, limit: int = 160) -> str:
    text = json.dumps(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _count(results: dict[str, Any]) -> tuple[int, int, int]:
    """(embeddings, refused embeddings, detections) in ``results``."""
    embeds = refused = detections = 0
    for mesh in results.values():
        detections += 1
        for method in METHODS:
            detections += 1
            for case in PAYLOADS:
                entry = mesh[method][case]
                embeds += 1
                refused += "error" in entry["embed"]
                detections += 2 * ("detect" in entry)
    return embeds, refused, detections


def run(args: Any) -> int:
    """``--write FILE`` records the fingerprints; ``--check FILE`` compares with them (exit 1 on
    any difference)."""
    names = mesh_files()
    if args.meshes:
        names = [n for n in names if n in args.meshes]
    started = time.perf_counter()
    results, used = fingerprints(names, args.jobs)
    seconds = time.perf_counter() - started
    embeds, refused, detections = _count(results)
    summary = (f"{len(names)} meshes x {len(METHODS)} methods x {len(PAYLOADS)} payload cases: "
               f"{embeds} embeddings ({refused} refused), {detections} detections, "
               f"{len(names) * len(METHODS)} capacity reports, in {seconds:.0f} s")
    if args.write:
        env = environment()
        doc = {"key": KEY, "payload": PAYLOAD, "git": env["git"], "versions": env["versions"],
               "cpu": env["cpu"], "kernels": used, "meshes": results}
        Path(args.write).write_text(json.dumps(doc, indent=1, sort_keys=True) + "\n")
        print(f"identical: wrote {args.write}: {summary}")
        return 0
    baseline = json.loads(Path(args.check).read_text())
    old = baseline["meshes"]
    if args.meshes:
        old = {n: v for n, v in old.items() if n in names}
    diffs = differences(old, results)
    if baseline.get("kernels") != used:
        print(f"identical: numpy kernels {baseline.get('kernels', 'not recorded')} in the baseline "
              f"(cpu {baseline.get('cpu', 'not recorded')}), {used} here: "
              "last-digit differences may be theirs")
    if diffs:
        print(f"identical: {len(diffs)} differences from {args.check} (baseline git {baseline['git']}):")
        for line in diffs:
            print(f"  {line}")
        return 1
    print(f"identical: no difference from {args.check} (baseline git {baseline['git']}): {summary}")
    return 0

"""Rotated files of meshes whose regular labels rest on a frame that a rotation leaves open (issue 14:
symmetric and tied meshes found after any rotation).

    .venv/bin/python -m bench.rotations [--meshes capsule.obj] [--keys 4] [--rotations 8] [--out FILE.md]

For every mesh and method, ``--keys`` keys with a random 32-bit payload each: the file marked
(public file-level API, default strength), then read back after ``--rotations`` similarity
transforms (:func:`bench.attacks.similarity`: uniform rotation, scale, translation), after the three
quarter turns about the file's axes (a Y-up / Z-up export), and after each similarity with float32
positions; every attacked mesh is written as double PLY and read with the right key and with a
wrong one.  A cell is payloads recovered exactly (CRC) / tried, or false detections / wrong-key
detections; "method named": recoveries whose report names the method the file was marked with
(detection without a method); times are medians over the attacked files.
"""

from __future__ import annotations

import argparse
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from bench.attacks import similarity
from bench.common import environment, header, load_mesh, md_table, meshes_dir

MESHES = ["capsule.obj"]
METHODS = ["ellipsoids", "planes"]
#: quarter turns about x, y and z
QUARTERS = [np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]], np.float64),
            np.array([[0, 0, 1], [0, 1, 0], [-1, 0, 0]], np.float64),
            np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1]], np.float64)]


def run_one(name: str, method: str, key_index: int, rotations: int) -> dict[str, Any]:
    from bench.attacks import write_parts
    from core.api import detect_file, embed_file

    data = (meshes_dir() / name).read_bytes()
    rng = np.random.default_rng(7000 + key_index)
    key = f"rotations-key-{key_index}"
    payload = "".join(str(b) for b in rng.integers(0, 2, 32))
    marked = embed_file(data, key, filename=name, payload=payload, method=method)
    mesh = load_mesh(marked.data, name)
    out: dict[str, Any] = {"mesh": name, "method": method, "key": key, "found": {}, "times": {},
                           "false": 0, "wrong": 0, "wrong_times": [], "fpp": [], "named": [0, 0]}

    def read(kind: str, parts: list[tuple[np.ndarray, np.ndarray]]) -> None:
        blob, fname = write_parts(parts, mesh.names)
        t = time.perf_counter()
        res = detect_file(blob, key, filename=fname)
        out["times"].setdefault(kind, []).append(time.perf_counter() - t)
        ok = res.detected and res.crc_ok and res.payload == payload
        got = out["found"].setdefault(kind, [0, 0])
        got[0] += int(ok)
        got[1] += 1
        if ok:
            out["fpp"].append(res.false_positive_probability)
            out["named"][0] += int(res.method == method)
            out["named"][1] += 1
        t = time.perf_counter()
        wrong = detect_file(blob, key + "-wrong", filename=fname)
        out["wrong_times"].append(time.perf_counter() - t)
        out["wrong"] += 1
        out["false"] += int(wrong.detected)

    read("untouched", list(mesh.parts))
    for k in range(rotations):
        arng = np.random.default_rng(9000 + 100 * key_index + k)
        moved = [similarity(v, f, 0, np.random.default_rng(arng.integers(2**32))) for v, f in mesh.parts]
        read("rotation", moved)
        read("rotation, float32", [(v.astype(np.float32).astype(np.float64), f) for v, f in moved])
    for q in QUARTERS:
        read("quarter turn", [(v @ q.T, f) for v, f in mesh.parts])
    return out


KINDS = ["untouched", "rotation", "quarter turn", "rotation, float32"]


def table(rows: list[dict[str, Any]]) -> str:
    head = ["mesh", "method", *KINDS, "method named", "median s (found)", "false / wrong-key detections",
            "median s (wrong key)", "reported false-positive figure (max)"]
    body = []
    by: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for r in rows:
        by.setdefault((r["mesh"], r["method"]), []).append(r)
    for (mesh, method), rs in by.items():
        cells = []
        for kind in KINDS:
            found = sum(r["found"].get(kind, [0, 0])[0] for r in rs)
            tried = sum(r["found"].get(kind, [0, 0])[1] for r in rs)
            cells.append(f"{found}/{tried}")
        found_t = [t for r in rs for kind in KINDS[1:] for t in r["times"].get(kind, [])]
        wrong_t = [t for r in rs for t in r["wrong_times"]]
        fpp = [p for r in rs for p in r["fpp"]]
        named = f"{sum(r['named'][0] for r in rs)}/{sum(r['named'][1] for r in rs)}"
        body.append([mesh, method, *cells, named, f"{np.median(found_t):.2f}",
                     f"{sum(r['false'] for r in rs)}/{sum(r['wrong'] for r in rs)}",
                     f"{np.median(wrong_t):.2f}", f"{max(fpp):.2e}" if fpp else "-"])
    return md_table(head, body)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.rotations", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--meshes", nargs="+", default=MESHES)
    p.add_argument("--methods", nargs="+", default=METHODS)
    p.add_argument("--keys", type=int, default=4)
    p.add_argument("--rotations", type=int, default=8)
    p.add_argument("--jobs", type=int, default=2)
    p.add_argument("--out", type=Path, help="also write the table to this markdown file")
    a = p.parse_args(argv)
    tasks = [(m, meth, k) for m in a.meshes for meth in a.methods for k in range(a.keys)]
    start = time.perf_counter()
    with ProcessPoolExecutor(a.jobs) as pool:
        rows = list(pool.map(run_one, *zip(*tasks, strict=True), [a.rotations] * len(tasks)))
    text = table(rows)
    print(text)
    if a.out:
        cmd = " ".join(["python -m bench.rotations", *(argv if argv is not None else sys.argv[1:])])
        env = environment()
        env["command"] = f"{cmd}` ({time.perf_counter() - start:.0f} s, {a.jobs} processes)`"
        a.out.write_text(header("MeshMark: rotated surfaces of revolution and symmetric parts", env)
                         + "\n" + (__doc__ or "").split("\n\n", 2)[2] + "\n" + text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Attacked detections of the engine table's payload, for comparing two revisions of the engine.

    .venv/bin/python -m bench.attack_ab --out A.jsonl [--meshes NAME ...] [--methods ...]
    .venv/bin/python -m bench.attack_ab --compare A.jsonl B.jsonl [--verbose]

For every mesh (default: the nine shared meshes of >= 10k vertices of ``bench.engine_table``) and
method, the key and 32-bit payload of ``bench.engine_table`` are embedded at the default strength,
and each attack of :data:`ATTACKS` is applied (the random ones twice) and read blind (payload back
exactly) and informed (the payload's bit errors).  One JSON line per mesh and method.  To measure
another revision, run this file by its path with ``PYTHONPATH`` at a checkout of it (``git worktree
add /tmp/old REV; PYTHONPATH=/tmp/old .venv/bin/python bench/attack_ab.py --out before.jsonl``: the
engine and the attacks are then that checkout's; ``python -m`` would import this one's).
``--compare`` totals two runs per attack.  Core README, section 3 (signed offsets), used it to
choose the sides.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from bench.attacks import attack_parts, write_parts
from bench.common import load_mesh, meshes_dir
from bench.engine_table import KEY, MESHES, PAYLOAD

#: (attack of bench.attacks, level, draws)
ATTACKS: list[tuple[str, Any, int]] = [
    ("uniform_noise", 0.003, 2), ("uniform_noise", 0.005, 2), ("quantize", 8, 1), ("quantize", 7, 1),
    ("smoothing", 30, 1), ("simplify", 0.3, 1), ("simplify", 0.4, 1), ("simplify", 0.5, 1),
    ("simplify_meshopt", 0.1, 1), ("simplify_meshopt", 0.3, 1), ("crop", 0.75, 1),
]


def run_one(name: str, method: str) -> dict[str, Any]:
    from core.api import detect_file, embed_file

    data = (meshes_dir() / name).read_bytes()
    out = embed_file(data, KEY, filename=name, payload=PAYLOAD, method=method)
    mesh = load_mesh(out.data, name)
    row: dict[str, Any] = {"mesh": name, "method": method, "rms": out.report.rms_displacement}
    for attack, level, draws in ATTACKS:
        found, errors = 0, []
        for seed in range(draws):
            parts = attack_parts(attack, mesh.parts, level, np.random.default_rng(1000 + seed))
            blob, fname = write_parts(parts, mesh.names)
            blind = detect_file(blob, KEY, filename=fname, method=method)
            found += int(blind.detected and blind.payload == PAYLOAD)
            informed = detect_file(blob, KEY, filename=fname, method=method, payload=PAYLOAD)
            errors.append(informed.bit_errors if informed.bit_errors is not None else len(PAYLOAD))
        row[f"{attack} {level}"] = {"found": found, "draws": draws, "bit_errors": float(np.mean(errors))}
    return row


def compare(a_path: Path, b_path: Path, verbose: bool) -> str:
    rows_a = [json.loads(line) for line in a_path.read_text().splitlines() if line.strip()]
    rows_b = {(r["mesh"], r["method"]): r for r in
              (json.loads(line) for line in b_path.read_text().splitlines() if line.strip())}
    lines, totals = [], {}
    for ra in rows_a:
        rb = rows_b.get((ra["mesh"], ra["method"]))
        if rb is None:
            continue
        for col, va in ra.items():
            if not isinstance(va, dict):
                continue
            vb = rb[col]
            t = totals.setdefault(col, [0, 0, 0.0, 0.0, 0])
            t[0] += va["found"]
            t[1] += vb["found"]
            t[2] += va["bit_errors"] * va["draws"]
            t[3] += vb["bit_errors"] * vb["draws"]
            t[4] += va["draws"]
            if verbose and va["found"] != vb["found"]:
                lines.append(f"{ra['mesh']} {ra['method']} {col}: {va['found']}/{va['draws']} -> "
                             f"{vb['found']}/{vb['draws']}")
    for col, (fa, fb, ea, eb, n) in totals.items():
        lines.append(f"{col:24s} found {fa:3d} -> {fb:3d} of {n}   payload bit errors {ea:6.1f} -> {eb:6.1f}")
    lines.append(f"total found {sum(t[0] for t in totals.values())} -> {sum(t[1] for t in totals.values())}"
                 f" of {sum(t[4] for t in totals.values())}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.attack_ab", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--meshes", nargs="+", default=[m for m in MESHES if m != "capsule.obj"])
    p.add_argument("--methods", nargs="+", default=["ellipsoids", "planes"])
    p.add_argument("--out", type=Path, help="JSON lines, one per mesh and method")
    p.add_argument("--compare", nargs=2, type=Path, metavar=("A", "B"), help="totals of two runs")
    p.add_argument("--verbose", action="store_true", help="with --compare: every cell that changed")
    args = p.parse_args(argv)
    if args.compare:
        print(compare(args.compare[0], args.compare[1], args.verbose))
        return 0
    if args.out is None:
        p.error("--out or --compare is required")
    with args.out.open("w") as fh:
        for name in args.meshes:
            for method in args.methods:
                row = run_one(name, method)
                fh.write(json.dumps(row) + "\n")
                fh.flush()
                print(json.dumps(row), file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

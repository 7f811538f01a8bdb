"""Distortion, carriers and detection per mesh for the engine's work on issue 14 (a quick table).

    .venv/bin/python -m bench.engine_table [--meshes NAME ...] [--seeds 1] [--out FILE.md]

For every mesh (default: the shared meshes of >= 10k vertices, the cycloidal gear, the CAD STL
soup and the capsule) and both methods, with one fixed key and a fixed 32-bit payload at the
default strength: the embed report's RMS and max displacement (of the bounding-box diagonal),
carriers as % of the welded vertices and the cap factor, or the refusal; then whether the
payload comes back exactly (CRC) after each attack of :data:`CASES`, ``--seeds`` draws each
(a cell reads ``found/tried``).  Only the public file-level functions of :mod:`core.api` are
called, on file bytes; attacked meshes are written as double PLY (:mod:`bench.attacks`).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench.attacks import attack_parts, write_parts
from bench.common import environment, header, load_mesh, md_table, meshes_dir

KEY = "meshmark-issue14-key"
PAYLOAD = "10110011100011110000101011001010"
MESHES = ["rocker-arm.obj", "beetle.off", "bun_zipper.ply", "armadillo.obj", "horse.ply", "dragon.ply",
          "turbineblade.ply", "cycloidal.ply", "counter.unitsmm.STL", "capsule.obj"]
#: column -> (attack of bench.attacks, level)
CASES: dict[str, tuple[str, Any]] = {
    "none": ("none", 0),
    "rotation": ("similarity", 1),
    "noise 0.3 %": ("uniform_noise", 0.003),
    "Laplacian 0.1x10": ("smoothing", 10),
    "crop to 25 %": ("crop", 0.75),
    "crop to 50 %": ("crop", 0.5),
    # issue 14's re-triangulation, smoothing and quantisation rows
    "midpoint": ("subdivide", "midpoint"),
    "Loop": ("subdivide", "loop"),
    "sqrt(3)": ("subdivide", "sqrt3"),
    "quadric 10 %": ("simplify", 0.1),
    "quadric 30 %": ("simplify", 0.3),
    "quadric 50 %": ("simplify", 0.5),
    "meshopt 5 %": ("simplify_meshopt", 0.05),
    "meshopt 10 %": ("simplify_meshopt", 0.1),
    "Laplacian 0.1x30": ("smoothing", 30),
    "quant 8 bit": ("quantize", 8),
}
#: attacks without randomness: one draw whatever ``--seeds`` says
DETERMINISTIC = {"none", "smoothing", "subdivide", "simplify", "simplify_meshopt", "quantize"}


def run_one(name: str, method: str, seeds: int, cases: dict[str, tuple[str, Any]],
            strength: float | None = None) -> dict[str, Any]:
    from core.api import detect_file, embed_file
    from core.errors import MeshMarkError
    from core.formats import read_mesh

    data = (meshes_dir() / name).read_bytes()
    n = sum(len(p.vertices) for p in read_mesh(data, name).parts)
    row: dict[str, Any] = {"mesh": name, "method": method, "vertices": n}
    t = time.perf_counter()
    try:
        out = embed_file(data, KEY, filename=name, payload=PAYLOAD, method=method, strength=strength)
    except MeshMarkError as exc:
        row["refused"] = str(exc)
        return row
    row["embed_s"] = round(time.perf_counter() - t, 2)
    rep = out.report
    row.update(rms=rep.rms_displacement, max=rep.max_displacement, carriers=rep.carriers,
               carriers_pct=100.0 * rep.carriers / max(n, 1), cap_factor=rep.cap_factor)
    mesh = load_mesh(out.data, name)
    row["layers"] = ",".join(rep.layers)
    for col, (attack, level) in cases.items():
        found = 0
        layers: set[str] = set()
        tries = 1 if attack in DETERMINISTIC else seeds
        for seed in range(tries):
            rng = np.random.default_rng(1000 + seed)
            parts = attack_parts(attack, mesh.parts, level, rng)
            blob, fname = write_parts(parts, mesh.names)
            res = detect_file(blob, KEY, filename=fname, method=method)
            ok = res.detected and res.crc_ok and res.payload == PAYLOAD
            found += int(ok)
            if ok and res.layer:
                layers.add(LAYER_MARKS[res.layer])
        row[col] = f"{found}/{tries}" + (" " + "".join(sorted(layers)) if layers else "")
    return row


#: how a cell says which layer read the payload (DetectResult.layer)
LAYER_MARKS = {"connectivity": "c", "both": "b", "geometry": "g"}


def table(rows: list[dict[str, Any]], cases: list[str]) -> str:
    head = ["mesh", "method", "vertices", "carriers %", "RMS", "max", "cap x", "layers"] + cases
    body = []
    for r in rows:
        if "refused" in r:
            body.append([r["mesh"], r["method"], r["vertices"], "refused: " + r["refused"][:90]]
                        + [""] * (4 + len(cases)))
            continue
        body.append([r["mesh"], r["method"], r["vertices"], f"{r['carriers_pct']:.1f}", f"{r['rms']:.2e}",
                     f"{r['max']:.2e}", f"{r['cap_factor']:g}", r["layers"]] + [r[c] for c in cases])
    return md_table(head, body)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.engine_table", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--meshes", nargs="+", default=MESHES)
    p.add_argument("--methods", nargs="+", default=["ellipsoids", "planes"])
    p.add_argument("--seeds", type=int, default=1, help="draws of each random attack (default: %(default)s)")
    p.add_argument("--attacks", nargs="+", default=list(CASES), help="columns of CASES to run")
    p.add_argument("--strength", type=float, help="embedding strength (default: the engine's default)")
    p.add_argument("--out", type=Path, help="also write the table to this markdown file")
    a = p.parse_args(argv)
    cases = {c: CASES[c] for c in a.attacks}
    rows = []
    for name in a.meshes:
        for method in a.methods:
            rows.append(run_one(name, method, a.seeds, cases, a.strength))
            print(rows[-1], file=sys.stderr, flush=True)
    text = table(rows, list(cases))
    print(text)
    if a.out:
        env = environment()
        given = argv if argv is not None else sys.argv[1:]
        env["command"] = "python -m bench.engine_table " + " ".join(given)
        intro = [f"- Key `{KEY}`, payload `{PAYLOAD}` (32 bits), default strength; a cell is payloads "
                 "recovered exactly (CRC) / attacks tried, and which layer read them (c: connectivity, "
                 "b: both together, g: geometric); RMS and max displacement of the bounding-box "
                 "diagonal; `layers`: those the embedder verified to read alone", ""]
        a.out.write_text(header("MeshMark engine table (issue 14 targets)", env, intro) + "\n" + text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

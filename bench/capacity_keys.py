"""Does ``capacity`` say exactly what embeds?  For many keys, every payload length it allows is embedded.

    .venv/bin/python -m bench capacity-keys [--keys 50] [--first-key 0] [--payloads 2] [--meshes NAME ...]
                                           [--jobs 2] [--out bench/results] [--seed 2006]

For every mesh (default: the small models and scenes of :data:`MESHES`), both methods and no method
(``default``: what MeshMark chooses, :data:`core.options.AUTO_METHOD`) and keys ``key-F`` ...
``key-{F+K-1}`` (``--first-key`` F, default 0: a run from another F has keys of its own), at the
default strength: ``capacity`` with the key gives
``M = max_payload_bits``; then ``--payloads`` random payloads of each length M, M - 1, ceil(M / 2), 1
and two random lengths in [1, M] are embedded with that key and method (an embedding is only
returned when it reads back, so a refusal is a failure of capacity's promise).  A separate row
embeds a random 32-bit payload whatever M is (issue 14: the Sink with a payload of the user's
choosing; the method that carried it is counted).  Writes ``capacity_keys.md`` and
``capacity_keys.json``; only :mod:`core.api` is called, on file bytes.
"""

from __future__ import annotations

import math
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from bench.common import METHODS, environment, header, md_table, meshes_dir, save_json

MESHES = ["sink.3ds", "Duck.glb", "spot.obj", "monkey.glb", "CesiumMilkTruck.glb", "fandisk.off"]
#: the methods asked: each one, and none (MeshMark's choice)
DEFAULT = "default"
ASKED = (*METHODS, DEFAULT)


def lengths_to_try(m: int, rng: np.random.Generator) -> list[int]:
    """M, M - 1, ceil(M / 2), 1 and two random lengths in [1, M], without repeats (none when M = 0)."""
    if m <= 0:
        return []
    wanted = [m, m - 1, math.ceil(m / 2), 1, *(int(x) for x in rng.integers(1, m + 1, 2))]
    return list(dict.fromkeys(n for n in wanted if n > 0))


def run_one(name: str, method: str, key: str, payloads: int, seed: int) -> dict[str, Any]:
    """Capacity and every trial embedding of one (mesh, method, key)."""
    from core.api import Options, capacity, embed
    from core.errors import MeshMarkError

    data = (meshes_dir() / name).read_bytes()
    rng = np.random.default_rng([seed, sum(map(ord, name)), ASKED.index(method), int(key.split("-")[-1])])
    asked = None if method == DEFAULT else method
    t = time.perf_counter()
    rep = capacity(data, Options(key=key, method=asked), filename=name)
    cap_s = time.perf_counter() - t
    m = rep.max_payload_bits
    trials, failures = 0, []
    t = time.perf_counter()
    for n in lengths_to_try(m, rng):
        for _ in range(payloads):
            bits = "".join(map(str, rng.integers(0, 2, n)))
            trials += 1
            try:
                embed(data, Options(key=key, payload=bits, method=asked), filename=name)
            except MeshMarkError as exc:
                failures.append({"length": n, "payload": bits, "error": str(exc)[:200]})
    embed_s = time.perf_counter() - t
    bits32 = "".join(map(str, rng.integers(0, 2, 32)))
    try:
        fits32 = embed(data, Options(key=key, payload=bits32, method=asked), filename=name).report.method
    except MeshMarkError:
        fits32 = None
    return {"mesh": name, "method": method, "key": key, "carriers": rep.carriers, "max_payload_bits": m,
            "capacity_method": rep.method, "trials": trials, "failures": failures, "fits32": fits32,
            "capacity_s": round(cap_s, 3),
            "embed_s": round(embed_s, 3)}


def run(args: Any) -> None:
    names = args.meshes or MESHES
    keys = [f"key-{i}" for i in range(args.first_key, args.first_key + args.keys)]
    jobs = [(n, m, k) for n in names for m in ASKED for k in keys]
    started = time.perf_counter()
    with ProcessPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        futures = [pool.submit(run_one, n, m, k, args.payloads, args.seed) for n, m, k in jobs]
        rows = [f.result() for f in futures]
    seconds = time.perf_counter() - started
    env = environment()
    table = []
    for n in names:
        for m in ASKED:
            rs = [r for r in rows if r["mesh"] == n and r["method"] == m]
            via = {x: sum(r["fits32"] == x for r in rs) for x in METHODS}
            caps = [r["max_payload_bits"] for r in rs]
            carriers = [r["carriers"] for r in rs]
            table.append([n, m, f"{min(carriers)}-{max(carriers)}", f"{min(caps)}-{max(caps)}",
                          sum(c == 0 for c in caps), sum(r["trials"] for r in rs),
                          sum(len(r["failures"]) for r in rs), sum(bool(r["failures"]) for r in rs),
                          sum(r["fits32"] is not None for r in rs),
                          ", ".join(f"{x} {c}" for x, c in via.items() if c) or "-",
                          round(float(np.median([r["capacity_s"] for r in rs])), 2),
                          round(max(r["capacity_s"] for r in rs), 2)])
    fail_rows = [[r["mesh"], r["method"], r["key"], r["max_payload_bits"], f["length"], f["error"][:110]]
                 for r in rows for f in r["failures"]]
    text = header("Capacity says what embeds: many keys, every allowed length", env, [
        f"- {len(keys)} keys (`{keys[0]}`...`{keys[-1]}`), {args.payloads} random payloads per length, "
        "default strength; "
        f"{len(jobs)} capacity calls in {seconds:.0f} s ({args.jobs} processes)",
        "",
    ])
    text += ("\nPer mesh and method: carriers and `max_payload_bits` (M) over the keys, keys with M = 0, "
             "trial embeddings of lengths M, M-1, ceil(M/2), 1 and two random lengths <= M, how many were "
             "refused and for how many keys, keys for which a random 32-bit payload embeds (whatever M "
             "says) and with which method, and capacity's time per call (median, max). `default`: no "
             "method asked (ellipsoids, or planes where only planes carries the payload).\n\n")
    text += md_table(["mesh", "method", "carriers", "M", "M = 0", "trials", "refused", "keys with a refusal",
                      "32 bits embed", "32 bits with", "capacity s (median)", "capacity s (max)"], table,
                     "llrrrrrrrlrr")
    text += "\n## Refusals\n\n"
    text += md_table(["mesh", "method", "key", "M", "length", "error"], fail_rows, "lllrrl") if fail_rows \
        else "None.\n"
    out = Path(args.out)
    (out / "capacity_keys.md").write_text(text)
    save_json(out / "capacity_keys.json", {"env": env, "rows": rows})
    print(text)

"""False positives: blind detection with wrong random keys, on marked and on unmarked meshes.

Every detection calls ``detect_file(data, wrong_key, method=None)`` as a user who does not know
the method would (both methods are tried, so each call is two chances to go wrong).  Marked
files are marked with the bench key, once with the key-derived code and once with a 64-bit
payload, per method.  A detection counts as false when ``detected`` is true.
"""

from __future__ import annotations

import multiprocessing as mp
import time
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from bench.common import (
    KEY,
    METHODS,
    SMALL_MEDIUM_MESHES,
    available_meshes,
    environment,
    header,
    md_table,
    mesh_path,
    random_payload,
    save_json,
)

QUICK_FP_MESHES = ["sink.3ds", "spot.obj"]


def _variant(name: str, variant: str, seed: int) -> bytes | None:
    """The file for ``variant``: ``"unmarked"`` or ``"<method>, key-derived|64-bit payload"``."""
    from core.api import embed_file

    data = mesh_path(name).read_bytes()
    if variant == "unmarked":
        return data
    meth, mode = variant.split(", ")
    rng = np.random.default_rng([seed, zlib.crc32(name.encode()), zlib.crc32(variant.encode())])
    payload = random_payload(rng, 64) if mode != "key-derived" else None
    try:
        return embed_file(data, KEY, filename=name, payload=payload, method=meth).data
    except Exception as e:
        print(f"  false-positives: cannot mark {name} ({variant}): {type(e).__name__}: {e}", flush=True)
        return None


def fp_job(job: dict[str, Any]) -> dict[str, Any]:
    from core.api import detect_file

    name = job["mesh"]
    variant = job["variant"]
    data = _variant(name, variant, job["seed"])
    out: dict[str, Any] = {
        "mesh": name,
        "variant": variant,
        "n": 0,
        "false": 0,
        "crc_ok": 0,
        "fpp": [],
        "errors": 0,
        "seconds": 0.0,
        "false_cases": [],
    }
    if data is None:
        out["skipped"] = True
        return out
    if variant != "unmarked" and job["part"] == 0:
        # what the detector claims for a positive answer in the same call mode (right key)
        r = detect_file(data, KEY, filename=name, method=None)
        out["claimed_fpp"] = float(r.false_positive_probability) if r.detected else None
    rng = np.random.default_rng(
        [job["seed"], zlib.crc32(name.encode()), zlib.crc32(variant.encode()), job["part"]]
    )
    t = time.perf_counter()
    for _ in range(job["n"]):
        key = rng.bytes(16).hex()
        if key == KEY:
            continue
        try:
            r = detect_file(data, key, filename=name, method=None)
        except Exception:
            out["errors"] += 1
            continue
        out["n"] += 1
        out["fpp"].append(float(r.false_positive_probability))
        if r.detected:
            out["false"] += 1
            out["false_cases"].append(
                {"key": key, "fpp": r.false_positive_probability, "method": r.method, "payload": r.payload}
            )
        out["crc_ok"] += bool(r.crc_ok)
    out["seconds"] = time.perf_counter() - t
    return out


def run(args) -> dict[str, Any]:
    quick = args.quick
    total = args.fp_detections or (400 if quick else 10_000)
    meshes = available_meshes(args.meshes or (QUICK_FP_MESHES if quick else SMALL_MEDIUM_MESHES))
    variants = ["unmarked"] + [f"{m}, {mode}" for m in METHODS for mode in ("key-derived", "64-bit payload")]
    # only the files that exist count: a small mesh refuses a 64-bit payload (CapacityError)
    cells = [(m, v) for m in meshes for v in variants if _variant(m, v, args.seed) is not None]
    per = -(-total // max(len(cells), 1))
    chunk = 50 if quick else 250
    jobs = []
    for m, v in cells:
        for part, start in enumerate(range(0, per, chunk)):
            jobs.append(
                {"mesh": m, "variant": v, "n": min(chunk, per - start), "part": part, "seed": args.seed}
            )
    env = environment()
    t0 = time.perf_counter()
    res: list[dict[str, Any]] = []
    if args.jobs > 1:
        with mp.get_context("spawn").Pool(args.jobs, maxtasksperchild=8) as pool:
            for r in pool.imap_unordered(fp_job, jobs):
                res.append(r)
                if len(res) % max(1, len(jobs) // 10) == 0:
                    print(
                        f"  false-positives: {len(res)}/{len(jobs)} ({time.perf_counter() - t0:.0f} s)",
                        flush=True,
                    )
    else:
        res = [fp_job(j) for j in jobs]
    result = {
        "env": env,
        "quick": quick,
        "seed": args.seed,
        "jobs": res,
        "elapsed_s": time.perf_counter() - t0,
    }
    out_dir = Path(args.out)
    save_json(out_dir / "false_positives.json", _compact(result))
    write_report(result, out_dir)
    return result


def _compact(result: dict[str, Any]) -> dict[str, Any]:
    """Keep summary statistics of the reported probabilities, not every value."""
    out = dict(result)
    jobs = []
    for j in result["jobs"]:
        j = dict(j)
        f = np.asarray(j.pop("fpp"), np.float64)
        j.update(
            fpp_mean=float(f.mean()) if f.size else None,
            fpp_max=float(f.max()) if f.size else None,
            fpp_min=float(f.min()) if f.size else None,
            fpp_sum=float(f.sum()),
        )
        jobs.append(j)
    out["jobs"] = jobs
    return out


def summarize(result: dict[str, Any]) -> dict[str, Any]:
    jobs = [j for j in result["jobs"] if not j.get("skipped")]
    n = sum(j["n"] for j in jobs)
    false = sum(j["false"] for j in jobs)
    if jobs and "fpp" in jobs[0]:
        f = np.concatenate([np.asarray(j["fpp"], np.float64) for j in jobs]) if n else np.zeros(0)
        fmean, fmax, fmin = (
            (float(f.mean()), float(f.max()), float(f.min())) if f.size else (None, None, None)
        )
    else:
        fmean = sum(j["fpp_sum"] for j in jobs) / n if n else None
        fmax = max((j["fpp_max"] for j in jobs if j["fpp_max"] is not None), default=None)
        fmin = min((j["fpp_min"] for j in jobs if j["fpp_min"] is not None), default=None)
    # one-sided 95 % upper bound on the false detection rate (exact for zero events: 3/n rule)
    upper = (3.0 / n if false == 0 else None) if n else None
    claimed = [j["claimed_fpp"] for j in jobs if j.get("claimed_fpp") is not None]
    return {
        "claimed_fpp": max(claimed) if claimed else None,
        "expected_claimed": max(claimed) * n if claimed else None,
        "n": n,
        "false": false,
        "fpp_mean": fmean,
        "fpp_max": fmax,
        "fpp_min": fmin,
        "upper95": upper,
        "expected": fmean * n if fmean is not None else None,
        "errors": sum(j["errors"] for j in jobs),
        "seconds": sum(j["seconds"] for j in jobs),
    }


def write_report(result: dict[str, Any], out_dir: Path) -> None:
    s = summarize(result)
    jobs = [j for j in result["jobs"] if not j.get("skipped")]
    lines = [
        header(
            "MeshMark false positives",
            result["env"],
            [
                f"- Seed {result['seed']}; {'quick slice' if result['quick'] else 'full run'}; "
                f"wall time {result['elapsed_s'] / 60:.1f} min",
                "- Each detection: `detect_file(file, random 128-bit hex key, method=None)` "
                "(both methods tried).",
                "- The detector reports `false_positive_probability` = 1 whenever it rejects, so the "
                "figure to "
                "hold the observed rate against is the one it reports with a positive answer (a union bound "
                "over every candidate it tries).",
            ],
        )
    ]
    lines.append("\n## Overall\n")
    rows = [
        ["detections with a wrong key", s["n"]],
        ["false detections (`detected` true)", s["false"]],
        ["observed false detection rate", s["false"] / s["n"] if s["n"] else None],
        ["95 % upper bound on the rate (3/n rule, zero events)", s["upper95"]],
        ["FPP the detector reports with a positive answer (right key, same call mode)", s["claimed_fpp"]],
        ["false detections expected from that figure (n x FPP)", s["expected_claimed"]],
        ["mean reported `false_positive_probability` on the wrong-key calls", s["fpp_mean"]],
        ["max reported `false_positive_probability`", s["fpp_max"]],
        ["min reported `false_positive_probability`", s["fpp_min"]],
        ["detector exceptions", s["errors"]],
        ["CPU seconds in detection", s["seconds"]],
    ]
    lines.append(md_table(["quantity", "value"], rows))
    lines.append("\n## Per mesh and file\n")
    agg: dict[tuple[str, str], dict[str, Any]] = {}
    for j in jobs:
        a = agg.setdefault(
            (j["mesh"], j["variant"]), {"n": 0, "false": 0, "crc": 0, "fsum": 0.0, "fmax": 0.0, "sec": 0.0}
        )
        a["n"] += j["n"]
        a["false"] += j["false"]
        a["crc"] += j["crc_ok"]
        fp = j.get("fpp")
        a["fsum"] += float(np.sum(fp)) if fp is not None else j["fpp_sum"]
        a["fmax"] = max(a["fmax"], float(np.max(fp)) if fp else (j.get("fpp_max") or 0.0))
        a["sec"] += j["seconds"]
    rows = [
        [
            m,
            v,
            a["n"],
            a["false"],
            a["crc"],
            a["fsum"] / a["n"] if a["n"] else None,
            a["fmax"],
            1000 * a["sec"] / a["n"] if a["n"] else None,
        ]
        for (m, v), a in sorted(agg.items())
    ]
    lines.append(
        md_table(
            [
                "mesh",
                "file",
                "detections",
                "false",
                "CRC ok",
                "mean reported FPP",
                "max reported FPP",
                "ms / detection",
            ],
            rows,
            "llrrrrrr",
        )
    )
    cases = [c | {"mesh": j["mesh"], "variant": j["variant"]} for j in jobs for c in j["false_cases"]]
    if cases:
        lines.append("\n## False detections\n")
        lines.append(
            md_table(
                ["mesh", "file", "key", "method", "reported FPP"],
                [[c["mesh"], c["variant"], c["key"], c["method"], c["fpp"]] for c in cases[:50]],
            )
        )
    (out_dir / "false_positives.md").write_text("\n".join(lines))

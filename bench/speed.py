"""Speed and peak memory of embed, detect and capacity at ~10k, ~100k and ~1M vertices.

Every measurement runs in a fresh Python subprocess (``python -m bench.speed --worker ...``):
the worker imports what it needs and reads the file, then times only the operation with
``time.perf_counter``.  Peak memory is the child's resident high-water mark ``VmHWM`` from
``/proc/self/status`` (whole process: interpreter, imports, input bytes and the operation),
reset to the current RSS through ``/proc/self/clear_refs`` just before the call, so the table
also gives the growth during the call itself.  (``ru_maxrss`` is not used: Linux keeps it across
``execve``, so a child would start with its parent's mark.)  Each figure is the median of several runs.
The baselines are trimesh's ``load`` (default processing) followed by ``export`` of the same
mesh as binary PLY and as OBJ, measured the same way in the same run.
"""

from __future__ import annotations

import json
import resource
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from bench.common import KEY, environment, header, json_child, md_table, mesh_path, save_json

ONE_MILLION = "turbineblade.ply x2 midpoint, cut to 1M"
SIZES = [("10k", "rocker-arm.obj"), ("100k", "turbineblade.ply"), ("1M", ONE_MILLION)]
OPS = ["embed", "detect", "detect-auto", "detect-wrong", "capacity", "trimesh-ply", "trimesh-obj"]


def _status_kib(field: str) -> int | None:
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith(field + ":"):
                    return int(line.split()[1])
    except OSError:
        pass
    return None


def _reset_peak() -> bool:
    """Reset the kernel's resident high-water mark (VmHWM) to the current RSS (Linux >= 4.0)."""
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
        return True
    except OSError:
        return False


def worker(argv: list[str]) -> None:
    """``--worker OP PATH [OUT]``: run one operation twice (cold, then warm) and print a JSON line."""
    op, path = argv[0], Path(argv[1])
    save = Path(argv[2]) if len(argv) > 2 else None
    data = path.read_bytes()
    if op.startswith("trimesh"):
        import io

        import trimesh
    else:
        import core.pipeline  # noqa: F401  (core.api imports it lazily: keep the import out of the timing)
        from core.allocator import tune_malloc
        from core.api import capacity_file, detect_file, embed_file

        tune_malloc()
    # ru_maxrss survives execve (a child starts with its parent's mark), so read VmHWM instead
    reset = _reset_peak()
    before = _status_kib("VmRSS") if reset else _status_kib("VmHWM")
    if before is None:
        before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss

    def once() -> dict[str, Any]:
        if op == "embed":
            emb = embed_file(data, KEY, filename=path.name, method="ellipsoids")
            if save:
                save.write_bytes(emb.data)
            return {"carriers": emb.report.carriers, "copies": emb.report.copies}
        if op in ("detect", "detect-auto", "detect-wrong"):
            # detect-wrong: another key, so that nothing reads and every view is tried (what a caller
            # who guesses keys costs the service)
            r = detect_file(data, KEY + ("-wrong" if op == "detect-wrong" else ""), filename=path.name,
                            method=None if op == "detect-auto" else "ellipsoids")
            return {"detected": r.detected, "carriers": r.carriers}
        if op == "capacity":
            return {"carriers": capacity_file(data, filename=path.name, method="ellipsoids").carriers}
        if op in ("trimesh-ply", "trimesh-obj"):
            m = trimesh.load(io.BytesIO(data), file_type=path.suffix[1:], force="mesh")
            return {"bytes_out": len(m.export(file_type="ply" if op == "trimesh-ply" else "obj"))}
        raise SystemExit(f"unknown op {op}")

    # cold: the first call of a fresh process (its memory is faulted in from the kernel); warm: the
    # same call again in the same process, as in a long-lived service worker
    t = time.perf_counter()
    info = once()
    cold = time.perf_counter() - t
    peak = _status_kib("VmHWM") or resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t = time.perf_counter()
    once()
    warm = time.perf_counter() - t
    print(json.dumps({"op": op, "seconds": warm, "cold_seconds": cold, "peak_kib": peak, "before_kib": before,
                      "hwm_reset": reset, **info}))


def _measure(op: str, path: Path, save: Path | None = None, timeout: float = 3600) -> dict[str, Any]:
    out = json_child("bench.speed", ["--worker", op, str(path)] + ([str(save)] if save else []), timeout)
    return {"op": op, **out} if "error" in out else out


def make_1m(tmp: Path, target: int = 1_000_000) -> Path:
    """A real scan at one million vertices: ``turbineblade.ply`` (99,519 vertices) subdivided twice
    (midpoint, ``trimesh.remesh.subdivide``: 1,592,274 vertices), then cut by a plane across its
    longest axis, keeping the faces below it, so that ``target`` vertices remain; written as binary
    PLY (double coordinates) in a temporary directory."""
    import numpy as np
    import trimesh
    from trimesh import remesh

    m = trimesh.load(str(mesh_path("turbineblade.ply")), force="mesh")
    v, f = np.asarray(m.vertices), np.asarray(m.faces)
    for _ in range(2):
        v, f = remesh.subdivide(v, f)
    axis = int(np.argmax(np.ptp(v, axis=0)))
    f = f[np.argsort(v[f, axis].max(axis=1), kind="stable")]
    # a vertex is kept once the prefix of faces reaches it: cut where the (target + 1)-th appears
    first = np.full(len(v), len(f))
    np.minimum.at(first, f.ravel(), np.repeat(np.arange(len(f)), 3))
    f = f[: np.sort(first)[target]] if target < len(v) else f
    used, f = np.unique(f, return_inverse=True)
    out = tmp / "turbineblade-1m.ply"
    out.write_bytes(trimesh.Trimesh(v[used], f.reshape(-1, 3), process=False).export(file_type="ply"))
    return out


def run(args) -> dict[str, Any]:
    runs = max(3, args.speed_runs)
    sizes = SIZES[:1] if args.quick else SIZES
    if args.meshes:
        sizes = [(Path(m).stem, m) for m in args.meshes]
    env = environment()
    t0 = time.perf_counter()
    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="meshmark-speed-") as tmpd:
        tmp = Path(tmpd)
        for label, name in sizes:
            if name == ONE_MILLION:
                if not mesh_path("turbineblade.ply").is_file():
                    continue
                path = make_1m(tmp)
            else:
                path = mesh_path(name)
                if not path.is_file():
                    continue
            marked = tmp / f"marked-{path.name}"
            first = _measure("embed", path, marked)
            import trimesh

            tm = trimesh.load(str(path), force="mesh", process=False)
            entry: dict[str, Any] = {
                "size": label,
                "mesh": name,
                "vertices": len(tm.vertices),
                "faces": len(tm.faces),
                "bytes": path.stat().st_size,
                "ops": {},
            }
            del tm
            for op in OPS:
                src = marked if op.startswith("detect") else path
                if op.startswith("detect") and not marked.is_file():
                    entry["ops"][op] = {"error": first.get("error", "embed failed")}
                    continue
                ms = [first] if op == "embed" else []
                while len(ms) < runs:
                    ms.append(_measure(op, src))
                    if "error" in ms[-1]:
                        break
                ok = [m for m in ms if "error" not in m]
                if not ok:
                    entry["ops"][op] = {"error": ms[-1]["error"]}
                    continue
                entry["ops"][op] = {
                    "median_s": statistics.median(m["seconds"] for m in ok),
                    "runs": [m["seconds"] for m in ok],
                    "cold_median_s": statistics.median(m["cold_seconds"] for m in ok),
                    "cold_runs": [m["cold_seconds"] for m in ok],
                    "peak_mib": statistics.median(m["peak_kib"] for m in ok) / 1024,
                    "delta_mib": statistics.median(m["peak_kib"] - m["before_kib"] for m in ok) / 1024,
                    "info": {
                        k: v
                        for k, v in ok[0].items()
                        if k not in ("seconds", "cold_seconds", "peak_kib", "before_kib", "op", "hwm_reset")
                    },
                }
                print(f"  speed: {label} {op}: warm {entry['ops'][op]['median_s']:.2f} s, "
                      f"cold {entry['ops'][op]['cold_median_s']:.2f} s", flush=True)
            rows.append(entry)
    result = {
        "env": env,
        "quick": args.quick,
        "runs": runs,
        "sizes": rows,
        "elapsed_s": time.perf_counter() - t0,
    }
    out_dir = Path(args.out)
    save_json(out_dir / "speed.json", result)
    write_report(result, out_dir)
    return result


def write_report(result: dict[str, Any], out_dir: Path) -> None:
    lines = [
        header(
            "MeshMark speed",
            result["env"],
            [
                f"- Median of {result['runs']} runs, each in a fresh subprocess; wall time "
                f"{result['elapsed_s'] / 60:.1f} min",
                "- Time: the operation only (file bytes already in memory, imports done). Each child calls "
                "it twice: **cold** = the first call of the fresh process, whose memory is faulted in "
                "from the kernel (on this VM that alone varies from 0.2 to 1.6 s per 0.5 GB touched); "
                "**warm** = the same call again in the same process, as in a long-lived service worker. "
                "Ratios use the warm figures of both sides.",
                "- Peak memory: the child's `VmHWM` after the cold call (whole process, reset to the "
                "current RSS just before it); 'growth' = peak minus the RSS before the call.",
                "- embed/capacity: ellipsoids, default strength; detect: key + method given; "
                "detect-auto: key only "
                "(both methods tried); detect-wrong: the marked file with another key, method given (nothing "
                "reads, so every view is tried: what a caller guessing keys costs). Ratios: MeshMark time / "
                "trimesh `load` + `export` of the same file.",
                "- 1M: `turbineblade.ply` subdivided twice (midpoint, `trimesh.remesh.subdivide`: "
                "1,592,274 vertices) and cut across its longest axis to 1,000,000 vertices, written as "
                "binary PLY in a temporary directory (`bench.speed.make_1m`).",
                "- Every MeshMark child first applies `core.allocator.tune_malloc()`, as the service "
                "workers and the CLI do (heap instead of a fresh mmap per large array).",
            ],
        )
    ]
    rows = []
    for e in result["sizes"]:
        ops = e["ops"]
        tp = ops.get("trimesh-ply", {}).get("median_s")
        to = ops.get("trimesh-obj", {}).get("median_s")
        for op in OPS:
            o = ops.get(op, {})
            if "error" in o:
                rows.append(
                    [e["size"], e["mesh"], e["vertices"], op, "error: " + o["error"][:60]] + [None] * 6
                )
                continue
            s = o.get("median_s")
            rows.append(
                [
                    e["size"],
                    e["mesh"],
                    e["vertices"],
                    op,
                    s,
                    o.get("cold_median_s"),
                    o.get("peak_mib"),
                    o.get("delta_mib"),
                    s / tp if s and tp and not op.startswith("trimesh") else None,
                    s / to if s and to and not op.startswith("trimesh") else None,
                    ", ".join(f"{k}={v}" for k, v in o.get("info", {}).items()),
                ]
            )
    lines.append(
        "\n"
        + md_table(
            [
                "size",
                "mesh",
                "vertices",
                "operation",
                "warm s",
                "cold s",
                "peak MiB",
                "growth MiB",
                "x trimesh PLY",
                "x trimesh OBJ",
                "notes",
            ],
            rows,
            "llrlrrrrrrl",
        )
    )
    (out_dir / "speed.md").write_text("\n".join(lines))


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--worker":
        worker(sys.argv[2:])
    else:
        raise SystemExit("use: python -m bench speed")

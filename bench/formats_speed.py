"""Read/write speed and peak memory of ``core.formats`` against trimesh (issue 2).

``python -m bench formats [--speed-runs N] [--out DIR]``

Inputs (made once per run, in a child process, into a temporary directory with trimesh's own
exporters, so that both libraries read the very same bytes):

- **100k**: ``turbineblade.ply`` (99,519 vertices, 199,034 triangles), loaded with
  ``process=False``;
- **1M**: ``dragon.ply`` subdivided twice with ``trimesh.remesh.subdivide`` (midpoint):
  800,000 vertices, 1,600,000 triangles;

each exported as binary PLY, GLB, OBJ and ASCII PLY (``trimesh.Trimesh.export``).

Every measurement runs in a fresh Python subprocess (``python -m bench.formats_speed --worker``)
that imports what it needs and reads the file bytes first, then times:

- **MeshMark**: ``core.formats.read_mesh(data, name)``, then ``doc.write(new)`` where ``new``
  moves 20 % of each part's vertices (seeded choice) by about 1e-5 bounding-box diagonals, as a
  watermark does (building ``new`` is not timed);
- **trimesh**: ``trimesh.load(file_obj=BytesIO(data), file_type=..., process=False)`` then
  ``.export(file_type=...)``.

Peak memory is the child's ``ru_maxrss`` at the end (whole process: interpreter, imports, input
bytes, the operation).  ``growth`` is the kernel's ``VmHWM`` minus the RSS just before the read
(the input bytes already loaded), i.e. what reading (and writing) adds.  The orchestrating
process stays small (it never loads a mesh), because a child's ``ru_maxrss`` starts at its
parent's high-water mark on ``execve``.  MeshMark and trimesh runs alternate; each figure is the
median of the runs.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import resource
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from bench.common import environment, json_child, md_table, mesh_path

#: (label, how the mesh is made)
SIZES = [("100k", "turbineblade.ply"), ("1M", "dragon.ply subdivided x2")]
#: (key, file suffix, trimesh export arguments, trimesh file_type)
FORMATS: list[tuple[str, str, dict[str, Any], str]] = [
    ("ply", "ply", {"file_type": "ply", "encoding": "binary"}, "ply"),
    ("glb", "glb", {"file_type": "glb"}, "glb"),
    ("obj", "obj", {"file_type": "obj"}, "obj"),
    ("ply-ascii", "ply", {"file_type": "ply", "encoding": "ascii"}, "ply"),
]
LABELS = {"ply": "PLY (binary LE)", "glb": "GLB", "obj": "OBJ", "ply-ascii": "PLY (ASCII)"}
#: target on MeshMark read+write / trimesh load+export (issue 2)
TARGETS = {"ply": 1.2, "glb": 1.2, "obj": 1.0}
MOVED_FRACTION = 0.2
MOVE_SCALE = 1e-5  # bounding-box diagonals
LIBS = ("meshmark", "trimesh")


# ---------------------------------------------------------------------------------------------
# child processes


def _status_kib(field: str) -> int:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith(field + ":"):
                return int(line.split()[1])
    raise RuntimeError(f"{field} not in /proc/self/status")


def make_inputs(out_dir: Path) -> None:
    """``--make DIR``: write the input files and ``inputs.json`` (runs in a child process)."""
    import numpy as np
    import trimesh
    from trimesh import remesh

    manifest: dict[str, Any] = {}
    for label, source in SIZES:
        name = source.split()[0]
        m: Any = trimesh.load(str(mesh_path(name)), force="mesh", process=False)
        v, f = np.asarray(m.vertices), np.asarray(m.faces)
        if "subdivided" in source:
            for _ in range(2):
                v, f = remesh.subdivide(v, f)
        mesh = trimesh.Trimesh(v, f, process=False)
        for key, suffix, kwargs, _ in FORMATS:
            data: Any = mesh.export(**kwargs)
            raw: bytes = data.encode("ascii") if isinstance(data, str) else data
            path = out_dir / f"{label}-{key}.{suffix}"
            path.write_bytes(raw)
            manifest[f"{label}/{key}"] = {
                "path": str(path),
                "bytes": len(raw),
                "vertices": len(v),
                "faces": len(f),
                "source": source,
            }
    (out_dir / "inputs.json").write_text(json.dumps(manifest, indent=1))


def _watermark_like(vertices: Any, rng: Any) -> Any:
    """A copy of ``vertices`` with 20 % of the rows moved by ~1e-5 bounding-box diagonals."""
    import numpy as np

    new = np.array(vertices, dtype=np.float64)
    n = len(new)
    if n == 0:
        return new
    diag = float(np.linalg.norm(new.max(axis=0) - new.min(axis=0))) or 1.0
    idx = rng.choice(n, max(1, int(n * MOVED_FRACTION)), replace=False)
    step = rng.standard_normal((idx.size, 3))
    step *= MOVE_SCALE * diag / np.linalg.norm(step, axis=1, keepdims=True)
    new[idx] += step
    return new


def worker(argv: list[str]) -> None:
    """``--worker LIB KEY PATH``: read + write once, print one JSON line."""
    lib, key, path = argv[0], argv[1], Path(argv[2])
    file_type = next(ft for k, _, _, ft in FORMATS if k == key)
    data = path.read_bytes()
    import io

    import numpy as np

    if lib == "meshmark":
        import core.formats.gltf  # imported before the clock starts
        import core.formats.obj
        import core.formats.ply  # noqa: F401
        from core.formats import read_mesh
    else:
        import trimesh
    before = _status_kib("VmRSS")
    info: dict[str, Any] = {}
    if lib == "meshmark":
        t0 = time.perf_counter()
        doc = read_mesh(data, path.name)
        t1 = time.perf_counter()
        hwm_read = _status_kib("VmHWM")
        rng = np.random.default_rng(2006)
        new = [_watermark_like(p.vertices, rng) for p in doc.parts]
        t2 = time.perf_counter()
        out = doc.write(new)
        t3 = time.perf_counter()
        info["moved"] = int(
            sum(np.any(n != p.vertices, axis=1).sum() for n, p in zip(new, doc.parts, strict=True))
        )
        info["welded_vertices"] = int(sum(len(p.vertices) for p in doc.parts))
    else:
        t0 = time.perf_counter()
        loaded = trimesh.load(file_obj=io.BytesIO(data), file_type=file_type, process=False)
        t1 = time.perf_counter()
        hwm_read = _status_kib("VmHWM")
        t2 = time.perf_counter()
        exported = loaded.export(file_type=file_type, **({"encoding": "ascii"} if key == "ply-ascii" else {}))
        out = exported.encode("ascii") if isinstance(exported, str) else exported
        t3 = time.perf_counter()
    result = {
        "lib": lib,
        "key": key,
        "read_s": t1 - t0,
        "write_s": t3 - t2,
        "before_kib": before,
        "hwm_read_kib": hwm_read,
        "hwm_kib": _status_kib("VmHWM"),
        "maxrss_kib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss,
        "bytes_in": len(data),
        "bytes_out": len(out),
        "same_size": len(out) == len(data),
        **info,
    }
    print(json.dumps(result))


def _child(args: list[str], timeout: float = 1800) -> dict[str, Any]:
    return json_child("bench.formats_speed", args, timeout)


# ---------------------------------------------------------------------------------------------
# orchestration


def _median(runs: list[dict[str, Any]], f: Any) -> float:
    return float(statistics.median(f(r) for r in runs))


def summarize(runs: list[dict[str, Any]]) -> dict[str, Any]:
    ok = [r for r in runs if "error" not in r]
    if not ok:
        return {"error": runs[-1].get("error", "?") if runs else "no run"}
    mib = 1 / 1024
    return {
        "runs": len(ok),
        "read_s": _median(ok, lambda r: r["read_s"]),
        "write_s": _median(ok, lambda r: r["write_s"]),
        "total_s": _median(ok, lambda r: r["read_s"] + r["write_s"]),
        "total_runs_s": [r["read_s"] + r["write_s"] for r in ok],
        "peak_mib": _median(ok, lambda r: r["maxrss_kib"]) * mib,
        "before_mib": _median(ok, lambda r: r["before_kib"]) * mib,
        "growth_read_mib": _median(ok, lambda r: r["hwm_read_kib"] - r["before_kib"]) * mib,
        "growth_mib": _median(ok, lambda r: r["hwm_kib"] - r["before_kib"]) * mib,
        "bytes_out": ok[0]["bytes_out"],
        "same_size": ok[0]["same_size"],
        **{k: ok[0][k] for k in ("moved", "welded_vertices") if k in ok[0]},
    }


def run(args: Any) -> dict[str, Any]:
    runs = max(3, int(getattr(args, "speed_runs", 3) or 3))
    load_start = os.getloadavg()
    started = _dt.datetime.now(_dt.UTC).strftime("%Y-%m-%d %H:%M:%S UTC")
    t_start = time.perf_counter()
    keys = [k for k, _, _, _ in FORMATS]
    results: dict[str, Any] = {}
    with tempfile.TemporaryDirectory(prefix="meshmark-formats-") as tmpd:
        tmp = Path(tmpd)
        made = _child(["--make", str(tmp)])
        if "error" in made:
            raise SystemExit(f"could not make the inputs: {made['error']}")
        inputs = json.loads((tmp / "inputs.json").read_text())
        for label, _ in SIZES:
            for key in keys:
                entry = inputs[f"{label}/{key}"]
                measured: dict[str, list[dict[str, Any]]] = {lib: [] for lib in LIBS}
                for _ in range(runs):
                    for lib in LIBS:  # alternate, so that load changes hit both alike
                        measured[lib].append(_child(["--worker", lib, key, entry["path"]]))
                results[f"{label}/{key}"] = {
                    **{k: v for k, v in entry.items() if k != "path"},
                    "size": label,
                    "format": key,
                    **{lib: summarize(measured[lib]) for lib in LIBS},
                }
                mm, tm = results[f"{label}/{key}"]["meshmark"], results[f"{label}/{key}"]["trimesh"]
                if "error" in mm or "error" in tm:
                    print(f"  formats: {label} {key}: error {mm.get('error') or tm.get('error')}", flush=True)
                else:
                    print(
                        f"  formats: {label} {key}: meshmark {mm['read_s']:.3f}+{mm['write_s']:.3f} s, "
                        f"trimesh {tm['read_s']:.3f}+{tm['write_s']:.3f} s, "
                        f"ratio {mm['total_s'] / tm['total_s']:.2f}",
                        flush=True,
                    )
    parent_peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    env = environment()  # imports trimesh and scipy: only now, to keep this process small meanwhile
    env["date"] = started
    result = {
        "env": env,
        "load_start": load_start,
        "load_end": os.getloadavg(),
        "parent_maxrss_mib": parent_peak,
        "runs": runs,
        "results": results,
        "elapsed_s": time.perf_counter() - t_start,
    }
    update_report(Path(args.out), "speed", speed_section(result))
    return result


# ---------------------------------------------------------------------------------------------
# report: bench/results/formats.md, one section per suite (each run replaces only its own section)

REPORT = "formats.md"
TITLE = (
    "# MeshMark mesh formats: speed, memory and fuzzing (issue 2)\n\n"
    "Made by `.venv/bin/python -m bench formats` (speed and memory, `bench/formats_speed.py`) and "
    "`.venv/bin/python -m bench fuzz-formats` (fuzzing, `bench/fuzz_formats.py`); each run rewrites "
    "only its own section below, whose header gives the exact command, date, machine and load.\n"
)


def update_report(out_dir: Path, section: str, text: str) -> Path:
    """Replace the ``section`` (``"speed"``, ``"fuzz"`` or ``"fuzz-encoded"``) of
    ``out_dir/formats.md`` with ``text``."""
    path = out_dir / REPORT
    old = path.read_text() if path.is_file() else TITLE
    sections: dict[str, str] = {}
    for name in ("speed", "fuzz", "fuzz-encoded"):
        begin, end = f"<!-- {name}:begin -->", f"<!-- {name}:end -->"
        if begin in old and end in old:
            sections[name] = old[old.index(begin) + len(begin) : old.index(end)].strip("\n")
    sections[section] = text.strip("\n")
    body = [TITLE]
    for name in ("speed", "fuzz", "fuzz-encoded"):
        if name in sections:
            body.append(f"<!-- {name}:begin -->\n{sections[name]}\n<!-- {name}:end -->\n")
    out_dir.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(body))
    return path


def run_header(env: dict[str, Any], load_start: tuple[float, ...], load_end: tuple[float, ...]) -> list[str]:
    """Date, machine, load, versions and command lines of one suite's section."""
    v = env["versions"]
    return [
        f"- Date: {env['date']}",
        f"- Machine: {env['platform']}, {env['cpu']}, {env['cpu_count']} CPUs"
        + (f", {env['memory_gib']} GiB RAM" if env.get("memory_gib") else "")
        + "; shared with other jobs running at the same time",
        "- Load average (1, 5, 15 min) at start: "
        + ", ".join(f"{x:.2f}" for x in load_start)
        + "; at end: "
        + ", ".join(f"{x:.2f}" for x in load_end),
        f"- Python {v['python']}, numpy {v['numpy']}, scipy {v['scipy']}, trimesh {v['trimesh']}",
        f"- Code: git {env['git']} (plus uncommitted changes, if any)",
        f"- Command: `.venv/bin/{env['command']}`",
    ]


def speed_section(result: dict[str, Any]) -> str:
    lines = ["## Read/write speed and memory against trimesh", ""]
    lines += run_header(result["env"], result["load_start"], result["load_end"])
    inputs = {e["size"]: e for e in result["results"].values()}
    lines += [
        f"- Wall time of the suite: {result['elapsed_s'] / 60:.1f} min; median of {result['runs']} runs per "
        "cell, each run a fresh subprocess; MeshMark and trimesh runs alternate.",
        "- Inputs, written once per run by trimesh's exporters into a temporary directory: "
        + "; ".join(
            f"**{s}** = {e['source']} ({e['vertices']:,} vertices, {e['faces']:,} triangles)"
            for s, e in inputs.items()
        )
        + ". Binary PLY is little-endian float32 + `uchar int` face lists, GLB float32 with uint32 "
        "indices, OBJ trimesh's 8-decimal `v`/`f` lines, ASCII PLY the same mesh as text.",
        "- **MeshMark** (MM): `core.formats.read_mesh(data, name)`, then `doc.write(new)` with 20 % of "
        "the welded vertices (seeded choice) moved by 1e-5 bounding-box diagonals, as a watermark does "
        "(building `new` is not timed). **trimesh** (tm): `trimesh.load(file_obj=BytesIO(data), "
        "file_type=..., process=False)` then `.export(file_type=...)` (ASCII PLY: `encoding='ascii'`).",
        "- Times: the operations only (imports done, file bytes in memory). Peak: the child's "
        "`ru_maxrss` (whole process: interpreter, numpy/trimesh imports, input bytes, the operation). "
        f"The orchestrating process never loads a mesh (its own peak: {result['parent_maxrss_mib']:.0f} "
        "MiB), since a child's `ru_maxrss` starts from its parent's high-water mark on `execve`.",
        "- Targets (issue 2): MM read+write within 1.2x of trimesh load+export for binary PLY and GLB, "
        "no slower than trimesh for OBJ; ASCII PLY has no target and is shown for reference.",
        "",
        speed_tables(result),
        "",
        "Per-run MM read+write / tm load+export seconds:",
        "",
    ]
    for key, e in result["results"].items():
        mm, tm = e["meshmark"], e["trimesh"]
        if "error" in mm or "error" in tm:
            continue
        lines.append(
            f"- {key}: MM "
            + ", ".join(f"{x:.3f}" for x in mm["total_runs_s"])
            + "; tm "
            + ", ".join(f"{x:.3f}" for x in tm["total_runs_s"])
        )
    return "\n".join(lines) + "\n"


def speed_tables(result: dict[str, Any]) -> str:
    rows, peak_rows, mem_rows = [], [], []
    for e in result["results"].values():
        mm, tm = e["meshmark"], e["trimesh"]
        label = f"{e['size']} {LABELS[e['format']]}"
        if "error" in mm or "error" in tm:
            rows.append([label, "error: " + str(mm.get("error") or tm.get("error"))[:80]] + [None] * 9)
            continue
        ratio = mm["total_s"] / tm["total_s"]
        target = TARGETS.get(e["format"])
        verdict = (f"<= {target}: " + ("met" if ratio <= target else "**missed**")) if target else "(none)"
        rows.append(
            [label, e["vertices"], e["bytes"] / 1e6, mm["read_s"], mm["write_s"], mm["total_s"],
             tm["read_s"], tm["write_s"], tm["total_s"], ratio, verdict]
        )
        peak_rows.append(
            [label, mm["before_mib"], mm["peak_mib"], mm["growth_mib"], tm["before_mib"], tm["peak_mib"],
             tm["growth_mib"], mm["peak_mib"] / tm["peak_mib"], mm["growth_mib"] / tm["growth_mib"]]
        )
        mb = e["bytes"] / 2**20
        if e["format"] in ("ply-ascii", "obj"):
            mem_rows.append(
                [label, mb, mm["growth_read_mib"], mm["growth_read_mib"] / mb, mm["growth_mib"],
                 mm["growth_mib"] / mb, mm["peak_mib"], tm["growth_mib"] / mb]
            )
    out = "Time (seconds, medians):\n\n" + md_table(
        ["size / format", "vertices", "file MB", "MM read", "MM write", "MM read+write", "tm load",
         "tm export", "tm load+export", "ratio MM / tm", "target"],
        rows,
        "lrrrrrrrrrl",
    )
    out += (
        "\nPeak memory (MiB, medians). *before*: RSS after the imports and reading the file bytes; "
        "*peak*: `ru_maxrss` at the end; *growth*: high-water mark minus *before*:\n\n"
    )
    out += md_table(
        ["size / format", "MM before", "MM peak", "MM growth", "tm before", "tm peak", "tm growth",
         "peak ratio MM / tm", "growth ratio MM / tm"],
        peak_rows,
        "lrrrrrrrr",
    )
    out += "\nText formats, memory per MiB of input (growth as above, the input bytes already in memory):\n\n"
    out += md_table(
        ["size / format", "input MiB", "MM read growth MiB", "read growth / input MiB",
         "MM read+write growth MiB", "read+write growth / input MiB", "MM whole-process peak MiB",
         "tm load+export growth / input MiB"],
        mem_rows,
        "lrrrrrrr",
    )
    return out


if __name__ == "__main__":
    if len(sys.argv) > 2 and sys.argv[1] == "--worker":
        worker(sys.argv[2:])
    elif len(sys.argv) > 2 and sys.argv[1] == "--make":
        make_inputs(Path(sys.argv[2]))
    else:
        raise SystemExit("use: python -m bench formats")

"""Robustness: embed a 64-bit payload, attack the marked mesh, detect blind, count recoveries.

For every mesh x method x strength, one seeded random 64-bit payload is embedded with a fixed
key through :func:`core.api.embed_file`.  The marked file is read back with the engine's reader,
every attack of :data:`bench.attacks.ATTACKS` is applied to its arrays
(:func:`bench.attacks.attack_parts`: files with several meshes stay several meshes), and the
result is written as a binary PLY with ``double`` coordinates, or as GLB with one mesh per part
for files with several meshes (:func:`bench.attacks.write_parts`), or, for the round trips, as
the file trimesh's exporter writes, and handed to :func:`core.api.detect_file` with the key and
the method, without the payload: "recovered" means ``detected`` (CRC verified) and the returned
payload equals the embedded one.  A second, informed detection with the payload given yields
the bit error rate (``bit_errors``) and the owner's verification.  Files with several meshes
are also cut down to each single mesh ("extract").
"""

from __future__ import annotations

import multiprocessing as mp
import time
import traceback
import zlib
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np

from bench import attacks as A
from bench.common import (
    KEY,
    METHODS,
    QUICK_MESHES,
    available_meshes,
    environment,
    header,
    load_mesh,
    md_table,
    mesh_path,
    random_payload,
    save_json,
    write_ply_double,
)
from bench.metrics import Reliability, ber, surface_distance

LARGE = 10_000  # plots average over meshes with at least this many vertices


def _detect(data: bytes, filename: str, method: str, payload: str | None = None):
    """``detect_file`` with the bench key; an exception is a failed detection, not a crash."""
    from core.api import detect_file

    try:
        return detect_file(data, KEY, filename=filename, method=method, payload=payload), None
    except Exception as e:
        return None, f"{type(e).__name__}: {e}"[:200]


def check(
    data: bytes, filename: str, detect_method: str, truth: str, rel: Reliability, **info
) -> dict[str, Any]:
    """Blind detection (key + method) for the recovery rate, then informed detection (the expected
    payload given) for the bit error rate, the owner's verification and the confidence calibration."""
    rec = dict(info)
    t = time.perf_counter()
    blind, err = _detect(data, filename, detect_method)
    rec["detect_s"] = time.perf_counter() - t
    informed, err2 = _detect(data, filename, detect_method, truth)
    rec["error"] = err or err2
    rec.update(
        detected=bool(blind and blind.detected),
        crc_ok=bool(blind and blind.crc_ok),
        recovered=bool(blind and blind.detected and blind.payload == truth),
        carriers=int(blind.carriers) if blind else 0,
        copies=float(blind.copies) if blind else 0.0,
        fpp=float(blind.false_positive_probability) if blind else None,
        verified=bool(informed and informed.detected),
        p_value=informed.p_value if informed else None,
    )
    if informed is not None and informed.bit_errors is not None:
        rec["ber"] = informed.bit_errors / len(truth)
        rel.add(informed.bit_confidence, informed.payload, truth)
    else:
        rec["ber"] = ber(blind.payload if blind else None, truth)
    return rec


def run_unit(job: dict[str, Any]) -> dict[str, Any]:
    """Everything for one mesh and one method (all strengths, all attacks)."""
    from core.api import embed_file

    name, method, seed = job["mesh"], job["method"], job["seed"]
    data = mesh_path(name).read_bytes()
    orig = load_mesh(data, name)
    payload = random_payload(np.random.default_rng([seed, zlib.crc32(name.encode())]), 64)
    rel = Reliability()
    out: dict[str, Any] = {
        "mesh": name,
        "method": method,
        "vertices": orig.n_vertices,
        "faces": orig.n_faces,
        "parts": len(orig.parts),
        "payload": payload,
        "embeds": [],
        "records": [],
        "errors": [],
    }
    default_strength = None
    for slabel in job["strengths"]:
        if slabel == "default":
            strength = None
        elif default_strength is None:
            continue
        else:
            strength = min(1.0, job["strong_factor"] * default_strength)
        t = time.perf_counter()
        try:
            emb = embed_file(data, KEY, filename=name, payload=payload, method=method, strength=strength)
        except Exception as e:
            out["errors"].append(f"embed {slabel}: {type(e).__name__}: {e}")
            out["embeds"].append({"strength_label": slabel, "error": f"{type(e).__name__}: {e}"[:300]})
            continue
        t_embed = time.perf_counter() - t
        rep = emb.report
        if slabel == "default":
            default_strength = rep.strength
        marked = load_mesh(emb.data, name)
        sd = surface_distance(
            orig.vertices, orig.faces, marked.vertices, marked.faces, samples=job["metric_samples"], seed=seed
        )
        base = {"mesh": name, "method": method, "strength_label": slabel, "strength": rep.strength}
        clean = check(
            emb.data,
            name,
            method,
            payload,
            rel,
            **base,
            attack="file",
            level="marked file",
            seed=0,
            label="marked file",
        )
        out["records"].append(clean)
        out["embeds"].append(
            {
                "strength_label": slabel,
                "strength": rep.strength,
                "carriers": rep.carriers,
                "copies": rep.copies,
                "skipped": rep.skipped,
                "vertices_moved": rep.vertices_moved,
                "rms_displacement": rep.rms_displacement,
                "max_displacement": rep.max_displacement,
                "report_hausdorff": rep.hausdorff,
                "mrms": sd.mrms,
                "hausdorff": sd.hausdorff,
                "embed_s": t_embed,
                "detect_s": clean["detect_s"],
                "clean_recovered": clean["recovered"],
            }
        )
        for ai, spec in enumerate(A.ATTACKS.values()):
            if job["attacks"] and spec.name not in job["attacks"]:
                continue
            levels = spec.quick_levels if job["quick"] else spec.levels
            for li, level in enumerate(levels):
                for s in range(job["seeds"] if spec.random else 1):
                    arng = np.random.default_rng([seed, ai, li, s, zlib.crc32(name.encode())])
                    try:
                        if spec.name == "roundtrip":
                            adata, afile = A.export_bytes(
                                marked.vertices, marked.faces, str(level), marked.parts
                            )
                            nv = None
                        else:
                            attacked = A.attack_parts(spec.name, marked.parts, level, arng)
                            adata, afile = A.write_parts(attacked, marked.names)
                            nv = sum(len(v) for v, _ in attacked)
                    except Exception as e:
                        out["errors"].append(f"{spec.name} {level}: {type(e).__name__}: {e}")
                        continue
                    out["records"].append(
                        check(
                            adata,
                            afile,
                            method,
                            payload,
                            rel,
                            **base,
                            attack=spec.name,
                            level=level,
                            label=spec.label(level),
                            seed=s,
                            vertices_after=nv,
                        )
                    )
        if len(marked.parts) > 1 and (not job["attacks"] or "extract" in job["attacks"]):
            for k, (pv, pf) in enumerate(marked.parts):
                out["records"].append(
                    check(
                        write_ply_double(pv, pf),
                        "part.ply",
                        method,
                        payload,
                        rel,
                        **base,
                        attack="extract",
                        level=k,
                        label=f"{marked.names[k]} ({len(pv)} v)",
                        seed=0,
                        vertices_after=len(pv),
                    )
                )
    out["reliability"] = rel.to_dict()
    return out


def _safe_unit(job: dict[str, Any]) -> dict[str, Any]:
    try:
        return run_unit(job)
    except Exception:
        return {
            "mesh": job["mesh"],
            "method": job["method"],
            "fatal": traceback.format_exc(),
            "records": [],
            "embeds": [],
            "errors": [],
            "vertices": 0,
        }


def run(args) -> dict[str, Any]:
    quick = args.quick
    meshes = available_meshes(args.meshes or (QUICK_MESHES if quick else None))
    strengths = ["default"] if quick else ["default", "strong"]
    jobs = [
        {
            "mesh": m,
            "method": meth,
            "seed": args.seed,
            "quick": quick,
            "strengths": strengths,
            "strong_factor": 2.0,
            "seeds": 1 if quick else args.attack_seeds,
            "attacks": args.attacks,
            "metric_samples": 20_000 if quick else 100_000,
        }
        for m in meshes
        for meth in METHODS
    ]
    sizes = {m: mesh_path(m).stat().st_size for m in meshes}
    jobs.sort(key=lambda j: -sizes[j["mesh"]])
    env = environment()
    t0 = time.perf_counter()
    units: list[dict[str, Any]] = []
    out_dir = Path(args.out)
    if args.jobs > 1 and len(jobs) > 1:
        with mp.get_context("spawn").Pool(args.jobs, maxtasksperchild=1) as pool:
            for u in pool.imap_unordered(_safe_unit, jobs):
                units.append(u)
                print(
                    f"  robustness: {u['mesh']} {u['method']} done ({len(units)}/{len(jobs)}, "
                    f"{time.perf_counter() - t0:.0f} s)",
                    flush=True,
                )
    else:
        for j in jobs:
            units.append(_safe_unit(j))
            print(
                f"  robustness: {j['mesh']} {j['method']} done ({len(units)}/{len(jobs)}, "
                f"{time.perf_counter() - t0:.0f} s)",
                flush=True,
            )
    result = {
        "env": env,
        "quick": quick,
        "seed": args.seed,
        "elapsed_s": time.perf_counter() - t0,
        "units": units,
        "strong_factor": 2.0,
    }
    save_json(out_dir / "robustness.json", result)
    write_report(result, out_dir)
    return result


# ---------------------------------------------------------------------------------------------
# report


def _agg(records: list[dict[str, Any]]) -> tuple[float, float, float, int]:
    """Recovery rate (blind), verification rate (informed), mean BER, count."""
    n = len(records)
    if not n:
        return float("nan"), float("nan"), float("nan"), 0
    return (
        sum(r["recovered"] for r in records) / n,
        sum(r.get("verified", False) for r in records) / n,
        sum(r["ber"] for r in records) / n,
        n,
    )


def _cell(records: list[dict[str, Any]]) -> str:
    rate, ver, mber, n = _agg(records)
    return f"{rate:.0%} / {ver:.0%} / {mber:.3f} ({n})" if n else "–"


def _level_key(attack: str, level: Any) -> tuple:
    spec = A.ATTACKS.get(attack)
    if spec is not None and level in spec.levels:
        return (spec.levels.index(level),)
    return (999, str(level))


def write_report(result: dict[str, Any], out_dir: Path) -> None:
    units = [u for u in result["units"] if "fatal" not in u]
    records = [r for u in units for r in u["records"]]
    configs = sorted(
        {(r["method"], r["strength_label"]) for r in records},
        key=lambda c: (METHODS.index(c[0]), c[1] != "default"),
    )
    lines = [
        header(
            "MeshMark robustness",
            result["env"],
            [
                f"- Seed {result['seed']}; {'quick slice' if result['quick'] else 'full grid'}; "
                f"wall time {result['elapsed_s'] / 60:.1f} min",
                "- Key fixed, 64-bit random payload per mesh, detection blind (key + method, no payload). "
                "Recovered = detected (CRC verified) and payload equal.",
                "- Strengths: `default` = the engine's default; `strong` = "
                f"{result['strong_factor']:g} x default.",
                "- Attacked meshes are written as binary PLY with double coordinates; files with several "
                "meshes as GLB with one mesh per part (float32; OBJ/PLY readers give one part); "
                "round trips "
                "are trimesh's own exports (OBJ 8 digits, PLY/STL/GLB float32, OFF 10 digits).",
            ],
        )
    ]
    fatal = [u for u in result["units"] if "fatal" in u]
    if fatal:
        lines.append(
            "\n**Units that crashed:** " + ", ".join(f"{u['mesh']}/{u['method']}" for u in fatal) + "\n"
        )

    lines.append("\n## Embedding distortion\n")
    lines.append(
        "Displacements relative to the bounding-box diagonal. RMS/max: the engine's report; "
        "MRMS/Hausdorff: measured here between the original and the marked surfaces "
        "(exact point-to-triangle distances from 100k area-uniform samples + vertices).\n"
    )
    rows = []
    for u in sorted(units, key=lambda u: (u["vertices"], u["mesh"], METHODS.index(u["method"]))):
        for e in u["embeds"]:
            if "error" in e:
                rows.append(
                    [
                        u["mesh"],
                        u["vertices"],
                        u["method"],
                        e["strength_label"],
                        "embed failed: " + e["error"][:60],
                    ]
                    + [None] * 9
                )
                continue
            rows.append(
                [
                    u["mesh"],
                    u["vertices"],
                    u["method"],
                    e["strength_label"],
                    e["strength"],
                    e["carriers"],
                    e["copies"],
                    e["rms_displacement"],
                    e["max_displacement"],
                    e["mrms"],
                    e["hausdorff"],
                    e["embed_s"],
                    e["detect_s"],
                    e["clean_recovered"],
                ]
            )
    lines.append(
        md_table(
            [
                "mesh",
                "vertices",
                "method",
                "strength",
                "value",
                "carriers",
                "copies",
                "RMS disp.",
                "max disp.",
                "MRMS",
                "Hausdorff",
                "embed s",
                "detect s",
                "clean recovered",
            ],
            rows,
            "lrllrrrrrrrrrl",
        )
    )

    lines.append("\n## Recovery rate and mean BER per attack (all meshes)\n")
    lines.append(
        "Each cell: **recovered** (blind: key + method only; detected with the right payload) / "
        "**verified** (informed: the expected payload given to the detector, accepted when its p-value is "
        "tiny) / **mean BER** of the 64 payload bits from the informed detection (number of detections).\n"
    )
    groups: dict[tuple[str, Any], dict[tuple[str, str], list]] = defaultdict(lambda: defaultdict(list))
    labels: dict[tuple[str, Any], str] = {}
    for r in records:
        k = (r["attack"], r["level"] if r["attack"] != "extract" else "each mesh")
        groups[k][(r["method"], r["strength_label"])].append(r)
        labels[k] = r["label"] if r["attack"] != "extract" else "each mesh alone"
    order = ["file"] + list(A.ATTACKS) + ["extract"]
    keys = sorted(groups, key=lambda k: (order.index(k[0]) if k[0] in order else 99, _level_key(*k)))
    rows = []
    for k in keys:
        row: list[Any] = [k[0], labels[k]]
        for c in configs:
            row.append(_cell(groups[k].get(c, [])))
        rows.append(row)
    lines.append(
        md_table(["attack", "level"] + [f"{m} {s}" for m, s in configs], rows, "ll" + "r" * len(configs))
    )

    lines.append("\n## Per-bit confidence reliability\n")
    lines.append(
        "Informed detections (expected payload given, so a payload is returned even when not accepted): the "
        "detector's `bit_confidence` binned, against the "
        "fraction of those bits that were right. A calibrated detector has accuracy ~ mean confidence.\n"
    )
    for meth in METHODS:
        rel = Reliability()
        for u in units:
            if u["method"] == meth and "reliability" in u:
                rel.merge(Reliability.from_dict(u["reliability"]))
        lines.append(
            f"\n**{meth}**\n\n"
            + md_table(["confidence bin", "bits", "mean confidence", "accuracy"], rel.rows())
        )

    lines.append("\n## Per mesh\n")
    lines.append(
        "Recovered / verified / mean BER (count) per attack and level for each mesh, default and "
        "strong (2 x default) strength.\n"
    )
    for u in sorted(units, key=lambda u: (u["vertices"], u["mesh"], METHODS.index(u["method"]))):
        per: dict[tuple[str, Any], dict[str, list]] = defaultdict(lambda: defaultdict(list))
        for r in u["records"]:
            per[(r["attack"], r["level"])][r["strength_label"]].append(r)
        rows = []
        for k in sorted(per, key=lambda k: (order.index(k[0]) if k[0] in order else 99, _level_key(*k))):
            d = per[k]
            lab = d[next(iter(d))][0]["label"]
            cell = []
            for s in ("default", "strong"):
                if s in d:
                    cell.append(_cell(d[s]))
            rows.append([k[0], lab] + cell + [""] * (2 - len(cell)))
        lines.append(f"\n### {u['mesh']} — {u['method']} ({u['vertices']:,} vertices)\n\n")
        lines.append(md_table(["attack", "level", "default", "strong"], rows, "llrr"))
        if u["errors"]:
            lines.append("\nErrors: " + "; ".join(u["errors"][:5]) + "\n")
    errs = [r for r in records if r.get("error")]
    if errs:
        lines.append("\n## Detector exceptions on attacked files\n\n")
        seen: dict[str, int] = defaultdict(int)
        for r in errs:
            seen[f"{r['attack']}: {r['error'][:120]}"] += 1
        lines.append(md_table(["attack: error", "count"], [[k, v] for k, v in sorted(seen.items())], "lr"))
    lines.append("\n## Plots\n\n")
    pngs = plot(result, out_dir)
    for p in pngs:
        lines.append(f"![{p}]({p})\n")
    (out_dir / "robustness.md").write_text("\n".join(lines))


def plot(result: dict[str, Any], out_dir: Path) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    units = [u for u in result["units"] if "fatal" not in u]
    large = [u for u in units if u["vertices"] >= LARGE]
    pool, scope = (large, f"meshes with >= {LARGE:,} vertices") if large else (units, "meshes (all run)")
    files = []
    for spec in A.ATTACKS.values():
        recs = [r for u in pool for r in u["records"] if r["attack"] == spec.name]
        if not recs:
            continue
        fig, ax = plt.subplots(figsize=(7, 4.5))
        levels = [lv for lv in spec.levels if any(r["level"] == lv for r in recs)]
        numeric = all(isinstance(lv, (int, float)) for lv in levels) and len(levels) > 1
        configs = sorted(
            {(r["method"], r["strength_label"]) for r in recs},
            key=lambda c: (METHODS.index(c[0]), c[1] != "default"),
        )
        width = 0.8 / max(len(configs), 1)
        for ci, (meth, sl) in enumerate(configs):
            ys = []
            for lv in levels:
                sel = [
                    r for r in recs if r["level"] == lv and r["method"] == meth and r["strength_label"] == sl
                ]
                # average per mesh first, then over meshes, so each mesh weighs the same
                per = defaultdict(list)
                for r in sel:
                    per[r["mesh"]].append(r["recovered"])
                ys.append(100 * np.mean([np.mean(v) for v in per.values()]) if per else np.nan)
            style = {"color": "tab:blue" if meth == "ellipsoids" else "tab:orange"}
            lab = f"{meth} ({sl} strength)"
            if numeric:
                xs = [100 * lv if spec.name in ("uniform_noise", "crop", "simplify") else lv for lv in levels]
                ax.plot(xs, ys, marker="o", linestyle="-" if sl == "default" else "--", label=lab, **style)
            else:
                xs = np.arange(len(levels)) + (ci - (len(configs) - 1) / 2) * width
                ax.bar(xs, ys, width, label=lab, alpha=1.0 if sl == "default" else 0.5, **style)
        if numeric:
            unit = spec.unit + (" (%)" if spec.name in ("uniform_noise", "crop", "simplify") else "")
            ax.set_xlabel(unit)
            if spec.name == "gaussian_noise":
                ax.set_xscale("log")
        else:
            ax.set_xticks(np.arange(len(levels)))
            ax.set_xticklabels([spec.label(lv) for lv in levels])
            ax.set_xlabel(spec.unit)
        ax.set_ylabel("payload recovered (%)")
        ax.set_ylim(-3, 103)
        ax.grid(True, alpha=0.3)
        ax.set_title(
            f"{spec.title}\nrecovery of a 64-bit payload, mean over {len({r['mesh'] for r in recs})} {scope}",
            fontsize=10,
        )
        ax.legend(fontsize=8, loc="best")
        fig.tight_layout()
        fname = f"robustness_{spec.name}.png"
        fig.savefig(out_dir / fname, dpi=110)
        plt.close(fig)
        files.append(fname)
    return files

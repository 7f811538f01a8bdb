"""A short summary of the latest results (``bench/results/*.json``), to paste into the README."""

from __future__ import annotations

import json
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np

from bench import attacks as A
from bench.common import METHODS, environment, header, md_table

#: attack -> levels shown in the summary (a mild and a hard one)
SHOWN = {
    "similarity": (1,),
    "reorder": (1,),
    "uniform_noise": (0.001, 0.005),
    "gaussian_noise": (0.003, 0.03),
    "smoothing": (10, 50),
    "quantize": (10, 8),
    "simplify": (0.1, 0.5),
    "subdivide": ("midpoint", "loop"),
    "crop": (0.1, 0.5),
    "roundtrip": ("obj", "stl"),
}


def _load(out_dir: Path, name: str) -> dict[str, Any] | None:
    p = out_dir / f"{name}.json"
    return json.loads(p.read_text()) if p.is_file() else None


def run(args) -> str:
    out_dir = Path(args.out)
    sources = []
    for name in ("robustness", "paper", "false_positives", "speed"):
        d = _load(out_dir, name)
        if d and "env" in d:
            sources.append(
                f"  - {name}: {d['env']['date']}, git {d['env'].get('git', '?')}, `{d['env']['command']}`"
            )
    lines = [
        header(
            "MeshMark benchmark summary",
            environment(),
            [
                "- Full tables and plots: [robustness](robustness.md), [paper](paper.md), "
                "[false positives](false_positives.md), [speed](speed.md).",
                "- Data from:",
                *sources,
            ],
        )
    ]
    rob = _load(out_dir, "robustness")
    if rob:
        units = [u for u in rob["units"] if "fatal" not in u]
        large = [u for u in units if u["vertices"] >= 10_000] or units
        scope = (
            "meshes ≥ 10k vertices"
            if len(large) < len(units) or units[0]["vertices"] >= 10_000
            else "all meshes"
        )
        lines.append(
            f"\n## Robustness (64-bit payload recovered, default strength, {scope}; "
            f"{'quick slice' if rob['quick'] else 'full grid'})\n"
        )
        dist = defaultdict(list)
        for u in large:
            for e in u["embeds"]:
                if e.get("strength_label") == "default" and "mrms" in e:
                    dist[u["method"]].append(e["mrms"])
        rows = []
        for spec in A.ATTACKS.values():
            for lv in SHOWN.get(spec.name, ()):
                row: list[Any] = [spec.title, spec.label(lv)]
                any_ = False
                for meth in METHODS:
                    per = defaultdict(list)
                    for u in large:
                        if u["method"] != meth:
                            continue
                        for r in u["records"]:
                            if (
                                r["attack"] == spec.name
                                and r["level"] == lv
                                and r["strength_label"] == "default"
                            ):
                                per[u["mesh"]].append(r["recovered"])
                    if per:
                        any_ = True
                        row.append(f"{100 * np.mean([np.mean(v) for v in per.values()]):.0f} %")
                    else:
                        row.append(None)
                if any_:
                    rows.append(row)
        if dist:
            rows.insert(
                0,
                ["Embedding distortion (MRMS, median)", "-"]
                + [f"{np.median(dist[m]):.2e}" if dist[m] else None for m in METHODS],
            )
        lines.append(md_table(["attack", "level"] + list(METHODS), rows, "llrr"))
    pap = _load(out_dir, "paper")
    if pap:
        from bench.paper import breaking_point, fig21_curves

        lines.append("\n## Bors 2006 comparison\n")
        sink = {t["method"]: t for t in pap["tables"] if t["mesh"] == "sink.3ds"}
        rows = []
        for meth, paper in (("ellipsoids", "98 / 2"), ("planes", "66 / 1")):
            t = sink.get(meth, {})
            keys = t.get("keys", [])
            ok = [k for k in keys if "error" not in k]
            cap = t.get("capacity", {})
            cell = f"{ok[0]['carriers']} / {ok[0]['copies']:.2f}" if ok else "embedding refused"
            if len(ok) < len(keys):
                cell += f" ({len(keys) - len(ok)} of {len(keys)} keys refused)"
            if "carriers" in cap:
                cell += f"; capacity_file {cap['carriers']} / {cap['copies']:.2f}"
            rows.append([f"Sink carriers / copies ({meth})", paper, cell])
        curves = fig21_curves(pap)
        for meth, paper in (("ellipsoids", "≈ 0.75"), ("planes", "≈ 0.15")):
            c = curves.get(("all", meth))
            rows.append(
                [
                    f"Gaussian noise breaking point E ({meth}, bit rate ≥ 90 %)",
                    paper,
                    breaking_point(c) if c else None,
                ]
            )
        lines.append(md_table(["quantity", "paper", "MeshMark"], rows, "lrr"))
    fp = _load(out_dir, "false_positives")
    if fp:
        from bench.false_positives import summarize

        s = summarize(fp)
        lines.append("\n## False positives\n")
        lines.append(
            md_table(
                [
                    "wrong-key detections",
                    "false detections",
                    "FPP reported with a positive answer",
                    "expected false detections",
                ],
                [[s["n"], s["false"], s["claimed_fpp"], s["expected_claimed"]]],
                "rrrr",
            )
        )
    sp = _load(out_dir, "speed")
    if sp:
        lines.append("\n## Speed (median seconds; peak RSS MiB)\n")
        rows = []
        for e in sp["sizes"]:
            o = e["ops"]

            def cell(op, o=o):
                x = o.get(op, {})
                return f"{x['median_s']:.2f} s ({x['peak_mib']:.0f} MiB)" if "median_s" in x else None

            rows.append(
                [
                    f"{e['size']} ({e['vertices']:,} v)",
                    cell("embed"),
                    cell("detect"),
                    cell("capacity"),
                    cell("trimesh-ply"),
                    cell("trimesh-obj"),
                ]
            )
        lines.append(
            md_table(
                ["mesh", "embed", "detect", "capacity", "trimesh load+PLY", "trimesh load+OBJ"],
                rows,
                "lrrrrr",
            )
        )
    text = "\n".join(lines)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "summary.md").write_text(text)
    return text

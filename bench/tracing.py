"""Leak tracing (issue 18): who leaked this copy, and how sure.

For each shared mesh of >= 10k vertices, one asset with ``--recipients`` recipients (random
codewords, :mod:`core.fingerprint`); ``--copies`` of them get a real marked file
(:func:`core.fingerprint.embed_codeword`).  Cases:

* one leaked copy: untouched, uniform noise 0.3 %, Laplacian smoothing 0.1 x 10, crop to 50 %
  (a plane cut along a random direction);
* averages, vertex by vertex, of 2 and of 3 different copies (every pair / triple up to
  ``--collusions``), and 2 copies swapping halves (a random plane through the centroid);
* innocents only: the unmarked mesh under a fresh key per trial, a marked copy read with a wrong
  key, and a copy of another asset (another mesh, noise 0.1 %) traced against this asset's
  registry; each trial also draws fresh innocent codewords.

A recipient is accused when the false-accusation probability of its score (Hoeffding + union
bound over the registry and the decoding variants) is <= 1e-9.  Then the registry: the same trace
through SQLite and PostgreSQL (same ranking, same scores) and the time of the scoring step with
100k copies registered, beyond the detection's own analysis.
"""

from __future__ import annotations

import argparse
import datetime as dt
import itertools
import math
import os
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench.attacks import crop, laplacian_smoothing, uniform_noise
from bench.common import SHARED_MESHES, environment, header, md_table, mesh_path, save_json
from core.analysis import analyse, prepare
from core.fingerprint import (
    VARIANTS,
    codeword_votes,
    correlation_scores,
    embed_codeword,
    false_accusation,
    pack_codeword,
    random_codeword,
    score_threshold,
)
from core.formats import read_mesh
from core.options import DEFAULT_METHOD, Options

#: the shared meshes of >= 10k vertices (SHARED_MESHES is ordered by size)
MESHES = SHARED_MESHES[SHARED_MESHES.index("rocker-arm.obj") :]
THRESHOLD = 1e-9
SINGLE = {
    "untouched": lambda v, f, rng: (v, f),
    "noise 0.3 %": lambda v, f, rng: uniform_noise(v, f, 0.003, rng),
    "smoothing 0.1 x 10": lambda v, f, rng: laplacian_smoothing(v, f, 10, rng),
    "crop to 50 %": lambda v, f, rng: crop(v, f, 0.5, rng),
}


class Asset:
    """One mesh, its registry of codewords and the marked copies of the first few recipients."""

    def __init__(self, name: str, key: str, recipients: int, copies: int, rng: np.random.Generator) -> None:
        self.name, self.key = name, key
        data = mesh_path(name).read_bytes()
        self.data = data
        t = time.perf_counter()
        first = embed_codeword(data, Options(key=key), rng=rng, filename=name)
        self.embed_seconds = time.perf_counter() - t
        self.L = len(first.codeword)
        self.report = first.file.report
        self.codewords = [first.codeword] + [random_codeword(rng, self.L) for _ in range(recipients - 1)]
        self.packed = np.stack([np.frombuffer(pack_codeword(c), np.uint8) for c in self.codewords])
        files = [first.file.data] + [
            embed_codeword(data, Options(key=key), codeword=self.codewords[i], filename=name).file.data
            for i in range(1, copies)
        ]
        parts = [read_mesh(b, name).parts for b in files]
        if any(len(p) != 1 for p in parts):
            raise ValueError(f"{name}: one mesh part expected")
        self.faces = parts[0][0].faces
        self.copies = [p[0].vertices for p in parts]
        cover = read_mesh(data, name).parts[0]
        self.cover = cover.vertices
        self.prepared = prepare([cover.vertices], [cover.faces])[0]

    def scores(
        self, v: np.ndarray, f: np.ndarray, key: str | None = None, packed: np.ndarray | None = None
    ) -> np.ndarray:
        """Scores of every registered codeword (or of ``packed``) for the mesh ``(v, f)``."""
        same = f is self.faces
        adj, lab = self.prepared if same else (None, None)
        a = analyse(v, f, key or self.key, DEFAULT_METHOD, adj=adj, labels=lab)
        votes = codeword_votes([a], key or self.key, self.L)
        return correlation_scores(votes, self.packed if packed is None else packed, self.L)


def _verdict(scores: np.ndarray, guilty: set[int], tests: int) -> dict[str, Any]:
    fap = false_accusation(scores, tests)
    accused = set(np.flatnonzero(fap <= THRESHOLD).tolist())
    top = int(np.argmax(scores))
    return {
        "accused": sorted(accused),
        "guilty_named": len(accused & guilty),
        "innocent_accused": len(accused - guilty),
        "top_is_guilty": top in guilty,
        "min_guilty_score": float(min(scores[i] for i in guilty)) if guilty else None,
        "max_innocent_score": float(np.delete(scores, sorted(guilty)).max()),
        "best_fap": float(fap.min()),
    }


def run_asset(
    asset: Asset, other: Asset, args: argparse.Namespace, rng: np.random.Generator
) -> dict[str, Any]:
    tests = len(VARIANTS) * len(asset.codewords)
    out: dict[str, Any] = {
        "mesh": asset.name,
        "vertices": len(asset.cover),
        "carriers": asset.report.carriers,
        "codeword_bits": asset.L,
        "recipients": len(asset.codewords),
        "rms_displacement": asset.report.rms_displacement,
        "embed_seconds": asset.embed_seconds,
        "score_threshold": score_threshold(THRESHOLD, tests),
        "cases": {},
    }
    n = len(asset.copies)
    for case, attack in SINGLE.items():
        rows = []
        for t in range(n if case == "untouched" else args.single_trials):
            i = t % n
            v, f = attack(asset.copies[i], asset.faces, rng)
            f = asset.faces if f.shape == asset.faces.shape and np.array_equal(f, asset.faces) else f
            rows.append(_verdict(asset.scores(v, f), {i}, tests))
        out["cases"][case] = rows
    for c in (2, 3):
        groups = list(itertools.combinations(range(n), c))
        rng.shuffle(groups)
        rows = []
        for g in groups[: args.collusions]:
            v = sum(asset.copies[i] for i in g) / c
            rows.append(_verdict(asset.scores(v, asset.faces), set(g), tests))
        out["cases"][f"average of {c}"] = rows
    # two colluders swap regions: one's vertices on one side of a random plane through the
    # centroid, the other's on the other side
    pairs = list(itertools.combinations(range(n), 2))
    rng.shuffle(pairs)
    rows = []
    for i, j in pairs[: args.collusions]:
        d = rng.normal(size=3)
        side = (asset.cover - asset.cover.mean(axis=0)) @ d > 0
        v = np.where(side[:, None], asset.copies[i], asset.copies[j])
        rows.append(_verdict(asset.scores(v, asset.faces), {i, j}, tests))
    out["cases"]["halves of 2 swapped"] = rows
    # innocents only: fresh innocent codewords every trial
    innocents: dict[str, list[dict[str, Any]]] = {
        "unmarked, fresh key": [],
        "wrong key": [],
        "copy of another asset": [],
    }
    for t in range(args.innocent_trials):
        packed = np.stack(
            [
                np.frombuffer(pack_codeword(random_codeword(rng, asset.L)), np.uint8)
                for _ in range(len(asset.codewords))
            ]
        )
        key = f"innocent-{t}-{rng.integers(2**62)}"
        cases = {
            "unmarked, fresh key": (asset.cover, asset.faces, key, asset),
            "wrong key": (asset.copies[t % n], asset.faces, key, asset),
            "copy of another asset": (
                uniform_noise(other.copies[t % len(other.copies)], other.faces, 0.001, rng)[0],
                other.faces,
                asset.key,
                other,
            ),
        }
        for case, (v, f, k, owner) in cases.items():
            adj, lab = owner.prepared
            a = analyse(v, f, k, DEFAULT_METHOD, adj=adj, labels=lab)
            s = correlation_scores(codeword_votes([a], k, asset.L), packed, asset.L)
            innocents[case].append(
                {
                    "max_innocent_score": float(s.max()),
                    "innocent_accused": int((false_accusation(s, tests) <= THRESHOLD).sum()),
                    "above_3": int((s >= 3).sum()),
                    "above_4": int((s >= 4).sum()),
                    "above_5": int((s >= 5).sum()),
                    "scored": len(s),
                }
            )
    out["innocents"] = {case: innocent_summary(trials) for case, trials in innocents.items()}
    return out


def innocent_summary(trials: list[dict[str, Any]]) -> dict[str, Any]:
    """The innocent-only trials of one case, added up (the JSON keeps no row per trial)."""
    return {
        "trials": len(trials),
        "scored": sum(t["scored"] for t in trials),
        "trials_accusing": sum(t["innocent_accused"] > 0 for t in trials),
        "max_innocent_score": max(t["max_innocent_score"] for t in trials),
        **{f"above_{k}": sum(t[f"above_{k}"] for t in trials) for k in (3, 4, 5)},
    }


def registry_check(asset: Asset, args: argparse.Namespace, rng: np.random.Generator) -> dict[str, Any]:
    """The same traces from SQLite and PostgreSQL; scoring time with ``--registry-copies`` rows."""
    from app.registry import Copy, Registry, sqlite_url

    now = dt.datetime.now(dt.UTC)
    rows = [
        Copy(asset.name, f"recipient-{i:06d}", pack_codeword(c), asset.L, DEFAULT_METHOD, 0.07, now)
        for i, c in enumerate(asset.codewords)
    ]
    extra = args.registry_copies - len(rows)
    rows += [
        Copy(
            asset.name,
            f"bulk-{i:07d}",
            pack_codeword(random_codeword(rng, asset.L)),
            asset.L,
            DEFAULT_METHOD,
            0.07,
            now,
        )
        for i in range(max(extra, 0))
    ]
    suspects = [asset.copies[0], sum(asset.copies[:2]) / 2, sum(asset.copies[:3]) / 3, asset.cover]
    votes = []
    for v in suspects:
        a = analyse(
            v, asset.faces, asset.key, DEFAULT_METHOD, adj=asset.prepared[0], labels=asset.prepared[1]
        )
        votes.append(codeword_votes([a], asset.key, asset.L))
    out: dict[str, Any] = {"copies": len(rows), "codeword_bits": asset.L, "backends": {}}
    answers = {}
    with tempfile.TemporaryDirectory() as tmp:
        urls = {"sqlite": sqlite_url(Path(tmp) / "registry.sqlite3")}
        pg_admin = os.environ.get(
            "MESHMARK_BENCH_POSTGRES_URL", "postgresql+psycopg://postgres@127.0.0.1:5432/postgres"
        )
        pg_name = f"meshmark_bench_{os.getpid()}"
        admin = None
        try:
            import sqlalchemy as sa

            admin = sa.create_engine(pg_admin, isolation_level="AUTOCOMMIT")
            with admin.connect() as conn:
                conn.execute(sa.text(f'DROP DATABASE IF EXISTS "{pg_name}"'))
                conn.execute(sa.text(f'CREATE DATABASE "{pg_name}"'))
            urls["postgresql"] = (
                sa.make_url(pg_admin).set(database=pg_name).render_as_string(hide_password=False)
            )
        except Exception as exc:
            out["postgresql_skipped"] = f"{exc.__class__.__name__}: {exc}"
        for kind, url in urls.items():
            reg = Registry(url)
            reg.migrate()
            t = time.perf_counter()
            for start in range(0, len(rows), 10_000):
                reg.issue_many(rows[start : start + 10_000])
            insert = time.perf_counter() - t
            fetch, score, ranked = [], [], []
            for y in votes:
                t = time.perf_counter()
                group = reg.codewords(asset.name, DEFAULT_METHOD, asset.L)
                t1 = time.perf_counter()
                s = correlation_scores(y, group.packed, asset.L)
                t2 = time.perf_counter()
                order = np.argsort(-s, kind="stable")[:5]
                ranked.append([(group.recipients[i], round(float(s[i]), 9)) for i in order])
                fetch.append(t1 - t)
                score.append(t2 - t1)
            answers[kind] = ranked
            out["backends"][kind] = {
                "insert_seconds": insert,
                "fetch_seconds": fetch,
                "score_seconds": score,
                "trace_beyond_detection_seconds": [a + b for a, b in zip(fetch, score, strict=True)],
                "top5": ranked,
            }
            reg.close()
        if admin is not None and "postgresql" in urls:
            with admin.connect() as conn:
                conn.execute(sa.text(f'DROP DATABASE IF EXISTS "{pg_name}" WITH (FORCE)'))
            admin.dispose()
    out["same_answers"] = len({repr(a) for a in answers.values()}) == 1
    return out


def _summary(results: list[dict[str, Any]]) -> list[list[Any]]:
    rows = []
    for r in results:
        for case, trials in r["cases"].items():
            guilty = (
                1 if case in SINGLE else 2 if case == "halves of 2 swapped" else int(case.rsplit(" ", 1)[1])
            )
            rows.append(
                [
                    r["mesh"],
                    case,
                    len(trials),
                    sum(t["guilty_named"] >= 1 for t in trials),
                    sum(t["guilty_named"] == guilty for t in trials),
                    sum(t["innocent_accused"] > 0 for t in trials),
                    min(t["min_guilty_score"] for t in trials),
                    max(t["max_innocent_score"] for t in trials),
                    max(t["best_fap"] for t in trials),
                ]
            )
    return rows


def run(args: argparse.Namespace) -> dict[str, Any]:
    rng = np.random.default_rng(args.seed)
    names = [n for n in (args.meshes or MESHES) if mesh_path(n).is_file()]
    t0 = time.perf_counter()
    assets = []
    for name in names:
        assets.append(Asset(name, f"tracing-{args.seed}", args.recipients, args.copies, rng))
        print(f"[tracing] {name}: {assets[-1].L}-bit codewords, {len(assets[-1].copies)} copies", flush=True)
    if args.registry_only:
        return registry_only(assets, args, rng, t0)
    results = []
    for k, asset in enumerate(assets):
        other = assets[(k + 1) % len(assets)] if len(assets) > 1 else asset
        results.append(run_asset(asset, other, args, rng))
        print(f"[tracing] {asset.name} done at {time.perf_counter() - t0:.0f} s", flush=True)
    registry = registry_check(assets[0], args, rng)
    doc = {
        "environment": environment(),
        "threshold": THRESHOLD,
        "recipients": args.recipients,
        "results": results,
        "registry": registry,
        "seconds": time.perf_counter() - t0,
    }
    out = Path(args.out)
    save_json(out / "tracing.json", doc)
    (out / "tracing.md").write_text(render(doc, args))
    return doc


def registry_only(
    assets: list[Asset], args: argparse.Namespace, rng: np.random.Generator, t0: float
) -> dict[str, Any]:
    """``--registry-only``: the registry check for each mesh's codeword length, to
    ``tracing_registry.md`` (+ json)."""
    checks = [registry_check(asset, args, rng) for asset in assets]
    doc = {"environment": environment(), "checks": checks, "seconds": time.perf_counter() - t0}
    out = Path(args.out)
    save_json(out / "tracing_registry.json", doc)
    rows = []
    for asset, check in zip(assets, checks, strict=True):
        for kind, b in check["backends"].items():
            rows.append(
                [
                    asset.name,
                    check["codeword_bits"],
                    check["copies"],
                    kind,
                    b["insert_seconds"],
                    max(b["fetch_seconds"]),
                    max(b["score_seconds"]),
                    max(b["trace_beyond_detection_seconds"]),
                    check["same_answers"],
                ]
            )
    text = header("Leak tracing: the registry at each codeword length", doc["environment"]) + "\n"
    text += (
        "Per mesh: its codeword length, the copies registered for one asset, and the slowest of four "
        "traces (copy 0, averages of 2 and 3 copies, the cover) beyond detection.\n\n"
    )
    text += md_table(
        [
            "mesh",
            "codeword bits",
            "copies",
            "backend",
            "insert all s",
            "fetch s",
            "score s",
            "trace beyond detection s",
            "same answers",
        ],
        rows,
    )
    (out / "tracing_registry.md").write_text(text)
    return doc


def render(doc: dict[str, Any], args: argparse.Namespace) -> str:
    env = doc["environment"]
    results = doc["results"]
    lines = [
        header(
            "Leak tracing (issue 18)",
            env,
            [
                f"- Threshold: false-accusation probability <= "
                f"{doc['threshold']:g}; {doc['recipients']:,} recipients "
                "per asset; total run "
                f"{doc['seconds']:.0f} s"
            ],
        ),
        "",
    ]
    lines.append("## Capacity: codeword length per mesh (4 carriers per bit, hashed slots)\n")
    lines.append(
        md_table(
            ["mesh", "vertices", "carriers", "codeword bits", "RMS displacement", "embed s", "score needed"],
            [
                [
                    r["mesh"],
                    r["vertices"],
                    r["carriers"],
                    r["codeword_bits"],
                    r["rms_displacement"],
                    r["embed_seconds"],
                    r["score_threshold"],
                ]
                for r in results
            ],
        )
    )
    lines.append("\n## Leaked copies and collusions\n")
    lines.append(
        "Per trial: the guilty recipients named at the threshold, any innocent accused, and the "
        "scores (an innocent's score is below t with probability >= 1 - exp(-t^2/2)).\n"
    )
    lines.append(
        md_table(
            [
                "mesh",
                "case",
                "trials",
                ">= 1 guilty named",
                "all guilty named",
                "innocent accused",
                "lowest guilty score",
                "highest innocent score",
                "worst best p",
            ],
            _summary(results),
        )
    )
    lines.append("\n## Innocents only\n")
    rows = []
    for r in results:
        for case, t in r["innocents"].items():
            scored = t["scored"]
            rows.append(
                [
                    r["mesh"],
                    case,
                    t["trials"],
                    scored,
                    t["trials_accusing"],
                    t["max_innocent_score"],
                    t["above_3"] / scored,
                    len(VARIANTS) * math.exp(-4.5),
                    t["above_4"] / scored,
                    len(VARIANTS) * math.exp(-8.0),
                    t["above_5"] / scored,
                    len(VARIANTS) * math.exp(-12.5),
                ]
            )
    lines.append(
        md_table(
            [
                "mesh",
                "case",
                "trials",
                "innocent scores",
                "trials accusing anyone",
                "highest score",
                "P(S>=3)",
                "bound",
                "P(S>=4)",
                "bound",
                "P(S>=5)",
                "bound",
            ],
            rows,
        )
    )
    lines.append(
        "\nA score is the best of the decoding variants, so its bound is theirs times exp(-t^2/2).\n"
    )
    total = sum(r[2] for r in rows)
    lines.append(
        f"\n{total:,} innocent-only trials in all, {sum(r[4] for r in rows)} of them accusing anyone.\n"
    )
    reg = doc["registry"]
    lines.append(
        f"\n## Registry: {reg['copies']:,} copies of one asset ({reg['codeword_bits']}-bit codewords)\n"
    )
    lines.append(
        "Suspects: copy 0, average of copies 0-1, of copies 0-2, the unmarked mesh. Trace time "
        "beyond detection = fetching the asset's codewords + scoring them all.\n"
    )
    brow = []
    for kind, b in reg["backends"].items():
        brow.append(
            [
                kind,
                b["insert_seconds"],
                max(b["fetch_seconds"]),
                max(b["score_seconds"]),
                max(b["trace_beyond_detection_seconds"]),
            ]
        )
    lines.append(
        md_table(
            ["backend", "insert all s", "fetch s (max)", "score s (max)", "trace beyond detection s"], brow
        )
    )
    lines.append(
        f"\nSame ranking and scores on every backend: {'yes' if reg['same_answers'] else 'NO'}"
        + (f" (PostgreSQL skipped: {reg['postgresql_skipped']})" if "postgresql_skipped" in reg else "")
        + "\n"
    )
    return "\n".join(lines)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--recipients", type=int, default=1000, help="recipients per asset (default: %(default)s)")
    p.add_argument("--copies", type=int, default=24, help="marked copies per asset (default: %(default)s)")
    p.add_argument(
        "--single-trials", type=int, default=50, help="trials per single-leak attack (default: 50)"
    )
    p.add_argument("--collusions", type=int, default=200, help="pairs / triples per mesh (default: 200)")
    p.add_argument(
        "--innocent-trials",
        type=int,
        default=1500,
        help="innocent-only trials per case and mesh (default: %(default)s)",
    )
    p.add_argument("--registry-copies", type=int, default=100_000, help="rows of the registry check")
    p.add_argument(
        "--registry-only",
        action="store_true",
        help="only the registry check, for each mesh's codeword length (tracing_registry.md)",
    )

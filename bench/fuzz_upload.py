"""Fuzzing the upload path: real meshes, mutated, sent to the HTTP API (embed, detect, capacity).

    .venv/bin/python -m bench.fuzz_upload [--cases 2000] [--seconds 600] [--seed 6]

Every answer must be a 200 or a documented 4xx problem; a 5xx, a non-problem error body or an
answer slower than ``--slow`` seconds is a *finding*, saved under ``bench/results/fuzz_findings/``
(file + what came back) so it can be replayed.  The app runs in-process (ASGI, two real worker
processes).  The mutation operators (:mod:`tests.mutations`) and the judge of an answer
(:mod:`tests.app.oracles`) are those of the quick test in ``tests/app/test_hardening_fuzz.py``.
"""

from __future__ import annotations

import argparse
import hashlib
import random
import time
from collections import Counter
from pathlib import Path
from typing import Any

from bench.common import DEFAULT_OUT, mesh_path
from bench.hardening import record, run_info
from tests.app.oracles import ROUTES, check_answer
from tests.mutations import OPS, TOKENS, Op, apply_ops

#: small and medium shared meshes, one or more per format
SEEDS = ["teapot.stl", "monkey.glb", "sink.3ds", "spot.obj", "fandisk.off", "Duck.glb", "horse.ply"]
def random_ops(rng: random.Random) -> list[Op]:
    ops = []
    for _ in range(rng.randint(1, 4)):
        where = rng.random() if rng.random() < 0.6 else rng.random() ** 6  # often near the header
        blob = rng.choice(TOKENS) if rng.random() < 0.5 else rng.randbytes(rng.randint(1, 6))
        ops.append((rng.choice(OPS), where, blob))
    return ops


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--cases", type=int, default=2000)
    p.add_argument("--seconds", type=float, default=600.0, help="stop after this long even if cases remain")
    p.add_argument("--seed", type=int, default=6)
    p.add_argument("--slow", type=float, default=10.0, help="an answer slower than this is a finding")
    p.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = p.parse_args(argv)

    from fastapi.testclient import TestClient

    from app.config import Settings
    from app.main import create_app

    info = run_info()
    seeds = [(name, mesh_path(name).read_bytes()) for name in SEEDS if mesh_path(name).is_file()]
    rng = random.Random(args.seed)
    outcomes: Counter[str] = Counter()
    by_seed: Counter[str] = Counter()
    findings: list[dict[str, Any]] = []
    slowest = 0.0
    findings_dir = args.out / "fuzz_findings"
    start = time.monotonic()
    cases = 0
    with TestClient(create_app(Settings(workers=2, job_timeout_seconds=60))) as client:
        while cases < args.cases and time.monotonic() - start < args.seconds:
            name, original = rng.choice(seeds)
            data = apply_ops(original, random_ops(rng))
            route = rng.choice(ROUTES)
            form = {} if route == "/v1/capacity" else {"key": "fuzz key"}
            t0 = time.perf_counter()
            response = client.post(route, files={"mesh": (name, data)}, data=form)
            seconds = time.perf_counter() - t0
            slowest = max(slowest, seconds)
            cases += 1
            by_seed[name] += 1
            slug = "ok"
            if response.status_code != 200:
                slug = str(response.json().get("type", "?")).rsplit("/", 1)[-1]
            outcomes[f"{response.status_code} {slug}"] += 1
            problem = check_answer(response) or (f"slow: {seconds:.1f} s" if seconds > args.slow else None)
            if problem:
                digest = hashlib.sha256(data).hexdigest()[:16]
                findings_dir.mkdir(parents=True, exist_ok=True)
                (findings_dir / f"{digest}-{name}").write_bytes(data)
                findings.append({"file": f"{digest}-{name}", "route": route, "problem": problem})
                print("FINDING", route, name, problem, flush=True)
            if cases % 200 == 0:
                print(f"{cases} cases, {time.monotonic() - start:.0f} s", flush=True)
    elapsed = time.monotonic() - start
    figures = {
        "cases": cases,
        "seconds": round(elapsed, 1),
        "outcomes": dict(outcomes.most_common()),
        "by_seed": dict(by_seed),
        "findings": findings,
        "slowest_seconds": round(slowest, 2),
        "seed": args.seed,
    }
    lines = [
        "## Fuzzing the upload path (`bench/fuzz_upload.py`)",
        "",
        f"{cases} mutated uploads of {len(seeds)} real meshes ({', '.join(n for n, _ in seeds)}) in "
        f"{elapsed:.0f} s, spread over embed, detect and capacity; seed {args.seed}. "
        f"Findings (5xx, an error that is not a problem document, or slower than {args.slow:g} s): "
        f"**{len(findings)}**. Slowest answer: {slowest:.2f} s.",
        "",
        "| Answer | Count |",
        "| --- | ---: |",
    ]
    lines += [f"| {k} | {v} |" for k, v in outcomes.most_common()]
    if findings:
        lines += ["", "Findings (files in `bench/results/fuzz_findings/`):", ""]
        lines += [f"- `{f['file']}` on {f['route']}: {f['problem']}" for f in findings]
    target = record("fuzz_upload", info, figures, "\n".join(lines), args.out)
    print(f"{cases} cases, {len(findings)} findings; wrote {target}")
    return 1 if findings else 0


if __name__ == "__main__":
    raise SystemExit(main())

"""schemathesis against the committed ``openapi/openapi.json``, through the ASGI app with real
worker processes: every answer must conform to the document and none may be a 5xx.

    .venv/bin/python -m bench.schemathesis_run [--examples 500] [--seed 0]

The long run (positive and negative cases for every operation, failures counted rather than
stopping the run) is recorded in ``bench/results/hardening.md``; ``tests/app/test_hardening_schema.py``
runs the same checks briefly in the test suite.  The checks, two of them adapted to multipart
uploads, are those of the tests (:mod:`tests.app.oracles`).
"""

from __future__ import annotations

import argparse
import time
from collections import Counter
from pathlib import Path
from typing import Any

from bench.common import DEFAULT_OUT
from tests.app.oracles import call_and_check, load_schema


def run_operation(
    operation: Any, mode: Any, app: Any, examples: int, seed_: int, failures: Counter[str]
) -> tuple[Counter[int], int] | None:
    """Up to ``examples`` cases of one operation in one mode; failures are counted (by kind), not
    raised, so that a long run reports every kind.  ``None`` when the mode has nothing to generate."""
    from hypothesis import HealthCheck, given, seed, settings
    from hypothesis.errors import Unsatisfiable

    statuses: Counter[int] = Counter()
    failed = 0

    @seed(seed_)
    @settings(max_examples=examples, deadline=None, database=None, suppress_health_check=list(HealthCheck))
    @given(operation.as_strategy(generation_mode=mode))
    def run(case: Any) -> None:
        nonlocal failed
        try:
            statuses[call_and_check(case, app).status_code] += 1
        except (Exception, BaseExceptionGroup) as exc:  # schemathesis's FailureGroup is a BaseExceptionGroup
            failed += 1
            inner = exc.exceptions[0] if isinstance(exc, BaseExceptionGroup) and exc.exceptions else exc
            text = " ".join(str(inner).split())
            kind = text[:200] if text else type(inner).__name__
            failures[f"{operation.label} ({mode.value}): {kind}"] += 1

    try:
        run()
    except Unsatisfiable:
        return None
    return statuses, failed


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--examples", type=int, default=500, help="examples per operation and mode")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = p.parse_args(argv)

    from schemathesis import GenerationMode
    from schemathesis.python import asgi

    from app.config import Settings
    from app.main import create_app
    from bench.hardening import record, run_info

    info = run_info()
    app = create_app(Settings(workers=2, job_timeout_seconds=30))
    schema = load_schema()
    rows: list[list[Any]] = []
    failures: Counter[str] = Counter()
    statuses_all: Counter[int] = Counter()
    total = 0
    start = time.monotonic()
    try:
        for result in schema.get_all_operations():
            operation = result.ok()
            for mode in (GenerationMode.POSITIVE, GenerationMode.NEGATIVE):
                t0 = time.monotonic()
                outcome = run_operation(operation, mode, app, args.examples, args.seed, failures)
                if outcome is None:  # nothing to break (no parameters, no body)
                    continue
                statuses, failed = outcome
                cases = sum(statuses.values()) + failed
                total += cases
                statuses_all.update(statuses)
                rows.append(
                    [
                        operation.label,
                        mode.value,
                        cases,
                        failed,
                        ", ".join(f"{s}: {n}" for s, n in sorted(statuses.items())),
                        f"{time.monotonic() - t0:.0f}",
                    ]
                )
                print(rows[-1], flush=True)
    finally:
        asgi.shutdown_lifespans()
    elapsed = time.monotonic() - start
    lines = [
        "## schemathesis against `openapi/openapi.json` (`bench/schemathesis_run.py`)",
        "",
        f"{total} generated requests ({args.examples} examples per operation and mode, hypothesis "
        f"seed {args.seed}) in {elapsed:.0f} s through the ASGI app with two worker processes. "
        f"Checks: schemathesis's defaults (no 5xx, status codes, content types, headers and bodies "
        f"as documented, negative data refused as sent) plus `valid_forms_are_accepted`. "
        f"Failing cases: **{sum(failures.values())}**; 5xx answers: "
        f"**{sum(n for s, n in statuses_all.items() if s >= 500)}**.",
        "",
        "| Operation | Mode | Cases | Failed | Statuses | Seconds |",
        "| --- | --- | ---: | ---: | --- | ---: |",
    ]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    if failures:
        lines += ["", "Failures:", ""] + [f"- {n} x {k}" for k, n in failures.most_common()]
    figures = {
        "cases": total,
        "seconds": round(elapsed, 1),
        "failures": dict(failures),
        "statuses": {str(k): v for k, v in sorted(statuses_all.items())},
        "rows": rows,
        "examples": args.examples,
        "seed": args.seed,
    }
    target = record("schemathesis", info, figures, "\n".join(lines), args.out)
    print(f"{total} cases, {sum(failures.values())} failing; wrote {target}")
    return 1 if failures else 0


if __name__ == "__main__":
    raise SystemExit(main())

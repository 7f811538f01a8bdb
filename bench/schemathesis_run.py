"""schemathesis against the committed ``openapi/openapi.json``, through the ASGI app with real
worker processes: every answer must conform to the document and none may be a 5xx.

    .venv/bin/python -m bench.schemathesis_run [--examples 500] [--seed 0]

The long run (positive and negative cases for every operation, failures counted rather than
stopping the run) is recorded in ``bench/results/hardening.md``; ``tests/app/test_hardening_schema.py``
runs the same checks briefly in the test suite.

Two of schemathesis's checks are adapted to multipart uploads:

* positive cases (schema-valid forms) may be refused for the mesh *content* (random bytes are no
  mesh), but never as ``bad-form`` -- except for the one rule a document cannot state: the key
  comes from the form field or the header, exactly one of them;
* a negative case counts only when the form *as sent* breaks the document: a file part always
  arrives as bytes, an empty list sends nothing and an empty field counts as not sent (as the
  README says), whatever schemathesis meant to break.

Half of the positive uploads carry a real small mesh, so that valid options reach the engine.
"""

from __future__ import annotations

import argparse
import json
import time
from collections import Counter
from email.parser import BytesParser
from email.policy import HTTP
from functools import cache
from pathlib import Path
from typing import Any

import jsonschema_rs
import schemathesis
from schemathesis.core.failures import AcceptedNegativeData
from schemathesis.specs.openapi.checks import negative_data_rejection, positive_data_acceptance

from app.openapi import OPENAPI_PATH
from bench.common import DEFAULT_OUT

MESH_PROBLEMS = {
    "unsupported-format",
    "malformed-mesh",
    "degenerate-mesh",
    "too-little-capacity",
    "too-large",
}
KEY_RULES = ("a watermark key is required", "give the key once")


@cache
def small_mesh() -> bytes:
    import trimesh

    return trimesh.creation.icosphere(subdivisions=4).export(file_type="obj").encode()  # embeds in ~50 ms


def load_schema() -> Any:
    return schemathesis.openapi.from_path(OPENAPI_PATH)


def _problem(response: Any) -> tuple[str, str]:
    problem = response.json()
    return str(problem.get("type", "")).rsplit("/", 1)[-1], str(problem.get("detail", ""))


def _form_as_sent(response: Any) -> dict[str, Any] | None:
    """The multipart fields the server received, read as the app reads them (each text field as
    text, and as a number when it is one)."""
    request = response.request
    body = request.body.encode() if isinstance(request.body, str) else request.body
    content_type = request.headers.get("Content-Type", "")
    if not isinstance(body, bytes) or not content_type.startswith("multipart/form-data"):
        return None
    message = BytesParser(policy=HTTP).parsebytes(f"Content-Type: {content_type}\r\n\r\n".encode() + body)
    sent: dict[str, Any] = {}
    for part in message.iter_parts():
        name = part.get_param("name", header="content-disposition")
        payload = part.get_payload(decode=True)
        if part.get_filename() is not None:
            sent[name] = ["(file)"]
        elif isinstance(payload, bytes) and payload:  # an empty field counts as not sent
            text = payload.decode("utf-8", "replace")
            try:
                sent[name] = [text, float(text)]
            except ValueError:
                sent[name] = [text]
    return sent


def valid_as_sent(case: Any, response: Any) -> bool:
    sent = _form_as_sent(response)
    body = case.operation.get_body_for_media_type("multipart/form-data")
    if sent is None or body is None:
        return False
    validator = jsonschema_rs.validator_for(body.optimized_schema)
    chosen: dict[str, Any] = {}
    for name, readings in sent.items():
        chosen[name] = next((r for r in readings if validator.is_valid({**chosen, name: r})), readings[0])
    return bool(validator.is_valid(chosen))


def valid_forms_are_accepted(ctx: Any, response: Any, case: Any) -> bool | None:
    """Schema-valid forms are taken; only the mesh content may be refused."""
    if case.meta is None or not case.meta.generation.mode.is_positive or response.status_code < 400:
        return None
    if response.status_code in (401, 404, 409, 429):
        return None
    slug, detail = _problem(response)
    if slug == "bad-form" and detail.startswith(KEY_RULES):
        return None
    assert slug in MESH_PROBLEMS, f"schema-valid request refused: {response.status_code} {slug}: {detail}"
    return None


def invalid_forms_are_refused(ctx: Any, response: Any, case: Any) -> bool | None:
    """schemathesis's ``negative_data_rejection``, judged on the form as it was sent."""
    try:
        return negative_data_rejection(ctx, response, case)
    except AcceptedNegativeData:
        if valid_as_sent(case, response):
            return None
        raise


CHECKS = {
    "excluded_checks": [positive_data_acceptance, negative_data_rejection],
    "additional_checks": [
        schemathesis.check(valid_forms_are_accepted),
        schemathesis.check(invalid_forms_are_refused),
    ],
}


def with_real_mesh(case: Any) -> None:
    """Put a real small mesh into half of the positive uploads (chosen from the case itself)."""
    body = case.body
    if (
        isinstance(body, dict)
        and "mesh" in body
        and case.meta is not None
        and case.meta.generation.mode.is_positive
        and len(json.dumps(sorted(body))) % 2 == 0
    ):
        body["mesh"] = small_mesh()


def call_and_check(case: Any, app: Any) -> Any:
    """One case through the app, with the adapted checks; raises on any failure."""
    with_real_mesh(case)
    response = case.call_and_validate(app=app, timeout=120, **CHECKS)
    assert response.status_code < 500, response.text
    return response


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

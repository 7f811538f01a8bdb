"""Judges of the service's answers, shared by the hardening tests and their long runs in
``bench/`` (``fuzz_upload``, ``schemathesis_run``).

:func:`check_answer`: an upload, however mangled, gets a 200 or a documented 4xx problem.

:func:`call_and_check`: schemathesis against the committed ``openapi/openapi.json``, with two of its
checks adapted to multipart uploads:

* positive cases (schema-valid forms) may be refused for the mesh *content* (random bytes are no
  mesh), but never as ``bad-form`` -- except for the one rule a document cannot state: the key
  comes from the form field or the header, exactly one of them;
* a negative case counts only when the form *as sent* breaks the document: a file part always
  arrives as bytes, an empty list sends nothing and an empty field counts as not sent (as the
  README says), whatever schemathesis meant to break.

Half of the positive uploads carry a real small mesh, so that valid options reach the engine.
"""

from __future__ import annotations

import json
from email.parser import BytesParser
from email.policy import HTTP
from functools import cache
from typing import Any

import jsonschema_rs
import schemathesis
from schemathesis.core.failures import AcceptedNegativeData
from schemathesis.specs.openapi.checks import negative_data_rejection, positive_data_acceptance

from app.openapi import OPENAPI_PATH

#: the routes that take an upload
ROUTES = ("/v1/embed", "/v1/detect", "/v1/capacity")


def check_answer(response: Any) -> str | None:
    """What is wrong with an answer, or ``None``: 200, or a 4xx problem document."""
    if response.status_code == 200:
        return None
    if response.status_code >= 500:
        return f"{response.status_code}: {response.text[:300]}"
    if response.headers.get("content-type") != "application/problem+json":
        return f"{response.status_code} without a problem document"
    body = response.json()
    if not str(body.get("type", "")).startswith("https://meshmark.dev/problems/"):
        return f"{response.status_code} with type {body.get('type')!r}"
    return None


MESH_PROBLEMS = {
    "unsupported-format",
    "malformed-mesh",
    "degenerate-mesh",
    "too-little-capacity",
    "too-large",
}
#: ...and the key's Unicode categories in the header, whose pattern can only say "UTF-8 bytes"
KEY_RULES = ("a watermark key is required", "give the key once", "the key must not contain")
#: refusals that depend on the server's settings, which no schema can say (which hosts a callback
#: may reach: MESHMARK_CALLBACK_HOSTS, none by default)
POLICY_PROBLEMS = {"callback-not-allowed"}


@cache
def small_mesh() -> bytes:
    import trimesh

    return trimesh.creation.icosphere(subdivisions=5).export(file_type="obj").encode()  # embeds in ~0.2 s


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
    if slug in POLICY_PROBLEMS:
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

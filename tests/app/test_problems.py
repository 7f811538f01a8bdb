"""The exception -> problem table and the key-redaction helper."""

from __future__ import annotations

import pytest

from app.problems import PROBLEM_TYPES, problem_for_core_error, redact
from core import errors


@pytest.mark.parametrize(("exc", "status", "slug"), [
    (errors.UnsupportedFormatError("x"), 415, "unsupported-format"),
    (errors.MeshFormatError("bad face", "line 3"), 422, "malformed-mesh"),
    (errors.LimitExceededError("vertices", 10, 5), 413, "too-large"),
    (errors.DegenerateMeshError("flat"), 422, "degenerate-mesh"),
    (errors.CapacityError("small", carriers=3, needed=56), 422, "too-little-capacity"),
    (errors.PayloadError("bits"), 422, "bad-form"),
    (errors.MeshMarkError("other"), 422, "invalid-input"),
])
def test_core_errors_map_to_problems(exc, status, slug):
    problem = problem_for_core_error(type(exc), str(exc), {"extra": 1})
    body = problem.to_dict("/v1/embed")
    assert problem.status_code == status
    assert body == {"type": f"https://meshmark.dev/problems/{slug}", "title": problem.problem.title,
                    "status": status, "detail": str(exc), "instance": "/v1/embed", "extra": 1}


def test_problem_slugs_are_unique_and_stable():
    slugs = [p.slug for p in PROBLEM_TYPES]
    assert len(slugs) == len(set(slugs))
    for required in ("bad-form", "unsupported-format", "malformed-mesh", "too-large", "too-little-capacity",
                     "degenerate-mesh", "busy", "timed-out", "worker-failed", "not-found", "unauthorized"):
        assert required in slugs


def test_redact():
    assert redact("key 'hunter22' too long", "hunter22") == "key '[key]' too long"
    assert "ab" not in redact("a message about ab", "ab")
    assert redact("nothing secret", "hunter22") == "nothing secret"
    assert redact("text", None) == "text"

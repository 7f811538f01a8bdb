"""The committed OpenAPI document matches the app, and documents problems on every route."""

from __future__ import annotations

import json

from app.openapi import OPENAPI_PATH, render_openapi


def test_committed_openapi_is_current():
    assert OPENAPI_PATH.read_text(encoding="utf-8") == render_openapi(), (
        "openapi/openapi.json is stale: regenerate it with `.venv/bin/python scripts/export_openapi.py`"
    )


def test_routes_declare_their_problems():
    document = json.loads(render_openapi())
    problem_ref = {"$ref": "#/components/schemas/Problem"}
    for path, operations in document["paths"].items():
        for method, operation in operations.items():
            errors = {code: r for code, r in operation["responses"].items() if code >= "400"}
            if path.startswith("/v1/"):
                assert {"401", "422"} <= set(errors), (method, path)
            for code, response in errors.items():
                assert response["content"]["application/problem+json"]["schema"] == problem_ref, (path, code)
    embed = document["paths"]["/v1/embed"]["post"]
    assert {"413", "415", "422", "429", "503"} <= set(embed["responses"])
    assert "X-MeshMark-Report" in embed["responses"]["200"]["headers"]
    assert "HTTPValidationError" not in document["components"]["schemas"]

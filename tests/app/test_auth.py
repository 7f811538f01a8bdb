"""Caller authentication with MESHMARK_API_KEYS (off by default)."""

from __future__ import annotations

from tests.app.conftest import assert_problem, make_client


def test_api_keys(sphere_obj):
    with make_client(workers=1, api_keys="first-key, second-key") as client:
        files = {"mesh": ("s.obj", sphere_obj)}
        response = client.post("/v1/capacity", files=files)
        assert_problem(response, 401, "unauthorized")
        assert response.headers["www-authenticate"] == "Bearer"
        assert_problem(client.post("/v1/capacity", files=files, headers={"X-API-Key": "third-key"}), 401,
                       "unauthorized")
        response = client.get("/v1/jobs/x", headers={"Authorization": "Bearer nope"})
        assert_problem(response, 401, "unauthorized")
        ok = client.post("/v1/capacity", files=files, headers={"Authorization": "Bearer second-key"})
        assert ok.status_code == 200
        assert client.post("/v1/capacity", files=files, headers={"X-API-Key": "first-key"}).status_code == 200
        # health and metrics stay open for probes and scrapers
        for path in ("/healthz", "/readyz", "/metrics"):
            assert client.get(path).status_code == 200


def test_open_by_default(client, sphere_obj):
    assert client.post("/v1/capacity", files={"mesh": ("s.obj", sphere_obj)}).status_code == 200

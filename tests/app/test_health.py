"""/healthz, /readyz and /metrics."""

from __future__ import annotations

import re

from fastapi.testclient import TestClient

from app.config import Settings
from app.main import create_app
from tests.app.conftest import assert_problem, embed


def test_healthz_and_readyz(client):
    assert client.get("/healthz").json() == {"status": "ok"}
    ready = client.get("/readyz")
    assert ready.status_code == 200
    assert ready.json()["status"] == "ready" and ready.json()["workers"] == 2


def test_not_ready_without_workers():
    client = TestClient(create_app(Settings(workers=1)))  # no lifespan: no pool
    assert client.get("/healthz").status_code == 200
    assert_problem(client.get("/readyz"), 503, "not-ready")


def test_metrics_exposition(client, sphere_obj):
    embed(client, "s.obj", sphere_obj)
    embed(client, "s.obj", sphere_obj, payload="nope")
    response = client.get("/metrics")
    assert response.status_code == 200
    assert response.headers["content-type"].startswith("text/plain; version=0.0.4")
    text = response.text
    for status in (200, 422):
        sample = rf'meshmark_http_requests_total\{{method="POST",route="/v1/embed",status="{status}"\}} [1-9]'
        assert re.search(sample, text), status
    assert 'meshmark_http_request_duration_seconds_bucket{route="/v1/embed",le="+Inf"}' in text
    assert 'meshmark_http_request_duration_seconds_count{route="/v1/embed"}' in text
    for family in ("meshmark_queue_depth", "meshmark_tasks_in_flight", "meshmark_queue_capacity",
                   "meshmark_workers_live", "meshmark_http_requests_in_progress"):
        assert re.search(rf"^# TYPE {family} gauge$", text, re.M), family
    assert re.search(r'^meshmark_worker_restarts_total\{reason="crashed"\} \d+$', text, re.M)
    assert re.search(r'^meshmark_tasks_total\{kind="embed",outcome="ok"\} [1-9]', text, re.M)
    assert re.search(r'^meshmark_jobs\{state="running"\} \d+$', text, re.M)
    assert "meshmark_workers_live 2" in text
    # every sample line is `name{labels} value`
    for line in text.splitlines():
        assert line.startswith("#") or re.fullmatch(r'[a-z_]+(\{[^}]*\})? -?[0-9.e+-]+', line), line

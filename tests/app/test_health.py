"""/healthz, /readyz, /metrics and /docs."""

from __future__ import annotations

import platform
import re

from fastapi.testclient import TestClient
from prometheus_client.parser import text_string_to_metric_families

import meshmark
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
    assert response.headers["content-type"].startswith("text/plain; version=")
    # Prometheus's own parser reads it back (it raises on a malformed line)
    families = {f.name: f for f in text_string_to_metric_families(response.text)}
    samples = {(s.name, tuple(sorted(s.labels.items()))): s.value
               for f in families.values() for s in f.samples}

    def value(name: str, **labels: str) -> float:
        return samples[(name, tuple(sorted(labels.items())))]

    for status in ("200", "422"):
        assert value("meshmark_http_requests_total", method="POST", route="/v1/embed", status=status) >= 1
    assert value("meshmark_http_request_duration_seconds_count", route="/v1/embed") >= 2
    assert value("meshmark_http_request_duration_seconds_bucket", route="/v1/embed", le="+Inf") >= 2
    for family in ("meshmark_queue_depth", "meshmark_tasks_in_flight", "meshmark_queue_capacity",
                   "meshmark_workers_live", "meshmark_http_requests_in_progress"):
        assert families[family].type == "gauge", family
    assert value("meshmark_worker_restarts_total", reason="crashed") >= 0
    assert value("meshmark_tasks_total", kind="embed", outcome="ok") >= 1
    assert value("meshmark_jobs", state="running") >= 0
    assert value("meshmark_workers_live") == 2
    # the process and the build, which the hand-written exposition lacked
    assert value("process_resident_memory_bytes") > 10e6 and value("process_cpu_seconds_total") > 0
    assert value("meshmark_build_info", version=meshmark.__version__,
                 python=platform.python_version()) == 1


def test_docs_work_offline(client):
    """/docs and /redoc load their scripts and styles from this server, never from a CDN."""
    for page in ("/docs", "/redoc"):
        html = client.get(page).text
        assets = re.findall(r'(?:src|href)=["\']([^"\']+)["\']', html)
        assert assets and not [a for a in assets if "//" in a], (page, assets)
        for asset in assets:
            response = client.get(asset)
            assert response.status_code == 200 and len(response.content) > 1000, asset

"""/v1/jobs: create, poll (with relayed progress), fetch the result, cancel, delete, expire."""

from __future__ import annotations

import json
import time

import pytest
from pydantic import ValidationError

from app.config import Settings
from meshmark.client import verify_signature
from tests.app.conftest import (
    CALLBACK_SECRET,
    KEY,
    assert_problem,
    detect,
    make_client,
    shared_mesh,
    wait_for,
    wait_job,
)

STATUS_KEYS = {"id", "kind", "state", "progress", "created", "started", "finished", "expires", "error",
               "request_id"}


def start_job(client, kind: str, name: str, data: bytes, key: str = KEY, **fields: str):
    response = client.post(f"/v1/jobs/{kind}", files={"mesh": (name, data)}, data={"key": key, **fields})
    assert response.status_code == 202, response.text
    job = response.json()
    assert response.headers["location"] == f"/v1/jobs/{job['id']}"
    assert set(job) == STATUS_KEYS and job["kind"] == kind and job["state"] in ("queued", "running")
    return job


def test_embed_job_lifecycle(client):
    data = shared_mesh("bun_zipper.ply")
    job = start_job(client, "embed", "bun_zipper.ply", data, payload="1100")
    seen = []
    while True:
        status = client.get(f"/v1/jobs/{job['id']}").json()
        seen.append((status["state"], status["progress"]))
        if status["state"] not in ("queued", "running"):
            break
        time.sleep(0.005)
    assert status["state"] == "succeeded", status
    assert status["progress"] == 1.0 and status["error"] is None
    assert status["started"] and status["finished"] and status["expires"] > status["finished"]
    progress = [p for _, p in seen]
    assert progress == sorted(progress)  # never goes back
    assert any(state == "running" and 0 < p < 1 for state, p in seen), seen  # relayed from the worker

    result = client.get(f"/v1/jobs/{job['id']}/result")
    assert result.status_code == 200
    assert result.headers["content-disposition"] == 'attachment; filename="bun_zipper.marked.ply"'
    assert int(result.headers["x-meshmark-payload-bits"]) == 4
    found = detect(client, "bun_zipper.ply", result.content, payload="1100").json()
    assert found["detected"] and found["payload"] == "1100"

    # deleting a finished job forgets it
    assert client.delete(f"/v1/jobs/{job['id']}").status_code == 204
    assert_problem(client.get(f"/v1/jobs/{job['id']}"), 404, "not-found")
    assert_problem(client.get(f"/v1/jobs/{job['id']}/result"), 404, "not-found")


def test_detect_job(client, sphere_obj):
    marked = client.post("/v1/embed", files={"mesh": ("s.obj", sphere_obj)}, data={"key": KEY}).content
    job = start_job(client, "detect", "s.obj", marked)
    assert wait_job(client, job["id"])["state"] == "succeeded"
    result = client.get(f"/v1/jobs/{job['id']}/result")
    assert result.headers["content-type"] == "application/json"
    assert result.json()["detected"] is True
    assert result.json() == detect(client, "s.obj", marked).json()  # same answer as the synchronous route


def test_failed_job_keeps_its_problem(client):
    job = start_job(client, "embed", "photo.obj", b"\xff\xd8\xff\xe0" + bytes(64))
    status = wait_job(client, job["id"])
    assert status["state"] == "failed"
    assert status["error"]["type"] == "https://meshmark.dev/problems/unsupported-format"
    assert status["error"]["status"] == 415
    body = assert_problem(client.get(f"/v1/jobs/{job['id']}/result"), 409, "job-failed")
    assert body["error"]["status"] == 415


def test_form_errors_are_immediate(client, sphere_obj):
    response = client.post("/v1/jobs/embed", files={"mesh": ("s.obj", sphere_obj)}, data={"key": KEY,
                                                                                        "payload": "x"})
    assert_problem(response, 422, "bad-form")


def test_not_ready_then_cancel():
    armadillo = shared_mesh("armadillo.obj")
    with make_client(workers=1) as client:
        first = start_job(client, "embed", "armadillo.obj", armadillo)
        second = start_job(client, "embed", "armadillo.obj", armadillo)  # waits behind the first
        body = assert_problem(client.get(f"/v1/jobs/{second['id']}/result"), 409, "job-not-ready")
        assert body["state"] in ("queued", "running")
        response = client.delete(f"/v1/jobs/{second['id']}")
        assert response.status_code == 200 and response.json()["state"] == "cancelled"
        status = client.get(f"/v1/jobs/{second['id']}").json()
        assert status["state"] == "cancelled" and status["expires"] is not None
        assert assert_problem(client.get(f"/v1/jobs/{second['id']}/result"), 409, "job-failed")["state"] == \
            "cancelled"
        assert wait_job(client, first["id"])["state"] == "succeeded"
        # the cancelled job does not come back to life when its work would have finished
        time.sleep(0.5)
        assert client.get(f"/v1/jobs/{second['id']}").json()["state"] == "cancelled"
        assert client.delete(f"/v1/jobs/{second['id']}").status_code == 204


def test_unknown_job(client):
    for method, path in [("GET", "/v1/jobs/nope"), ("GET", "/v1/jobs/nope/result"),
                         ("DELETE", "/v1/jobs/nope")]:
        assert_problem(client.request(method, path), 404, "not-found")


def test_results_expire(sphere_obj):
    with make_client(workers=1, job_result_ttl_seconds=0.3) as client:
        job = start_job(client, "embed", "s.obj", sphere_obj)
        assert wait_job(client, job["id"])["state"] == "succeeded"
        assert client.get(f"/v1/jobs/{job['id']}/result").status_code == 200
        time.sleep(0.4)
        assert_problem(client.get(f"/v1/jobs/{job['id']}/result"), 404, "not-found")
        assert "meshmark_jobs{state=\"succeeded\"} 0" in client.get("/metrics").text


def test_store_limit_answers_busy(sphere_obj):
    with make_client(workers=1, max_stored_jobs=2) as client:
        for _ in range(2):
            wait_job(client, start_job(client, "embed", "s.obj", sphere_obj)["id"])
        response = client.post("/v1/jobs/embed", files={"mesh": ("s.obj", sphere_obj)}, data={"key": KEY})
        assert "DELETE" in assert_problem(response, 429, "busy")["detail"]
        assert int(response.headers["retry-after"]) >= 1


def test_callback_is_signed_and_retried(sphere_obj, receiver):
    """The final status reaches the receiver, signed with the server's secret; a 503 from the
    receiver is tried again after the backoff; the URL must name an allowed host."""
    receiver.answers = [503]  # the first delivery fails
    with make_client(callback_hosts="127.0.0.1", callback_secret=CALLBACK_SECRET) as client:
        bad = client.post("/v1/jobs/detect", files={"mesh": ("s.obj", sphere_obj)},
                          data={"key": KEY, "callback_url": "http://169.254.169.254/latest/meta-data"})
        assert "not among the hosts" in assert_problem(bad, 422, "callback-not-allowed")["detail"]
        response = client.post("/v1/jobs/detect", files={"mesh": ("s.obj", sphere_obj)},
                               data={"key": KEY, "callback_url": receiver.url},
                               headers={"X-Request-ID": "cms-9"})
        assert response.status_code == 202, response.text
        job_id = response.json()["id"]
        wait_for(lambda: len(receiver.received) >= 2, timeout=30)
    (first, _, _), (second, headers, body) = receiver.received[:2]
    assert second - first >= 0.9  # the backoff before the second attempt
    assert verify_signature(CALLBACK_SECRET, body, headers["X-MeshMark-Signature"])
    assert not verify_signature("another secret", body, headers["X-MeshMark-Signature"])
    status = json.loads(body)
    assert status["id"] == job_id == headers["X-MeshMark-Job"] and status["state"] == "succeeded"
    assert status["request_id"] == headers["X-Request-ID"] == "cms-9"
    time.sleep(1.5)
    assert len(receiver.received) == 2  # delivered: no more attempts


def test_callbacks_are_off_by_default(client, sphere_obj):
    response = client.post("/v1/jobs/embed", files={"mesh": ("s.obj", sphere_obj)},
                           data={"key": KEY, "callback_url": "http://127.0.0.1:9/hook"})
    assert "callbacks are off" in assert_problem(response, 422, "callback-not-allowed")["detail"]
    with pytest.raises(ValidationError, match="CALLBACK_SECRET is required"):
        Settings(callback_hosts="cms.example")

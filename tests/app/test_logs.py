"""One log stream: every line of a real ``meshmark serve`` (uvicorn's included) in one format, JSON
lines on request, each with the request id that the answer and the job status carry."""

from __future__ import annotations

import json
import time

import httpx

from tests.app.conftest import KEY, assert_problem, shared_mesh
from tests.app.real_server import serve


def test_json_lines_with_request_ids(tmp_path):
    spot = shared_mesh("spot.obj")
    with serve(tmp_path / "server.log", log_format="json") as server, \
            httpx.Client(base_url=server.base, timeout=60) as http:
        given = http.post("/v1/capacity", files={"mesh": ("spot.obj", spot)},
                          headers={"X-Request-ID": "cms-upload-42"})
        assert given.status_code == 200 and given.headers["x-request-id"] == "cms-upload-42"
        made = http.post("/v1/embed", content=b"{}", headers={"content-type": "application/json",
                                                               "X-Request-ID": "not a token"})
        assert_problem(made, 415, "not-multipart")
        made_id = made.headers["x-request-id"]
        assert len(made_id) == 32 and made_id != "not a token"  # refused as given: a new one
        job = http.post("/v1/jobs/detect", files={"mesh": ("spot.obj", spot)}, data={"key": KEY},
                        headers={"X-Request-ID": "job-7"})
        status = job.json()
        while status["state"] in ("queued", "running"):
            time.sleep(0.05)
            status = http.get(job.headers["location"]).json()
        assert status["request_id"] == "job-7" and status["state"] == "succeeded"
        assert http.get(job.headers["location"]).headers["x-request-id"] != "job-7"  # each request its own
        time.sleep(0.2)
        lines = [json.loads(line) for line in server.text().splitlines()]  # every line is JSON
    assert {"time", "level", "logger", "message", "request_id"} <= set(lines[0])
    assert any(rec["logger"].startswith("uvicorn") for rec in lines)  # uvicorn's own lines too
    access = [rec for rec in lines if rec["logger"] == "meshmark.access"]
    assert any(rec["request_id"] == "cms-upload-42" and " /v1/capacity 200 - " in rec["message"]
               for rec in access)
    assert any(rec["request_id"] == made_id and " /v1/embed 415 not-multipart " in rec["message"]
               for rec in access)
    job_lines = [rec["message"] for rec in lines if rec["request_id"] == "job-7"]
    assert any(m.startswith("detect key=") for m in job_lines)  # the route's line
    assert any(m.endswith("(detect) succeeded") for m in job_lines)  # the runner's, when it ended
    assert KEY not in server.text()


def test_text_lines_carry_the_request_id(tmp_path):
    with serve(tmp_path / "server.log") as server:
        httpx.get(f"{server.base}/v1/jobs/nope", headers={"X-Request-ID": "r-1"})
        time.sleep(0.2)
        text = server.text()
    assert "INFO meshmark.access [r-1] " in text and " 404 not-found " in text
    assert " INFO uvicorn.error [-] " in text  # uvicorn's lines in the same format

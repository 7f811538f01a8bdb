"""Caller authentication with MESHMARK_API_KEYS (off by default): checked from the headers before
anything else, and jobs belong to the key that created them."""

from __future__ import annotations

import socket
import time

from tests.app.conftest import KEY, assert_problem, make_client, wait_job
from tests.app.real_server import free_port, start_server

FIRST, SECOND = "first-key-0123456789", "second-key-0123456789"


def test_api_keys(sphere_obj):
    with make_client(workers=1, api_keys=f"{FIRST}, {SECOND}") as client:
        files = {"mesh": ("s.obj", sphere_obj)}
        response = client.post("/v1/capacity", files=files)
        assert_problem(response, 401, "unauthorized")
        assert response.headers["www-authenticate"] == "Bearer"
        wrong = {"X-API-Key": "third-key-0123456789"}
        assert_problem(client.post("/v1/capacity", files=files, headers=wrong), 401, "unauthorized")
        response = client.get("/v1/jobs/x", headers={"Authorization": "Bearer nope"})
        assert_problem(response, 401, "unauthorized")
        ok = client.post("/v1/capacity", files=files, headers={"Authorization": f"Bearer {SECOND}"})
        assert ok.status_code == 200
        assert client.post("/v1/capacity", files=files, headers={"X-API-Key": FIRST}).status_code == 200
        # health and metrics stay open for probes and scrapers
        for path in ("/healthz", "/readyz", "/metrics"):
            assert client.get(path).status_code == 200


def test_open_by_default(client, sphere_obj):
    assert client.post("/v1/capacity", files={"mesh": ("s.obj", sphere_obj)}).status_code == 200


def test_no_other_refusal_comes_before_401(sphere_obj):
    # a caller without a valid key learned the form's rules (422) and the load (429) before 401
    with make_client(workers=1, queue_size=1, api_keys=FIRST) as client:
        assert_problem(client.post("/v1/embed", files={"mesh": ("s.obj", sphere_obj)}), 401, "unauthorized")
        assert_problem(client.post("/v1/embed", data={"key": "x\n"}), 401, "unauthorized")
        assert_problem(client.post("/v1/embed", content=b"&" * 10_000,
                                   headers={"content-type": "application/x-www-form-urlencoded"}),
                       401, "unauthorized")
        assert_problem(client.post("/v1/jobs/embed", data={"key": KEY}), 401, "unauthorized")
        assert_problem(client.post("/v1/preview", files={"mesh": ("s.obj", b"")}), 401, "unauthorized")


def test_jobs_belong_to_the_key_that_created_them(sphere_obj):
    with make_client(workers=1, api_keys=f"{FIRST},{SECOND}") as client:
        mine, theirs = {"X-API-Key": FIRST}, {"Authorization": f"Bearer {SECOND}"}
        created = client.post("/v1/jobs/detect", files={"mesh": ("s.obj", sphere_obj)}, data={"key": KEY},
                              headers=mine)
        assert created.status_code == 202
        job = created.json()["id"]
        assert len(job) == 32 and int(job, 16) >= 0  # 128 random bits, hex
        client.headers.update(mine)
        wait_job(client, job)
        client.headers.pop("X-API-Key")
        for method, path in (("GET", f"/v1/jobs/{job}"), ("GET", f"/v1/jobs/{job}/result"),
                             ("DELETE", f"/v1/jobs/{job}")):
            assert_problem(client.request(method, path, headers=theirs), 404, "not-found")
        assert client.get(f"/v1/jobs/{job}/result", headers=mine).status_code == 200
        assert client.delete(f"/v1/jobs/{job}", headers=mine).status_code == 204


def test_the_body_is_not_read_before_the_key_is_checked():
    # a real server: a client declares 60 MB and sends none of it; without a valid key the answer
    # (401) comes at once, from the headers alone (the form was parsed first: 21 s of CPU)
    port = free_port()
    proc = start_server(port, {"MESHMARK_API_KEYS": FIRST, "MESHMARK_WORKERS": "1"})
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=10) as sock:
            sock.sendall(b"POST /v1/embed HTTP/1.1\r\nHost: x\r\nContent-Length: 60000000\r\n"
                         b"Content-Type: multipart/form-data; boundary=b\r\n\r\n")
            start = time.monotonic()
            answer = sock.recv(4096)
            assert answer.startswith(b"HTTP/1.1 401"), answer[:200]
            assert time.monotonic() - start < 5
    finally:
        proc.terminate()
        proc.wait(30)

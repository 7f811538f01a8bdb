"""The API process's memory is bounded by settings, not by callers (issue 15): job results on
disk within a byte budget, uploads in flight within a budget and a body-read timeout, a cap on
the process's resident memory."""

from __future__ import annotations

import re
import socket
import time
from pathlib import Path

from tests.app.conftest import KEY, assert_problem, make_client, wait_job
from tests.app.real_server import serve

BOUNDARY = "b0undary"


def _metric(client, name: str) -> float:
    match = re.search(rf"^{name} (\S+)$", client.get("/metrics").text, re.MULTILINE)
    assert match is not None, name
    return float(match.group(1))


def test_job_results_live_on_disk_within_a_budget(tmp_path, sphere_obj):
    # 40 results of 60 MB each took the API process from 543 MB to 2.9 GB; now they are files
    with make_client(workers=1, blob_dir=str(tmp_path)) as client:
        job = client.post("/v1/jobs/embed", files={"mesh": ("s.obj", sphere_obj)}, data={"key": KEY}).json()
        assert wait_job(client, job["id"])["state"] == "succeeded"
        result = client.get(f"/v1/jobs/{job['id']}/result")
        assert result.status_code == 200
        files = [p for p in tmp_path.rglob("*") if p.is_file()]
        assert [p.read_bytes() for p in files] == [result.content]
        assert files[0].stat().st_mode & 0o777 == 0o600
        assert _metric(client, "meshmark_job_result_bytes") == len(result.content)
        assert client.delete(f"/v1/jobs/{job['id']}").status_code == 204
        assert not [p for p in tmp_path.rglob("*") if p.is_file()]
        assert _metric(client, "meshmark_job_result_bytes") == 0
    assert not list(tmp_path.glob("results-*"))  # the store's directory goes with the process


def test_job_results_stay_within_their_byte_budget(tmp_path, sphere_obj):
    files = {"mesh": ("s.obj", sphere_obj)}
    with make_client(workers=1, blob_dir=str(tmp_path), max_result_bytes=1000) as client:
        # an embedding's answer is about as large as its upload: refused at once when it cannot fit
        body = assert_problem(client.post("/v1/jobs/embed", files=files, data={"key": KEY}), 429, "busy")
        assert "fetch and delete finished jobs" in body["detail"]
    room_for_one = len(sphere_obj) + 1000
    with make_client(workers=1, blob_dir=str(tmp_path), max_result_bytes=room_for_one) as client:
        # two admitted together (each fits alone): the second result to arrive fails its job
        jobs = [client.post("/v1/jobs/embed", files=files, data={"key": KEY}).json()["id"] for _ in range(2)]
        states = sorted((s["state"], (s["error"] or {}).get("type", "")) for s in
                        (wait_job(client, job) for job in jobs))
        assert states == [("failed", "https://meshmark.dev/problems/busy"), ("succeeded", "")], states
        response = client.post("/v1/jobs/embed", files=files, data={"key": KEY})
        assert_problem(response, 429, "busy")
        assert response.headers["retry-after"]
        for job in jobs:
            client.delete(f"/v1/jobs/{job}")
        assert client.post("/v1/jobs/embed", files=files, data={"key": KEY}).status_code == 202


def test_memory_cap_refuses_new_work_before_reading_it(sphere_obj):
    with make_client(workers=1, api_memory_mb=1) as client:  # any live process is above 1 MiB
        response = client.post("/v1/embed", files={"mesh": ("s.obj", sphere_obj)}, data={"key": KEY})
        assert "memory budget" in assert_problem(response, 429, "busy")["detail"]
        assert _metric(client, "meshmark_api_memory_limit_bytes") == 1 << 20
        assert _metric(client, "process_resident_memory_bytes") > 1 << 20
        assert client.get("/healthz").status_code == 200


def _upload_head(size: int) -> bytes:
    return (b"POST /v1/embed HTTP/1.1\r\nHost: x\r\nContent-Type: multipart/form-data; boundary="
            + BOUNDARY.encode() + b"\r\nContent-Length: %d\r\n\r\n" % size
            + f'--{BOUNDARY}\r\nContent-Disposition: form-data; name="mesh"; '.encode()
            + b'filename="m.obj"\r\n\r\n')


def _answer(sock: socket.socket, until_complete: bool = False) -> bytes:
    """The answer, until the server closes the connection (or, ``until_complete``, until its
    Content-Length has arrived)."""
    data = b""
    while chunk := sock.recv(65536):
        data += chunk
        head, _, body = data.partition(b"\r\n\r\n")
        length = re.search(rb"content-length: (\d+)", head.lower())
        if until_complete and length is not None and len(body) >= int(length.group(1)):
            break
    return data


def test_a_stalled_upload_is_cut_off(tmp_path: Path):
    with serve(tmp_path / "server.log", body_timeout_seconds="1") as server, \
            socket.create_connection(("127.0.0.1", server.port), timeout=20) as sock:
        sock.sendall(_upload_head(1_000_000) + b"v 0 0 0\n" * 100)  # ...and nothing more
        start = time.monotonic()
        answer = _answer(sock)
        assert answer.startswith(b"HTTP/1.1 408 "), answer[:300]
        assert b"body-timeout" in answer and b"connection: close" in answer.lower()
        assert time.monotonic() - start < 10


def test_uploads_in_flight_share_a_budget(tmp_path: Path):
    # 120 stalled uploads held 1.9 GB; bodies being received now count against one budget
    limit = 200_000
    budget = limit + 64 * 1024  # the smallest allowed: one request body
    with serve(tmp_path / "server.log", max_upload_bytes=str(limit), upload_budget_bytes=str(budget),
               body_timeout_seconds="20") as server, \
            socket.create_connection(("127.0.0.1", server.port), timeout=20) as first, \
            socket.create_connection(("127.0.0.1", server.port), timeout=20) as second:
        first.sendall(_upload_head(250_000) + b"v 0 0 0\n" * 25_000)  # 200 KB held, stalled
        time.sleep(1.0)
        second.sendall(_upload_head(250_000) + b"v 0 0 0\n" * 25_000)
        answer = _answer(second, until_complete=True)
        assert answer.startswith(b"HTTP/1.1 429 "), answer[:300]
        assert b"budget" in answer and b"retry-after" in answer.lower()

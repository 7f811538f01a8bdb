"""Faults around valid requests: a worker over its memory or time limit fails only its own
request (503 problem), while a valid request running beside it on the other worker gets
byte-identical output and the next request succeeds; and SIGTERM of the real server under load
lets the requests in flight finish (200, whole bodies), refuses new ones, and leaves no process.

``test_workers.py`` covers the same limits one request at a time (and SIGKILL mid-job, a full
queue, an idle worker dying); this module adds the concurrency and the shutdown.
"""

from __future__ import annotations

import logging
import re
import signal
import socket
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import httpx
import pytest

from core import api
from tests.app.conftest import assert_problem, detect, embed, make_client, wait_for
from tests.app.real_server import alive, descendants, serve

CANARY_KEY = "CANARY-KEY-c4f0-never-in-a-log"


@pytest.fixture(autouse=True)
def key_never_logged(caplog):
    caplog.set_level(logging.DEBUG)
    yield
    for record in caplog.records:
        assert CANARY_KEY not in record.getMessage()


def _address_space_mb(pid: int) -> int:
    with open(f"/proc/{pid}/status") as f:
        match = re.search(r"VmSize:\s+(\d+) kB", f.read())
    assert match
    return int(match.group(1)) // 1024


def _poison_beside_valid(client: Any, poison: bytes, valid: bytes, reference: bytes,
                         send: Any = embed) -> Any:
    """The poison (sent by ``send``) on one worker and, while it runs, three valid requests on the
    other."""
    pool = client.app.state.pool
    with ThreadPoolExecutor(4) as threads:
        bad = threads.submit(send, client, "poison.ply", poison, key=CANARY_KEY)
        wait_for(lambda: pool.running >= 1, timeout=10)
        good = [threads.submit(embed, client, "ok.ply", valid, key=CANARY_KEY) for _ in range(3)]
        for future in good:
            response = future.result(timeout=60)
            assert response.status_code == 200, response.text
            assert response.content == reference  # byte-identical next to a failing neighbour
        response = bad.result(timeout=60)
    after = embed(client, "ok.ply", valid, key=CANARY_KEY)
    assert after.status_code == 200 and after.content == reference
    wait_for(lambda: len(pool.live_workers()) == 2, timeout=20)  # the failed worker was replaced
    return response


def test_worker_over_its_memory_limit_fails_alone(big_ply, sphere_ply):
    reference = api.embed_file(sphere_ply, CANARY_KEY, filename="ok.ply").data
    with make_client(workers=1, worker_memory_mb=0) as probe:
        idle = _address_space_mb(probe.app.state.pool.live_workers()[0])
    with make_client(workers=2, worker_memory_mb=idle + 48) as client:
        response = _poison_beside_valid(client, big_ply, sphere_ply, reference)
        body = assert_problem(response, 503, "worker-failed")
        assert "out of memory" in body["detail"] or "died" in body["detail"]


def test_worker_over_its_time_limit_fails_alone(slow_ply, sphere_ply):
    reference = api.embed_file(sphere_ply, CANARY_KEY, filename="ok.ply").data
    # the poison, a detection of the unmarked 655k-vertex sphere, is 11-19 s of work; the valid
    # embeddings 0.1 s of CPU, but at the workers' lower priority (`NICENESS`) beside a busy
    # process they get a small share of a core: a 1 s limit timed them out too beside two busy loops
    with make_client(workers=2, job_timeout_seconds=4.0) as client:
        response = _poison_beside_valid(client, slow_ply, sphere_ply, reference, send=detect)
        assert "4 s" in assert_problem(response, 503, "timed-out")["detail"]
        assert 'meshmark_worker_restarts_total{reason="timeout"} 1' in client.get("/metrics").text


def test_sigterm_under_load_finishes_in_flight_requests(tmp_path, big_ply):
    """Four embeds admitted (two running, two queued) when SIGTERM arrives: all four finish with
    the whole, correct file; a new connection is refused (or answered 503); the server and all
    its worker processes are gone afterwards."""
    reference = api.embed_file(big_ply, CANARY_KEY, filename="big.ply").data
    with serve(tmp_path / "server.log", workers="2", job_timeout_seconds="60") as server:
        children = descendants(server.proc.pid)
        assert len(children) >= 2  # the fork server and the workers

        def embed() -> httpx.Response:
            with httpx.Client(base_url=server.base, timeout=90) as http:
                return http.post("/v1/embed", files={"mesh": ("big.ply", big_ply)}, data={"key": CANARY_KEY})

        with ThreadPoolExecutor(4) as threads:
            futures = [threads.submit(embed) for _ in range(4)]

            def admitted() -> bool:
                status = httpx.get(f"{server.base}/readyz", timeout=5).json()
                return bool(status["queued"] + status["running"] == 4)

            wait_for(admitted, timeout=30, interval=0.05)
            server.proc.send_signal(signal.SIGTERM)
            late = _late_request(server.port)
            responses = [f.result(timeout=120) for f in futures]

        for response in responses:
            assert response.status_code == 200, response.text[:300]
            assert response.headers["content-length"] == str(len(reference))
            assert response.content == reference
        assert late in ("refused", 503), late
        assert server.proc.wait(timeout=60) in (0, -signal.SIGTERM)
        wait_for(lambda: not [pid for pid in children if alive(pid)], timeout=15)
    assert CANARY_KEY not in server.text()
    assert "Traceback" not in server.text(), server.text()


def _late_request(port: int) -> str | int:
    """A request made just after SIGTERM: 'refused' when the socket is closed, else its status."""
    deadline = time.monotonic() + 5
    while time.monotonic() < deadline:  # uvicorn closes the listening socket right after the signal
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=2) as sock:
                sock.sendall(b"GET /readyz HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n")
                answer = sock.recv(100)
        except (ConnectionRefusedError, ConnectionResetError):
            return "refused"
        except TimeoutError:
            continue
        if answer.startswith(b"HTTP/1.1 503"):
            return 503
        time.sleep(0.05)  # answered before the signal was handled: try again
    return "still serving"


def test_busy_answer_comes_before_the_upload_is_read_and_the_connection_survives(tmp_path, big_ply):
    """With every task slot taken, an upload gets 429 without being parsed; the rest of its body
    is read and dropped, so a client still sending sees the answer (no connection reset), and a
    kept-alive connection serves the next request."""
    upload = big_ply[:2_000_000]
    boundary = "b0undary"
    body = (f'--{boundary}\r\nContent-Disposition: form-data; name="key"\r\n\r\n{CANARY_KEY}\r\n'
            f'--{boundary}\r\nContent-Disposition: form-data; name="mesh"; filename="m.ply"\r\n\r\n'
            ).encode() + upload + f"\r\n--{boundary}--\r\n".encode()

    def request(extra: bytes = b"") -> bytes:
        return (b"POST /v1/embed HTTP/1.1\r\nHost: x\r\nContent-Type: multipart/form-data; boundary="
                + boundary.encode() + b"\r\nContent-Length: %d\r\n" % len(body) + extra + b"\r\n" + body)

    with serve(tmp_path / "server.log", workers="1", queue_size="1") as server, \
            httpx.Client(base_url=server.base, timeout=60) as http:
        job = http.post("/v1/jobs/embed", files={"mesh": ("big.ply", big_ply)}, data={"key": CANARY_KEY})
        assert job.status_code == 202
        with socket.create_connection(("127.0.0.1", server.port), timeout=30) as sock:
            for extra in (b"", b""):  # twice on one kept-alive connection
                start = time.perf_counter()
                sock.sendall(request(extra))
                answer = _read_answer(sock)
                assert answer.startswith(b"HTTP/1.1 429 "), answer[:200]
                assert b"retry-after" in answer.lower() and time.perf_counter() - start < 1.0
        with socket.create_connection(("127.0.0.1", server.port), timeout=30) as sock:
            sock.sendall(request(b"Connection: close\r\n"))
            answer = b""
            while chunk := sock.recv(65536):  # a reset here would raise ConnectionResetError
                answer += chunk
            assert answer.startswith(b"HTTP/1.1 429 "), answer[:200]
        status = http.get(f"/v1/jobs/{job.json()['id']}").json()
        assert status["state"] in ("queued", "running", "succeeded")
    assert CANARY_KEY not in server.text()


def _read_answer(sock: socket.socket) -> bytes:
    data = b""
    while b"\r\n\r\n" not in data:
        data += sock.recv(65536)
    head, _, rest = data.partition(b"\r\n\r\n")
    length = int(re.search(rb"(?i)content-length: (\d+)", head).group(1))  # type: ignore[union-attr]
    while len(rest) < length:
        rest += sock.recv(65536)
    return head + b"\r\n\r\n" + rest

"""The real server, started the way the README says (``meshmark serve``), over a real socket."""

from __future__ import annotations

import http.client
import signal

import httpx
import pytest

from tests.app.conftest import KEY, shared_mesh, wait_for
from tests.app.real_server import alive, descendants, serve


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """The real server started with the README's command path (``meshmark serve``), 1 worker."""
    with serve(tmp_path_factory.mktemp("server") / "server.log", log_level="warning") as running:
        yield running.base, running.port, running.proc


def test_round_trip_over_a_socket(server):
    base, _, _ = server
    spot = shared_mesh("spot.obj")
    with httpx.Client(base_url=base, timeout=60) as http:
        assert http.get("/readyz").json()["workers"] == 1
        marked = http.post("/v1/embed", files={"mesh": ("spot.obj", spot)}, data={"key": KEY})
        assert marked.status_code == 200
        assert marked.headers["content-disposition"] == 'attachment; filename="spot.marked.obj"'
        found = http.post("/v1/detect", files={"mesh": ("spot.marked.obj", marked.content)},
                          headers={"X-Watermark-Key": KEY}).json()
        assert found["detected"] is True
        assert "meshmark_workers_live 1" in http.get("/metrics").text


def test_key_header_must_be_utf8(server):
    _, port, _ = server
    body = (b"--b\r\nContent-Disposition: form-data; name=\"mesh\"; filename=\"s.obj\"\r\n\r\n"
            b"v 0 0 0\r\n--b--\r\n")
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
    try:
        conn.putrequest("POST", "/v1/embed")
        conn.putheader("Content-Type", "multipart/form-data; boundary=b")
        conn.putheader("Content-Length", str(len(body)))
        conn.putheader("X-Watermark-Key", b"caf\xe9")  # Latin-1 bytes, not UTF-8
        conn.endheaders(body)
        response = conn.getresponse()
        assert response.status == 422
        assert b"X-Watermark-Key header must be UTF-8" in response.read()
    finally:
        conn.close()


def test_sigterm_stops_server_and_workers(server):
    base, _, proc = server
    assert httpx.get(f"{base}/readyz").status_code == 200
    pids = descendants(proc.pid)
    assert pids  # the fork server and the worker
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(timeout=30) in (0, -signal.SIGTERM)  # uvicorn re-raises the signal after shutdown
    # the fork server and multiprocessing's resource tracker notice their parent is gone and exit
    wait_for(lambda: not [pid for pid in pids if alive(pid)], timeout=10)

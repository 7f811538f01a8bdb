"""Fixtures of the service tests: apps with real worker pools, real and generated meshes.

Nothing here fakes the engine: every request runs ``core`` in a worker process.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

import pytest
import trimesh
from fastapi.testclient import TestClient

from app.config import Settings
from app.main import create_app
from tests.conftest import shared_mesh_path

KEY = "correct horse battery staple"


def make_client(**overrides: Any) -> TestClient:
    """A client whose app has the given settings; use as a context manager (runs the lifespan)."""
    return TestClient(create_app(Settings(**{"workers": 2, **overrides})))


@pytest.fixture(scope="module")
def client() -> Iterator[TestClient]:
    """One app (two workers) shared by the tests of a module."""
    with make_client() as c:
        yield c


@pytest.fixture(scope="session")
def sphere_obj() -> bytes:
    """A generated icosphere (10,242 vertices) as OBJ text: small and fast to watermark, and fine enough
    for the default method within the displacement ceiling (2,562 vertices are not)."""
    return trimesh.creation.icosphere(subdivisions=5).export(file_type="obj").encode()


@pytest.fixture(scope="session")
def sphere_ply() -> bytes:
    return trimesh.creation.icosphere(subdivisions=5).export(file_type="ply")


@pytest.fixture(scope="session")
def slow_ply() -> bytes:
    """A 655,362-vertex icosphere (24 MB binary PLY): several seconds of work on any machine (its
    embedding 3-5 s, its detection, unmarked, 11-19 s), far beyond the time-limit tests' 4 s."""
    return trimesh.creation.icosphere(subdivisions=8).export(file_type="ply")


@pytest.fixture(scope="session")
def big_ply() -> bytes:
    """A 163,842-vertex icosphere (6 MB binary PLY): about 2 s of work and +100 MB in a worker."""
    return trimesh.creation.icosphere(subdivisions=7).export(file_type="ply")


def shared_mesh(name: str) -> bytes:
    return shared_mesh_path(name).read_bytes()


def embed(client: TestClient, name: str, data: bytes, key: str = KEY, **fields: str) -> Any:
    return client.post("/v1/embed", files={"mesh": (name, data)}, data={"key": key, **fields})


def detect(client: TestClient, name: str, data: bytes, key: str = KEY, **fields: str) -> Any:
    return client.post("/v1/detect", files={"mesh": (name, data)}, data={"key": key, **fields})


def assert_problem(response: Any, status: int, slug: str) -> dict[str, Any]:
    assert response.status_code == status, response.text[:1000]
    assert response.headers["content-type"] == "application/problem+json"
    body: dict[str, Any] = response.json()
    assert body["type"] == f"https://meshmark.dev/problems/{slug}", body
    assert body["status"] == status and body["title"] and body["detail"]
    return body


def wait_for(predicate: Callable[[], Any], timeout: float = 30.0, interval: float = 0.01) -> Any:
    """Poll until ``predicate()`` is truthy; returns its value."""
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"condition not met within {timeout} s")
        time.sleep(interval)


def wait_job(client: TestClient, job_id: str, timeout: float = 60.0) -> dict[str, Any]:
    """Poll a job until it finishes; returns its last status."""
    def finished() -> dict[str, Any] | None:
        status: dict[str, Any] = client.get(f"/v1/jobs/{job_id}").json()
        return status if status["state"] in ("succeeded", "failed", "cancelled") else None

    result: dict[str, Any] = wait_for(finished, timeout)
    return result


CALLBACK_SECRET = "callback-secret-for-tests"


class Receiver:
    """A real HTTP server on 127.0.0.1 that records the callbacks it gets and answers each with
    the next status of ``answers`` (then 200)."""

    def __init__(self) -> None:
        self.received: list[tuple[float, dict[str, str], bytes]] = []
        self.answers: list[int] = []
        receiver = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self) -> None:
                body = self.rfile.read(int(self.headers.get("content-length", 0)))
                receiver.received.append((time.monotonic(), dict(self.headers.items()), body))
                status = receiver.answers.pop(0) if receiver.answers else 200
                self.send_response(status)
                self.send_header("content-length", "0")
                self.end_headers()

            def log_message(self, *args: Any) -> None:
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}/hook"
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()


@pytest.fixture
def receiver() -> Iterator[Receiver]:
    r = Receiver()
    yield r
    r.close()

"""``meshmark.client`` and ``meshmark --server`` against a real ``meshmark serve`` over a socket."""

from __future__ import annotations

import asyncio
import email.utils
import json
import os
import subprocess
import threading
import time

import httpx
import pytest

from core import api
from meshmark.client import AsyncClient, Client, ProblemError, _retry_delay
from tests.app.conftest import KEY
from tests.app.real_server import MESHMARK, serve
from tests.conftest import shared_mesh_path

TETRAHEDRON = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n"


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """One worker, one stored job at a time (so that a second job is refused with 429)."""
    with serve(tmp_path_factory.mktemp("client") / "server.log", max_stored_jobs="1") as running:
        yield running


@pytest.fixture(scope="module")
def spot(tmp_path_factory):
    path = tmp_path_factory.mktemp("meshes") / "spot.obj"
    path.write_bytes(shared_mesh_path("spot.obj").read_bytes())
    return path


def test_embed_detect_capacity_match_the_engine(server, spot, tmp_path):
    """The client's answers are the engine's: same marked bytes, same report; progress rises to 1;
    the job is deleted once fetched."""
    local = api.embed(spot.read_bytes(), api.Options(key=KEY), filename="spot.obj")
    seen: list[float] = []
    out = tmp_path / "spot.marked.obj"
    with Client(server.base, poll_interval=0.05) as mm:
        report = mm.embed(spot, out, key=KEY, progress=seen.append)
        assert out.read_bytes() == local.data and report == local.report.to_dict()
        assert seen == sorted(seen) and seen[-1] == 1.0
        assert [p.name for p in tmp_path.iterdir()] == ["spot.marked.obj"]  # no temporary file left
        found = mm.detect(out, key=KEY)
        assert found["detected"] is True and found["key_derived"] is True
        capacity = mm.capacity(spot, method="planes")
        assert capacity == api.capacity(spot.read_bytes(), api.Options(method="planes")).to_dict()
    assert httpx.get(f"{server.base}/metrics").text.count('meshmark_jobs{state="succeeded"} 0.0') == 1


def test_a_refusal_raises_the_problem(server, tmp_path):
    out = tmp_path / "t.marked.obj"
    with Client(server.base) as mm, pytest.raises(ProblemError) as err:
        mm.embed(TETRAHEDRON, out, key=KEY, filename="t.obj")
    problem = err.value
    assert problem.status == 422 and problem.type.endswith("/too-little-capacity")
    assert str(problem).startswith("Too little capacity for the watermark: too little capacity: ")
    assert problem.request_id and problem.request_id in str(problem)
    assert not out.exists()
    with Client(server.base) as mm, pytest.raises(ProblemError) as err:
        mm.capacity(b"", filename="empty.obj")
    assert err.value.status == 415 and "the file is empty" in str(err.value)


def test_busy_is_retried_after_retry_after(server, spot, tmp_path):
    """With the one job place taken, the next job is refused 429 busy; the client waits for
    Retry-After and tries again, and gets through once the place is freed."""
    with httpx.Client(base_url=server.base, timeout=60) as raw:
        holder = raw.post("/v1/jobs/detect", files={"mesh": ("spot.obj", spot.read_bytes())},
                          data={"key": KEY})
        assert holder.status_code == 202
        with Client(server.base, retries=0) as impatient, pytest.raises(ProblemError) as err:
            impatient.detect(spot, key=KEY)
        assert err.value.status == 429
        freed = threading.Timer(1.5, lambda: raw.delete(holder.headers["location"]))
        freed.start()
        start = time.monotonic()
        with Client(server.base, retries=5, max_wait=2) as patient:
            while raw.get(holder.headers["location"]).json()["state"] != "succeeded":
                time.sleep(0.05)  # the holder must be finished for DELETE to free its place
            assert patient.detect(spot, key=KEY)["detected"] is False
        freed.join()
        assert time.monotonic() - start >= 1.0


def test_async_client(server, spot, tmp_path):
    async def work() -> tuple[dict, dict]:
        async with AsyncClient(server.base, poll_interval=0.05) as mm:
            report = await mm.embed(spot, tmp_path / "a.obj", key=KEY, payload="1011")
            return report, await mm.detect(tmp_path / "a.obj", key=KEY)

    report, found = asyncio.run(work())
    assert report["payload_bits"] == 4 and found["payload"] == "1011" and found["crc_ok"] is True
    local = api.embed(spot.read_bytes(), api.Options(key=KEY, payload="1011"), filename="spot.obj")
    assert (tmp_path / "a.obj").read_bytes() == local.data


def test_cli_with_server_prints_and_writes_what_the_local_cli_does(server, spot, tmp_path):
    def meshmark(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[bytes]:
        return subprocess.run([str(MESHMARK), *args], capture_output=True, timeout=120,
                              env={**os.environ, "MESHMARK_KEY": KEY, **(env or {})})

    local = meshmark("embed", str(spot), str(tmp_path / "local.obj"))
    remote = meshmark("embed", str(spot), str(tmp_path / "remote.obj"), "--server", server.base)
    assert local.returncode == remote.returncode == 0, remote.stderr
    assert remote.stdout == local.stdout
    assert (tmp_path / "remote.obj").read_bytes() == (tmp_path / "local.obj").read_bytes()
    detected = meshmark("detect", str(tmp_path / "remote.obj"), env={"MESHMARK_SERVER": server.base})
    assert detected.returncode == 0 and json.loads(detected.stdout)["detected"] is True
    refused = meshmark("embed", "-", "-", "--server", server.base)  # nothing on stdin
    assert refused.returncode == 2 and b"the file is empty" in refused.stderr
    unreachable = meshmark("capacity", str(spot), "--server", "http://127.0.0.1:9")
    assert unreachable.returncode == 4 and b"cannot reach" in unreachable.stderr


def test_retry_delay_follows_retry_after_within_bounds():
    """Seconds or an HTTP date, as RFC 9110 allows; exponential without one; never over max_wait."""
    def answer(**headers: str) -> httpx.Response:
        return httpx.Response(503, headers=headers)

    assert _retry_delay(answer(**{"Retry-After": "3"}), 0, max_wait=30) == 3
    assert _retry_delay(answer(**{"Retry-After": "120"}), 0, max_wait=30) == 30
    in_two = email.utils.formatdate(time.time() + 2, usegmt=True)
    assert 0.5 < _retry_delay(answer(**{"Retry-After": in_two}), 0, max_wait=30) <= 2
    assert [_retry_delay(answer(), n, max_wait=3) for n in range(4)] == [0.5, 1, 2, 3]
    assert _retry_delay(None, 1, max_wait=30) == 1  # a broken connection: exponential too

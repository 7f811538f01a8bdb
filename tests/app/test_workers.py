"""Worker processes: progress relay, failures confined to their own request, admission control.

Every failure here is real: a SIGKILL of a live worker process, a task past its time limit, an
address-space limit (RLIMIT_AS) that a large mesh exceeds.
"""

from __future__ import annotations

import asyncio
import os
import re
import signal
import threading
import time

import psutil

from app.workers.pool import WorkerPool
from app.workers.tasks import Task
from core.api import EmbeddedFile, Options
from tests.app.conftest import KEY, assert_problem, detect, embed, make_client, wait_for, wait_job


def test_progress_is_relayed_from_the_worker(sphere_obj):
    async def run() -> tuple[EmbeddedFile, list[float], int]:
        pool = WorkerPool(workers=1, slots=2, timeout=60, memory_mb=0, max_tasks=0)
        await pool.start()
        try:
            values: list[float] = []
            result = await pool.submit(Task("embed", sphere_obj, Options(key=KEY), filename="s.obj"),
                                       on_progress=values.append)
            return result, values, pool.pending
        finally:
            await pool.stop()

    result, values, pending = asyncio.run(run())
    assert isinstance(result, EmbeddedFile) and result.report.carriers > 0
    assert values[0] == 0.0  # the worker said it started
    assert any(0 < v < 1 for v in values), values  # and then how far it got
    assert values == sorted(values) and pending == 0


def _restarts(client, reason: str) -> int:
    text = client.get("/metrics").text
    match = re.search(rf'meshmark_worker_restarts_total{{reason="{reason}"}} (\d+)', text)
    assert match, "restart counter missing from /metrics"
    return int(match.group(1))


def test_sigkilled_worker_fails_only_its_own_job(sphere_obj, big_ply):
    """8 jobs on 2 workers; the worker running job 3 is SIGKILLed mid-job."""
    with make_client(workers=2) as client:
        pool = client.app.state.pool
        before = set(pool.live_workers())
        ids = []
        for i in range(8):
            name, data = ("big.ply", big_ply) if i == 2 else ("s.obj", sphere_obj)
            response = client.post("/v1/jobs/embed", files={"mesh": (name, data)}, data={"key": KEY})
            assert response.status_code == 202, response.text
            ids.append(response.json()["id"])
        target = ids[2]
        # mid-job: the worker has parsed the mesh and is embedding
        wait_for(lambda: client.get(f"/v1/jobs/{target}").json()["progress"] >= 0.1, timeout=30)
        pid = pool.running_tasks()[target]
        assert pid in before
        os.kill(pid, signal.SIGKILL)

        states = {job_id: wait_job(client, job_id) for job_id in ids}
        failed = {job_id: s for job_id, s in states.items() if s["state"] != "succeeded"}
        assert list(failed) == [target], states
        error = failed[target]["error"]
        assert error["status"] == 503 and error["type"] == "https://meshmark.dev/problems/worker-failed"
        assert _restarts(client, "crashed") == 1

        # the pool replaced the worker and keeps working
        live = wait_for(lambda: len(pool.live_workers()) == 2 and pool.live_workers())
        assert pid not in live
        assert embed(client, "s.obj", sphere_obj).status_code == 200
        assert client.get("/readyz").json()["workers"] == 2


def test_sigkilled_worker_fails_its_synchronous_request(big_ply, sphere_obj):
    with make_client(workers=1) as client:
        pool = client.app.state.pool
        responses = []
        request = threading.Thread(target=lambda: responses.append(embed(client, "big.ply", big_ply)))
        request.start()
        (pid,) = wait_for(lambda: list(pool.running_tasks().values()))
        os.kill(pid, signal.SIGKILL)
        request.join(timeout=60)
        body = assert_problem(responses[0], 503, "worker-failed")
        assert "died" in body["detail"]
        assert responses[0].headers["retry-after"] == "1"
        assert embed(client, "s.obj", sphere_obj).status_code == 200


def test_timeout_kills_the_task_not_the_service(slow_ply, sphere_obj):
    # a limit far from both: the detection of the unmarked 655k-vertex sphere is 11-19 s of work, the
    # small embedding 0.1 s of CPU at the worker's lower priority (a 1 s limit timed it out beside
    # two busy loops)
    with make_client(workers=1, job_timeout_seconds=4.0) as client:
        body = assert_problem(detect(client, "big.ply", slow_ply), 503, "timed-out")
        assert "4 s" in body["detail"]
        assert _restarts(client, "timeout") == 1
        again = embed(client, "s.obj", sphere_obj)
        assert again.status_code == 200, again.text


def _address_space_mb(pid: int) -> int:
    return int(psutil.Process(pid).memory_info().vms) // (1024 * 1024)


def test_memory_limit_fails_only_the_large_request(big_ply, sphere_obj):
    with make_client(workers=1, worker_memory_mb=0) as probe:
        idle = _address_space_mb(probe.app.state.pool.live_workers()[0])
    limit = idle + 48  # room for small meshes (+5 MB), not for the big one (+100 MB)
    with make_client(workers=1, worker_memory_mb=limit) as client:
        (pid,) = client.app.state.pool.live_workers()
        assert psutil.Process(pid).rlimit(psutil.RLIMIT_AS) == (limit * 1024 * 1024,) * 2
        body = assert_problem(embed(client, "big.ply", big_ply), 503, "worker-failed")
        assert "out of memory" in body["detail"] or "died" in body["detail"]
        assert embed(client, "s.obj", sphere_obj).status_code == 200


def test_full_queue_answers_429(big_ply, sphere_obj):
    with make_client(workers=1, queue_size=1) as client:
        job = client.post("/v1/jobs/embed", files={"mesh": ("big.ply", big_ply)}, data={"key": KEY}).json()
        response = embed(client, "s.obj", sphere_obj)
        body = assert_problem(response, 429, "busy")
        assert "1 task slots" in body["detail"]
        assert 1 <= int(response.headers["retry-after"]) <= 60
        response = client.post("/v1/jobs/detect", files={"mesh": ("s.obj", sphere_obj)}, data={"key": KEY})
        assert_problem(response, 429, "busy")
        assert "meshmark_queue_capacity 1" in client.get("/metrics").text

        assert client.delete(f"/v1/jobs/{job['id']}").json()["state"] == "cancelled"  # frees the slot
        assert wait_for(lambda: embed(client, "s.obj", sphere_obj).status_code == 200, timeout=30)


def test_retry_after_counts_the_time_running_tasks_have_taken(slow_ply, sphere_obj):
    # tasks that hold their worker long (hostile uploads: 85 s each) were answered Retry-After: 2,
    # from the mean of the tasks finished earlier; the running ones' time counts now
    with make_client(workers=1, queue_size=1) as client:
        job = client.post("/v1/jobs/embed", files={"mesh": ("slow.ply", slow_ply)}, data={"key": KEY}).json()
        assert wait_for(lambda: client.get(f"/v1/jobs/{job['id']}").json()["state"] == "running", timeout=30)
        time.sleep(1.5)  # the job runs for several seconds; main said 1 (the mean of no finished task)
        response = embed(client, "s.obj", sphere_obj)
        assert_problem(response, 429, "busy")
        assert int(response.headers["retry-after"]) >= 2
        client.delete(f"/v1/jobs/{job['id']}")


def test_idle_worker_killed_between_requests(sphere_obj):
    """pebble gives up on a pool whose worker dies with no task running; a new pool replaces it
    without waiting for a request (a failing readiness probe would keep requests away)."""
    with make_client(workers=1) as client:
        pool = client.app.state.pool
        (pid,) = pool.live_workers()
        os.kill(pid, signal.SIGKILL)
        new = wait_for(lambda: [p for p in pool.live_workers() if p != pid], timeout=10)
        assert client.get("/readyz").json()["workers"] == 1 and pid not in new
        assert _restarts(client, "pool-broken") == 1
        assert embed(client, "s.obj", sphere_obj).status_code == 200

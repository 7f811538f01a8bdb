"""Jobs through Redis + Celery against the in-process worker pool, with the same number of workers.

Both through the jobs *runner* (what ``POST /v1/jobs/embed`` calls, without the HTTP layer, which is
the same for both backends):

- **Throughput**: ``N`` embeds of ``beetle.off`` (19,887 vertices) submitted at once, from the first
  submit to the last job seen finished (the store's counts, polled every 50 ms).  In-process: a
  :class:`~app.workers.pool.WorkerPool` with ``--jobs`` processes.  Redis: ``--jobs`` separate
  ``meshmark worker --concurrency 1`` processes.  Rounds alternate between the two backends so that
  both see the same background load; the ratio is the median of the rounds' ratios.  The CPU time
  of every process taking part (this one, the workers, their children, redis-server) is counted
  too: per job, it does not depend on what else the machine runs.  No worker is recycled during
  the run (``worker_max_tasks = 0`` on both sides), so that every CPU second is still accounted for.
- **Queueing overhead**: one job at a time, submit to seen finished (store polled every 1 ms): a
  *no-op* job (an empty upload, refused at once by the engine) and a small embed (a 2,562-vertex
  icosphere, minus the same embed called directly in this process, interleaved).

Redis: ``$MESHMARK_BENCH_REDIS_URL`` (default ``redis://127.0.0.1:6379/15``); a namespace of its own,
deleted at the end.
"""

from __future__ import annotations

import argparse
import asyncio
import itertools
import os
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path
from typing import Any

from bench.common import KEY, child_pids, cpu_seconds, environment, header, md_table, mesh_path, save_json

REDIS_URL = os.environ.get("MESHMARK_BENCH_REDIS_URL", "redis://127.0.0.1:6379/15")
THROUGHPUT_MESH = "beetle.off"


def _loadavg() -> str:
    try:
        return " ".join(Path("/proc/loadavg").read_text().split()[:3])
    except OSError:
        return "?"


def _start_workers(n: int, env: dict[str, str], logs: Path) -> list[subprocess.Popen[bytes]]:
    script = Path(sys.executable).with_name("meshmark")
    command = [str(script)] if script.exists() else [sys.executable, "-m", "app.cli"]
    workers = []
    for i in range(n):
        with (logs / f"worker{i}.log").open("wb") as out:
            workers.append(
                subprocess.Popen(
                    [*command, "worker", "--concurrency", "1"],
                    env={**os.environ, **env, "MESHMARK_LOG_LEVEL": "warning"},
                    stdout=out,
                    stderr=subprocess.STDOUT,
                )
            )
    return workers


async def _wait_ready(runner: Any, workers: list[subprocess.Popen[bytes]], task: Any) -> None:
    """Until every worker has taken a job (Celery prints nothing at log level warning)."""
    deadline = time.monotonic() + 120
    seen: set[str] = set()
    while len(seen) < len(workers):
        if time.monotonic() > deadline or any(w.poll() is not None for w in workers):
            raise RuntimeError("the Celery workers did not start (see their logs)")
        jobs = [await runner.submit(task) for _ in workers]
        for job in jobs:
            while not (await runner.store.get(job.id)).done:
                await asyncio.sleep(0.01)
            seen.add((await runner.store.fields(job.id)).get("worker", ""))
            await runner.store.delete(job.id)


def _redis_server_pid() -> int | None:
    import redis

    try:
        info = redis.Redis.from_url(REDIS_URL).info("server")
    except redis.RedisError:
        return None
    return int(info["process_id"]) if Path(f"/proc/{info['process_id']}").exists() else None


async def _idle_gaps(runner: Any, ids: list[str]) -> list[float]:
    """Redis only: seconds each worker process waited between finishing a job and starting its next
    (from the jobs' ``started``/``finished`` stamps)."""
    by_worker: dict[str, list[tuple[float, float]]] = {}
    for job_id in ids:
        f = await runner.store.fields(job_id)
        runs = by_worker.setdefault(f"{f['worker']}:{f['pid']}", [])
        runs.append((float(f["started"]), float(f["finished"])))
    gaps = []
    for runs in by_worker.values():
        runs.sort()
        gaps += [b[0] - a[1] for a, b in itertools.pairwise(runs)]
    return gaps


async def _throughput(runner: Any, task: Any, n: int, gaps: list[float] | None = None) -> float:
    """Jobs per second for ``n`` jobs submitted at once."""
    t0 = time.perf_counter()
    ids = [(await runner.submit(task)).id for _ in range(n)]
    while True:
        counts = await runner.store.count()
        if counts["succeeded"] + counts["failed"] + counts["cancelled"] >= n:
            break
        await asyncio.sleep(0.05)
    seconds = time.perf_counter() - t0
    if counts["succeeded"] != n:
        raise RuntimeError(f"only {counts['succeeded']} of {n} jobs succeeded: {counts}")
    if gaps is not None:
        gaps += await _idle_gaps(runner, ids)
    for job_id in ids:
        await runner.store.delete(job_id)
    return n / seconds


async def _round_trip(runner: Any, task: Any) -> float:
    """Seconds from submit to seen finished, for one job alone."""
    t0 = time.perf_counter()
    job = await runner.submit(task)
    while not (await runner.store.get(job.id)).done:
        await asyncio.sleep(0.001)
    seconds = time.perf_counter() - t0
    await runner.store.delete(job.id)
    return seconds


def _inline_seconds(task: Any) -> float:
    t0 = time.perf_counter()
    task.run(lambda f: None)
    return time.perf_counter() - t0


async def _measure(args: argparse.Namespace, env: dict[str, str]) -> dict[str, Any]:
    import trimesh

    from app.config import Settings
    from app.memory_jobs import InMemoryJobStore, LocalJobRunner
    from app.redis_jobs.runner import CeleryJobRunner
    from app.workers.pool import WorkerPool
    from app.workers.tasks import Task
    from core.options import Options

    n_workers = args.jobs
    n_jobs = 16 if args.quick else 60
    rounds = 2 if args.quick else 9
    trips = 10 if args.quick else 30
    beetle = Task("embed", data=mesh_path(THROUGHPUT_MESH).read_bytes(), options=Options(key=KEY),
                  filename=THROUGHPUT_MESH)
    sphere = trimesh.creation.icosphere(subdivisions=4).export(file_type="obj").encode()
    small = Task("embed", data=sphere, options=Options(key=KEY), filename="sphere.obj")
    noop = Task("embed", data=b"", options=Options(key=KEY), filename="empty.obj")

    pool = WorkerPool(workers=n_workers, slots=4 * n_jobs, timeout=120, memory_mb=0, max_tasks=0)
    await pool.start()
    local = LocalJobRunner(InMemoryJobStore(), pool, ttl=3600, max_jobs=4 * n_jobs)
    settings = Settings(jobs_backend="redis", redis_url=env["MESHMARK_REDIS_URL"],
                        jobs_queue=env["MESHMARK_JOBS_QUEUE"], blob_dir=Path(env["MESHMARK_BLOB_DIR"]),
                        max_stored_jobs=4 * n_jobs)
    remote = CeleryJobRunner.from_settings(settings)
    logs = Path(env["MESHMARK_BLOB_DIR"]).parent
    workers = _start_workers(n_workers, env, logs)
    redis_pid = _redis_server_pid()
    result: dict[str, Any] = {"workers": n_workers, "jobs_per_round": n_jobs, "rounds": rounds,
                              "mesh": THROUGHPUT_MESH, "load_before": _loadavg()}

    def pids(backend: str) -> list[int]:
        if backend == "in-process":
            return [os.getpid(), *pool.live_workers()]
        nodes = [w.pid for w in workers]
        return [os.getpid(), *nodes, *(c for n in nodes for c in child_pids(n)),
                *([redis_pid] if redis_pid else [])]

    try:
        await _wait_ready(remote, workers, small)
        backends = {"in-process": local, "redis": remote}
        for runner in backends.values():  # warm-up: every worker has embedded the mesh once
            await _throughput(runner, beetle, 2 * n_workers)
        rates: dict[str, list[float]] = {name: [] for name in backends}
        cpu: dict[str, list[float]] = {name: [] for name in backends}
        gaps: list[float] = []
        for _ in range(rounds):
            for name, runner in backends.items():
                procs = pids(name)
                before = sum(cpu_seconds(p) for p in procs)
                rates[name].append(await _throughput(runner, beetle, n_jobs,
                                                     gaps if name == "redis" else None))
                cpu[name].append((sum(cpu_seconds(p) for p in procs) - before) / n_jobs)
        inline, round_trips = [], {name: {"noop": [], "small": []} for name in backends}
        for _ in range(trips):
            inline.append(_inline_seconds(small))
            for name, runner in backends.items():
                round_trips[name]["noop"].append(await _round_trip(runner, noop))
                round_trips[name]["small"].append(await _round_trip(runner, small))
        result.update(rates=rates, cpu_seconds_per_job=cpu, redis_idle_gaps=gaps,
                      inline_small_seconds=inline,
                      round_trips=round_trips, load_after=_loadavg())
    finally:
        await local.close()
        await pool.stop()
        await remote.close()
        for worker in workers:
            worker.send_signal(signal.SIGTERM)
        for worker in workers:
            try:
                worker.wait(timeout=20)
            except subprocess.TimeoutExpired:
                worker.kill()
    return result


def _versions() -> dict[str, str]:
    import celery
    import kombu
    import redis

    info = redis.Redis.from_url(REDIS_URL).info("server")
    return {
        "celery": celery.__version__,
        "kombu": kombu.__version__,
        "redis-py": redis.__version__,
        "redis-server": str(info.get("redis_version", "?")),
    }


def _ms(seconds: float) -> float:
    return seconds * 1000


def _report(result: dict[str, Any], env: dict[str, Any]) -> str:
    rates = {k: statistics.median(v) for k, v in result["rates"].items()}
    ratios = [r / i for r, i in zip(result["rates"]["redis"], result["rates"]["in-process"], strict=True)]
    ratio = statistics.median(ratios)
    cpu = {k: statistics.median(v) for k, v in result["cpu_seconds_per_job"].items()}
    inline = statistics.median(result["inline_small_seconds"])
    trips = result["round_trips"]
    noop = {k: statistics.median(v["noop"]) for k, v in trips.items()}
    small = {k: statistics.median(v["small"]) for k, v in trips.items()}
    gaps = result["redis_idle_gaps"]
    v = result["versions"]
    extra = [
        f"- Celery {v['celery']}, kombu {v['kombu']}, redis-py {v['redis-py']}, "
        f"Redis server {v['redis-server']} (on the same machine)",
        f"- Load average (1/5/15 min) before: {result['load_before']}; after: {result['load_after']}. "
        "The machine runs other work at the same time: wall-clock figures move with it, CPU "
        "seconds per job much less.",
    ]
    lines = [header("Jobs through Redis + Celery vs the in-process pool", env, extra), ""]
    lines += [
        "## Throughput",
        "",
        f"{result['jobs_per_round']} embeds of `{result['mesh']}` (19,887 vertices) submitted at once, "
        f"{result['workers']} worker processes on each side; {result['rounds']} rounds, alternating.",
        "",
        md_table(["backend", "jobs/s (median)", "jobs/s per round", "CPU ms per job (all processes)"],
                 [[k, rates[k], ", ".join(f"{r:.2f}" for r in result["rates"][k]), _ms(cpu[k])]
                  for k in rates]),
        f"Redis / in-process throughput: **{ratio:.0%}** (median of the rounds' ratios: "
        f"{', '.join(f'{r:.0%}' for r in ratios)}; goal: at least 90 %). "
        f"CPU per job, in-process / Redis: {cpu['in-process'] / cpu['redis']:.0%} (the throughput "
        "ratio to expect when the cores are saturated).",
        "",
        f"A Redis worker process waits between two jobs (its job acknowledged, the next message "
        f"fetched and handed to it: `prefetch_multiplier` 1 with `acks_late`): median "
        f"{_ms(statistics.median(gaps)):.1f} ms, mean {_ms(statistics.mean(gaps)):.1f} ms, against "
        f"{_ms(result['workers'] / rates['redis']):.0f} ms per job and process. The in-process "
        "pool's workers find their next task already in their pipe. Both run at nice 10 (as in "
        "production, to keep the API process responsive): when other work at nice 0 keeps the cores "
        "busy, a worker that sleeps between jobs gets the CPU back late, so the wall-clock ratio "
        "falls below the CPU ratio.",
        "",
        "## Queueing overhead per job",
        "",
        f"One job at a time ({len(result['inline_small_seconds'])} of each), submit to seen finished. "
        "*No-op*: an empty upload, which the engine refuses at once (the job fails): all of its round "
        "trip is overhead. *Small embed*: a 2,562-vertex icosphere, minus the same embed called "
        f"directly in this process ({_ms(inline):.1f} ms, median).",
        "",
        md_table(["backend", "no-op round trip ms", "small embed round trip ms", "small embed overhead ms"],
                 [[k, _ms(noop[k]), _ms(small[k]), _ms(small[k] - inline)] for k in noop]),
        f"Redis overhead: **{_ms(noop['redis']):.1f} ms** per job (no-op round trip; goal: under 20 ms).",
        "",
        "Per job, the Redis path adds: the upload written to the blob store, the job hash and one Celery "
        "message to Redis; on the worker, the begin/progress/finish scripts, the upload read and the "
        "result written; the client's status polls (one Redis read each).",
    ]
    return "\n".join(lines) + "\n"


def run(args: argparse.Namespace) -> None:
    try:
        import celery  # noqa: F401
        import redis

        redis.Redis.from_url(REDIS_URL, socket_connect_timeout=1).ping()
    except Exception as exc:  # nothing to measure here: say why
        print(f"[bench] redis: skipped: no Redis/Celery ({exc.__class__.__name__}: {exc})", flush=True)
        return
    scratch = Path(tempfile.mkdtemp(prefix="meshmark-bench-redis-"))
    namespace = f"mmbench-{uuid.uuid4().hex[:8]}"
    env = {
        "MESHMARK_REDIS_URL": REDIS_URL,
        "MESHMARK_JOBS_QUEUE": namespace,
        "MESHMARK_BLOB_DIR": str(scratch / "blobs"),
        "MESHMARK_WORKER_MEMORY_MB": "0",
    }
    try:
        result = asyncio.run(_measure(args, env))
    finally:
        client = redis.Redis.from_url(REDIS_URL)
        keys = list(client.scan_iter(match=f"*{namespace}*", count=1000))
        if keys:
            client.delete(*keys)
        shutil.rmtree(scratch, ignore_errors=True)
    result["versions"] = _versions()
    env_info = environment()
    out = Path(args.out)
    save_json(out / "redis.json", {"environment": env_info, **result})
    (out / "redis.md").write_text(_report(result, env_info))
    print((out / "redis.md").read_text(), flush=True)

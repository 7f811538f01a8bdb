"""The ``memory`` jobs backend (the default): jobs in this process's memory, run by its worker pool.

Jobs vanish on restart and are not shared between server processes; the ``redis`` backend
(:mod:`app.redis_jobs`) keeps them in Redis and runs them on Celery workers instead.  The job
records are small; results go to files (a private directory under ``blob_dir``), within a total
byte budget: 40 results kept in the process took it from 543 MB to 2.9 GB.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import time
from dataclasses import replace
from typing import Any

from app import callbacks
from app.blobs import BlobNotFound, LocalBlobStore
from app.jobs import STATES, Job, check_room, new_job_id
from app.problems import BUSY, INTERNAL, ProblemError
from app.results import Rendered
from app.workers.pool import WorkerPool
from app.workers.tasks import Task

log = logging.getLogger("meshmark.jobs")


class InMemoryJobStore:
    """A dict of immutable :class:`~app.jobs.Job` values; expired jobs are dropped when touched or
    counted.  Result bodies are files in ``result_dir`` (None: kept in memory, for tests of the
    store alone), at most ``max_result_bytes`` of them together."""

    def __init__(self, result_dir: str | os.PathLike[str] | None = None,
                 max_result_bytes: int = 1 << 62) -> None:
        self._jobs: dict[str, Job] = {}
        self._blobs = LocalBlobStore(result_dir) if result_dir is not None else None
        self._sizes: dict[str, int] = {}
        self.max_result_bytes = max_result_bytes
        self.result_bytes = 0

    def _purge(self) -> None:
        now = time.time()
        for job_id in [j.id for j in self._jobs.values() if j.expires is not None and j.expires <= now]:
            self._drop(job_id)

    def _drop(self, job_id: str) -> None:
        self._jobs.pop(job_id, None)
        self.result_bytes -= self._sizes.pop(job_id, 0)
        if self._blobs is not None:
            self._blobs.delete(job_id)

    def room_for_results(self, expected: int) -> bool:
        """Whether stored results leave room for ``expected`` more bytes under the budget."""
        self._purge()
        return self.result_bytes + expected <= self.max_result_bytes

    async def add(self, job: Job) -> None:
        self._jobs[job.id] = job

    async def get(self, job_id: str) -> Job | None:
        job = self._jobs.get(job_id)
        if job is not None and job.expires is not None and job.expires <= time.time():
            self._drop(job_id)
            return None
        return job

    async def update(self, job_id: str, **changes: Any) -> Job | None:
        job = await self.get(job_id)
        if job is None:
            return None
        result: Rendered | None = changes.get("result")
        if result is not None and self._blobs is not None:
            size = len(result.body)
            if self.result_bytes + size > self.max_result_bytes:
                raise ProblemError(BUSY, f"stored job results would exceed the server's "
                                   f"{self.max_result_bytes:,}-byte budget; fetch and delete finished "
                                   "jobs, or retry later", headers={"Retry-After": "60"})
            await asyncio.to_thread(self._blobs.put, job_id, result.body)
            self._sizes[job_id] = size
            self.result_bytes += size
            changes["result"] = replace(result, body=b"")  # the body is the file
        job = self._jobs[job_id] = replace(job, **changes)
        return job

    async def delete(self, job_id: str) -> None:
        self._drop(job_id)

    async def result(self, job: Job) -> Rendered | None:
        if job.result is None or self._blobs is None:
            return job.result
        try:
            body = await asyncio.to_thread(self._blobs.get, job.id)
        except BlobNotFound:  # deleted or expired meanwhile
            return None
        return replace(job.result, body=body)

    def close(self) -> None:
        """Delete every stored result (the jobs end with the process)."""
        for job_id in list(self._jobs):
            self._drop(job_id)
        if self._blobs is not None:
            with contextlib.suppress(OSError):
                self._blobs.root.rmdir()

    async def count(self) -> dict[str, int]:
        self._purge()
        counts: dict[str, int] = dict.fromkeys(STATES, 0)
        for job in self._jobs.values():
            counts[job.state] += 1
        return counts


class LocalJobRunner:
    """Admits a task into the worker pool, follows it, records the outcome in the store."""

    def __init__(self, store: InMemoryJobStore, pool: WorkerPool, *, ttl: float, max_jobs: int,
                 callback_secret: bytes = b"") -> None:
        self.store, self.pool, self.ttl, self.max_jobs = store, pool, ttl, max_jobs
        self.callback_secret = callback_secret
        self._watchers: set[asyncio.Task[None]] = set()

    async def submit(self, task: Task, callback_url: str | None = None, owner: str | None = None) -> Job:
        """Create a job for ``task``; raises a ``busy`` problem when the pool or the store is full."""
        await check_room(self.store, self.max_jobs, self.pool.retry_after())
        # an embedding answers a file about as large as its upload; a detection, a little JSON
        if not self.store.room_for_results(len(task.data) if task.kind == "embed" else 0):
            limit = self.store.max_result_bytes
            raise ProblemError(BUSY, f"stored job results fill the server's {limit:,}-byte budget; fetch and "
                               "delete finished jobs, or retry later", headers={"Retry-After": "60"})
        job = Job(id=new_job_id(), kind=task.kind, request_id=task.request_id, callback_url=callback_url,
                  owner=owner)
        await self.store.add(job)
        try:
            work = self.pool.submit(task, task_id=job.id, on_progress=lambda f: self._progress(job.id, f))
        except BaseException:
            await self.store.delete(job.id)
            raise
        self._watch(self._follow(job.id, work, task))
        return job

    def _watch(self, coroutine: Any) -> None:
        watcher = asyncio.ensure_future(coroutine)
        self._watchers.add(watcher)
        watcher.add_done_callback(self._watchers.discard)

    def _progress(self, job_id: str, fraction: float) -> None:
        self._watch(self._record_progress(job_id, fraction))

    async def _record_progress(self, job_id: str, fraction: float) -> None:
        job = await self.store.get(job_id)
        if job is None or job.done:
            return
        if job.state == "queued":
            await self.store.update(job_id, state="running", started=time.time(), progress=fraction)
        elif fraction > job.progress:
            await self.store.update(job_id, progress=fraction)

    async def _follow(self, job_id: str, work: asyncio.Task[Any], task: Task) -> None:
        try:
            value = await work
        except ProblemError as exc:
            await self._finish(job_id, state="failed", error=exc.to_dict())
            return
        except asyncio.CancelledError:
            await self._finish(job_id, state="cancelled")
            return
        try:
            result = task.render(value)
        except ProblemError as exc:  # a copy the registry refused (another one won the race)
            await self._finish(job_id, state="failed", error=exc.to_dict())
            return
        except Exception:
            log.exception("job %s: could not render the result", job_id)
            error = ProblemError(INTERNAL, "internal error").to_dict()
            await self._finish(job_id, state="failed", error=error)
            return
        del value
        try:
            await self._finish(job_id, state="succeeded", progress=1.0, result=result)
        except ProblemError as full:  # no room for the result: the job fails with the reason
            await self._finish(job_id, state="failed", error=full.to_dict())

    async def _finish(self, job_id: str, **changes: Any) -> None:
        job = await self.store.get(job_id)
        if job is None or job.done:
            return
        now = time.time()
        finished = await self.store.update(job_id, finished=now, expires=now + self.ttl, **changes)
        log.info("job %s (%s) %s", job_id, job.kind, changes["state"])
        if finished is not None and finished.callback_url:
            self._watch(callbacks.deliver(finished, self.callback_secret))

    async def cancel(self, job_id: str) -> Job | None:
        """Stop an unfinished job (its record stays, state ``cancelled``, until it expires)."""
        job = await self.store.get(job_id)
        if job is None or job.done:
            return job
        self.pool.cancel(job_id)
        await self._finish(job_id, state="cancelled")
        return await self.store.get(job_id)

    async def ready(self) -> dict[str, Any]:
        return {}  # the pool's own readiness is checked by /readyz

    async def close(self) -> None:
        """Stops following jobs; callbacks still being retried are dropped (the process is ending)."""
        for watcher in list(self._watchers):
            watcher.cancel()
        await asyncio.gather(*self._watchers, return_exceptions=True)
        self.store.close()

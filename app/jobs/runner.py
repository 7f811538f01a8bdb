"""Background jobs: admit a task into the worker pool, follow it, record the outcome in the store."""

from __future__ import annotations

import asyncio
import logging
import time
import uuid
from collections.abc import Callable
from typing import Any, Protocol

from app.jobs.store import Job, JobKind, JobResult, JobStore
from app.problems import BUSY, INTERNAL, ProblemError
from app.workers.pool import WorkerPool
from app.workers.tasks import Task

log = logging.getLogger("meshmark.jobs")

#: turns a task's return value into the response stored for ``GET /v1/jobs/{id}/result``
Render = Callable[[Any], JobResult]


class Runner(Protocol):
    """What the routes need of a jobs backend: :class:`JobRunner` (this process's worker pool) or
    :class:`app.jobs.celery_runner.CeleryJobRunner` (Celery workers through Redis)."""

    @property
    def store(self) -> JobStore: ...

    async def submit(self, kind: JobKind, task: Task, render: Render) -> Job: ...

    async def cancel(self, job_id: str) -> Job | None: ...

    async def ready(self) -> dict[str, Any]:
        """Facts for ``/readyz``; raises a ``not-ready`` problem when jobs cannot be taken."""

    async def close(self) -> None: ...


class JobRunner:
    def __init__(self, store: JobStore, pool: WorkerPool, *, ttl: float, max_jobs: int) -> None:
        self.store, self.pool, self.ttl, self.max_jobs = store, pool, ttl, max_jobs
        self._watchers: set[asyncio.Task[None]] = set()

    async def submit(self, kind: JobKind, task: Task, render: Render) -> Job:
        """Create a job for ``task``; raises a ``busy`` problem when the pool or the store is full."""
        stored = sum((await self.store.count()).values())
        if stored >= self.max_jobs:
            raise ProblemError(BUSY, f"{stored} jobs are stored (limit {self.max_jobs}); fetch or DELETE "
                               "finished jobs, or wait until they expire",
                               headers={"Retry-After": str(self.pool.retry_after())})
        job = Job(id=uuid.uuid4().hex, kind=kind)
        await self.store.add(job)
        try:
            work = self.pool.submit(task, task_id=job.id, on_progress=lambda f: self._progress(job.id, f))
        except BaseException:
            await self.store.delete(job.id)
            raise
        watcher = asyncio.ensure_future(self._follow(job.id, work, render))
        self._watchers.add(watcher)
        watcher.add_done_callback(self._watchers.discard)
        return job

    def _progress(self, job_id: str, fraction: float) -> None:
        watcher = asyncio.ensure_future(self._record_progress(job_id, fraction))
        self._watchers.add(watcher)
        watcher.add_done_callback(self._watchers.discard)

    async def _record_progress(self, job_id: str, fraction: float) -> None:
        job = await self.store.get(job_id)
        if job is None or job.done:
            return
        if job.state == "queued":
            await self.store.update(job_id, state="running", started=time.time(), progress=fraction)
        elif fraction > job.progress:
            await self.store.update(job_id, progress=fraction)

    async def _follow(self, job_id: str, work: asyncio.Task[Any], render: Render) -> None:
        try:
            value = await work
        except ProblemError as exc:
            await self._finish(job_id, state="failed", error=exc.to_dict())
            return
        except asyncio.CancelledError:
            await self._finish(job_id, state="cancelled")
            return
        try:
            result = render(value)
        except Exception:
            log.exception("job %s: could not render the result", job_id)
            error = ProblemError(INTERNAL, "internal error").to_dict()
            await self._finish(job_id, state="failed", error=error)
            return
        await self._finish(job_id, state="succeeded", progress=1.0, result=result)

    async def _finish(self, job_id: str, **changes: Any) -> None:
        job = await self.store.get(job_id)
        if job is None or job.done:
            return
        now = time.time()
        await self.store.update(job_id, finished=now, expires=now + self.ttl, **changes)
        log.info("job %s (%s) %s", job_id, job.kind, changes["state"])

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
        for watcher in list(self._watchers):
            watcher.cancel()
        await asyncio.gather(*self._watchers, return_exceptions=True)

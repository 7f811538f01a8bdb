"""The Redis backend of the jobs API, API side: jobs go to Celery workers (``meshmark worker``).

``submit`` writes the upload to the blob store, the job to Redis (``queued``), then sends the job
id, and nothing else, to the Celery queue.  Everything a job is lives in Redis and the blob store,
so restarting the API loses no job, and any number of API processes can share the workers.

The workers render results themselves, with the task's own kind (:meth:`app.workers.tasks.Task.render`),
as the in-process runner does.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from typing import Any

from app.blobs import BlobStore, LocalBlobStore
from app.config import Settings
from app.jobs import Job, check_room, new_job_id
from app.problems import NOT_READY, ProblemError
from app.redis_jobs.celery_app import CALLBACK_TASK, TASK_NAME, make_celery
from app.redis_jobs.store import RedisJobStore, input_key, unreachable
from app.redis_jobs.worker import encode_input
from app.workers.tasks import Task

log = logging.getLogger("meshmark.jobs")


class CeleryJobRunner:
    def __init__(self, store: RedisJobStore, celery: Any, blobs: BlobStore, *, queue: str,
                 max_jobs: int) -> None:
        self.store, self.celery, self.blobs = store, celery, blobs
        self.queue, self.max_jobs = queue, max_jobs

    @classmethod
    def from_settings(cls, settings: Settings) -> CeleryJobRunner:
        blobs = LocalBlobStore(settings.blob_dir)
        store = RedisJobStore.from_url(settings.redis_url, blobs, settings.jobs_queue,
                                       ttl=settings.job_result_ttl_seconds)
        return cls(store, make_celery(settings), blobs, queue=settings.jobs_queue,
                   max_jobs=settings.max_stored_jobs)

    async def submit(self, task: Task, callback_url: str | None = None, owner: str | None = None) -> Job:
        """Queue a job for ``task``; ``busy`` when the store is full, ``not-ready`` without Redis."""
        await check_room(self.store, self.max_jobs, retry_after=5)
        job = Job(id=new_job_id(), kind=task.kind, request_id=task.request_id, callback_url=callback_url,
                  owner=owner)
        await asyncio.to_thread(self.blobs.put, input_key(job.id), encode_input(task))
        try:
            await self.store.add(job)
            await asyncio.to_thread(self.celery.send_task, TASK_NAME, args=[job.id], task_id=job.id,
                                    queue=self.queue)
        except Exception as exc:
            await asyncio.to_thread(self.blobs.delete, input_key(job.id))
            with contextlib.suppress(ProblemError):
                await self.store.delete(job.id)
            if isinstance(exc, ProblemError):
                raise
            log.error("job %s: could not queue it: %r", job.id, exc)
            raise unreachable() from None
        return job

    async def cancel(self, job_id: str) -> Job | None:
        """Mark an unfinished job ``cancelled`` and revoke its message; a worker already running it
        stops at its next progress report (see :mod:`app.redis_jobs.worker`)."""
        job = await self.store.get(job_id)
        if job is None or job.done:
            return job
        if await self.store.finish(job_id, "cancelled"):
            log.info("job %s (%s) cancelled", job_id, job.kind)
            await asyncio.to_thread(self.blobs.delete, input_key(job_id))
            if job.callback_url:
                await asyncio.to_thread(self.celery.send_task, CALLBACK_TASK, args=[job_id], queue=self.queue)
            try:
                await asyncio.to_thread(self.celery.control.revoke, job_id)
            except Exception as exc:  # the state is what counts: workers check it before running
                log.warning("job %s: revoke not broadcast: %r", job_id, exc)
        return await self.store.get(job_id)

    async def ready(self) -> dict[str, Any]:
        if not await self.store.ping():
            raise ProblemError(NOT_READY, "the job queue (Redis) is unreachable",
                               headers={"Retry-After": "1"})
        return {"jobs_backend": "redis"}

    async def close(self) -> None:
        await self.store.close()
        await asyncio.to_thread(self.celery.close)

"""What the routes need of a jobs backend: :class:`Runner`.

Implementations: :class:`app.memory_jobs.LocalJobRunner` (this process's worker pool) and
:class:`app.redis_jobs.runner.CeleryJobRunner` (Celery workers through Redis).  Each renders a
finished task with the task's own kind (:data:`app.workers.tasks.TASKS`).
"""

from __future__ import annotations

from typing import Any, Protocol

from app.jobs.store import Job, JobStore
from app.problems import BUSY, ProblemError
from app.workers.tasks import Task


class Runner(Protocol):
    @property
    def store(self) -> JobStore: ...

    async def submit(self, task: Task, callback_url: str | None = None, owner: str | None = None) -> Job:
        """Create a job for ``task``; raises a problem (``busy``, ``not-ready``) when it cannot.
        ``callback_url`` (checked against the allowed hosts) receives the final status; only
        ``owner`` (see :attr:`app.jobs.Job.owner`) may see the job."""

    async def cancel(self, job_id: str) -> Job | None: ...

    async def ready(self) -> dict[str, Any]:
        """Facts for ``/readyz``; raises a ``not-ready`` problem when jobs cannot be taken."""

    async def close(self) -> None: ...


async def check_room(store: JobStore, max_jobs: int, retry_after: int) -> None:
    """A ``busy`` problem when ``max_jobs`` jobs are stored already, finished or not."""
    stored = sum((await store.count()).values())
    if stored >= max_jobs:
        raise ProblemError(BUSY, f"{stored} jobs are stored (limit {max_jobs}); fetch or DELETE finished "
                           "jobs, or wait until they expire", headers={"Retry-After": str(retry_after)})

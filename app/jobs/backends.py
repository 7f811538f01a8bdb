"""The jobs backend chosen by ``MESHMARK_JOBS_BACKEND``: ``memory`` (default) or ``redis``."""

from __future__ import annotations

from app.config import Settings
from app.jobs.runner import JobRunner, Runner
from app.jobs.store import InMemoryJobStore
from app.workers.pool import WorkerPool


def make_runner(settings: Settings, pool: WorkerPool) -> Runner:
    """The in-process runner on ``pool``, or the Celery runner (imported only when chosen, so that
    a single machine needs neither Celery nor Redis installed)."""
    if settings.jobs_backend == "redis":
        from app.jobs.celery_runner import CeleryJobRunner

        return CeleryJobRunner.from_settings(settings)
    return JobRunner(InMemoryJobStore(), pool, ttl=settings.job_result_ttl_seconds,
                     max_jobs=settings.max_stored_jobs)

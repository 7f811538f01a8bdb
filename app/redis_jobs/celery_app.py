"""The Celery application of the Redis backend: its configuration, its one task, the worker process.

Why Celery: it is the proven default of this ecosystem, and its prefork pool fits CPU-bound numpy
work the way the in-process pool does: long-lived child processes (imports paid once, before the
fork), one job per child at a time, a child that dies replaced.  RQ forks a new process for every
job; arq runs jobs on an asyncio loop, where CPU-bound work needs yet another process pool.

Delivery guarantees, as configured here:

- ``acks_late`` + ``reject_on_worker_lost``: the broker forgets a job only once a worker has
  finished it; a child process killed mid-job (SIGKILL, OOM killer) puts its job back in the
  queue for another child.  The attempt counter in Redis (:mod:`app.redis_jobs.store`) ends the
  loop: the third delivery fails the job ("its worker died 2 times").
- A whole worker machine that dies takes its children with it (Celery sets ``PDEATHSIG``); Redis
  redelivers its jobs ``visibility_timeout`` after they were taken, which is set just above the
  hard time limit so that a job still running is never handed out twice.
- ``prefetch_multiplier = 1`` with the ``fair`` scheduler: a worker holds no more jobs than it has
  idle children, so a long job never blocks short ones queued behind it on a busy worker.
- Soft time limit = ``job_timeout_seconds`` (the job fails ``timed-out``); the hard limit, 10 s
  later, kills a child stuck in native code and :meth:`JobTask.on_failure` records the same problem.
"""

from __future__ import annotations

import logging
import os
import time
from typing import Any

import httpx
import redis
from celery import Celery, Task
from celery.exceptions import Reject, TimeLimitExceeded
from celery.signals import after_setup_logger, after_setup_task_logger, worker_process_init

from app import callbacks
from app.blobs import LocalBlobStore
from app.config import Settings
from app.logs import decorate
from app.redis_jobs.store import JobRecords, input_key, job_from_hash
from app.redis_jobs.worker import execute_job
from app.workers import failures
from app.workers.process import init_engine_process, preload

log = logging.getLogger("meshmark.workers")

TASK_NAME = "meshmark.run_job"
CALLBACK_TASK = "meshmark.job_callback"

#: seconds between the soft and the hard time limit, and between the hard limit and redelivery
HARD_LIMIT_GRACE = 10
VISIBILITY_GRACE = 60


def celery_config(settings: Settings) -> dict[str, Any]:
    hard_limit = settings.job_timeout_seconds + HARD_LIMIT_GRACE
    return {
        "broker_url": settings.redis_url,
        "broker_connection_retry_on_startup": True,
        "broker_transport_options": {"visibility_timeout": int(hard_limit + VISIBILITY_GRACE),
                                     "socket_connect_timeout": 2},
        "broker_pool_limit": 10,
        "task_publish_retry_policy": {"max_retries": 2, "interval_start": 0, "interval_step": 0.2,
                                      "interval_max": 0.5},
        "task_serializer": "json",
        "accept_content": ["json"],
        "task_ignore_result": True,
        "task_acks_late": True,
        "task_reject_on_worker_lost": True,
        "task_acks_on_failure_or_timeout": True,
        "task_default_queue": settings.jobs_queue,
        "task_default_exchange": settings.jobs_queue,
        "task_default_routing_key": settings.jobs_queue,
        "task_soft_time_limit": settings.job_timeout_seconds,
        "task_time_limit": hard_limit,
        "task_send_sent_event": False,
        "worker_prefetch_multiplier": 1,
        "worker_max_tasks_per_child": settings.worker_max_tasks or None,
        "worker_send_task_events": False,
        "worker_cancel_long_running_tasks_on_connection_loss": False,
    }


class _Resources:
    """The Redis client and blob store of one process, made on first use after a fork."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self._pid: int | None = None
        self._records: JobRecords | None = None
        self._blobs: LocalBlobStore | None = None

    def _ensure(self) -> tuple[JobRecords, LocalBlobStore]:
        if self._pid != os.getpid() or self._records is None or self._blobs is None:
            self._pid = os.getpid()
            self._records = JobRecords.from_url(self.settings.redis_url, self.settings.jobs_queue)
            self._blobs = LocalBlobStore(self.settings.blob_dir)
        return self._records, self._blobs

    @property
    def records(self) -> JobRecords:
        return self._ensure()[0]

    @property
    def blobs(self) -> LocalBlobStore:
        return self._ensure()[1]


class JobTask(Task):  # type: ignore[misc]
    resources: _Resources

    def on_failure(self, exc: BaseException, task_id: str, args: Any, kwargs: Any, einfo: Any) -> None:
        """Runs in the worker's main process for a hard time limit (the child was killed)."""
        if isinstance(exc, TimeLimitExceeded):
            timeout = self.resources.settings.job_timeout_seconds
            error = failures.timed_out(timeout)
            self.resources.records.finish(task_id, "failed", error=error.to_dict())
            self.resources.blobs.delete(input_key(task_id))
            _callback_if_wanted(self.app, self.resources.records, task_id)


def make_celery(settings: Settings) -> Celery:
    """A Celery app for these settings, with the job task registered (API and workers alike)."""
    celery = Celery("meshmark", set_as_current=False)
    celery.conf.update(celery_config(settings))
    resources = _Resources(settings)
    base = type("MeshMarkJobTask", (JobTask,), {"resources": resources})

    @celery.task(name=TASK_NAME, bind=True, base=base)  # type: ignore[misc]
    def run_job(self: JobTask, job_id: str) -> str:
        try:
            outcome = execute_job(self.resources.records, self.resources.blobs, job_id,
                                  worker=str(self.request.hostname or ""), pid=os.getpid(),
                                  timeout=settings.job_timeout_seconds, memory_mb=settings.worker_memory_mb)
            if outcome != "skipped":
                _callback_if_wanted(celery, self.resources.records, job_id)
            return outcome
        except (redis.ConnectionError, redis.TimeoutError) as exc:
            # the job's state could not be read or written: back to the queue (the attempt counter
            # still bounds the retries of a job that got as far as starting)
            log.warning("job %s: Redis unreachable (%s); requeued", job_id, exc)
            time.sleep(1)
            raise Reject(str(exc), requeue=True) from None

    secret = settings.callback_secret.get_secret_value().encode() if settings.callback_secret else b""

    @celery.task(name=CALLBACK_TASK, bind=True, base=base, max_retries=len(callbacks.BACKOFF_SECONDS),
                 acks_late=False)  # type: ignore[misc]
    def job_callback(self: JobTask, job_id: str) -> str:
        """One delivery attempt of a finished job's callback; Celery runs the next one after the
        backoff (the job slot is not held while waiting)."""
        fields = self.resources.records.fields(job_id)
        if not fields or not fields.get("callback_url"):
            return "gone"
        job = job_from_hash(job_id, fields)
        body, headers = callbacks.request(job, secret)
        with httpx.Client(follow_redirects=False) as client:
            outcome = callbacks.attempt(client, fields["callback_url"], body, headers)
        if outcome is None:
            if self.request.retries >= len(callbacks.BACKOFF_SECONDS):
                log.error("job %s callback not delivered after %d attempts", job_id, self.request.retries + 1)
                return "undelivered"
            raise self.retry(countdown=callbacks.BACKOFF_SECONDS[self.request.retries])
        log.info("job %s callback %s", job_id, "delivered" if outcome else "refused by the receiver")
        return "delivered" if outcome else "refused"

    return celery


def _callback_if_wanted(celery: Celery, records: JobRecords, job_id: str) -> None:
    """Queue the callback of a job that has just finished, when its creator asked for one."""
    if records.client.hget(records.keys.job(job_id), "callback_url"):
        celery.send_task(CALLBACK_TASK, args=[job_id], queue=celery.conf.task_default_queue)


def run_worker(settings: Settings, *, concurrency: int | None = None, loglevel: str | None = None) -> None:
    """Run a Celery worker for ``settings.jobs_queue`` in this process until it is stopped.

    Set ``OMP_NUM_THREADS=1`` (and the OpenBLAS/MKL equivalents) before numpy is first imported, as
    ``meshmark worker`` does: the child processes are the parallelism.
    """
    preload()
    LocalBlobStore(settings.blob_dir)  # fail now, not on the first job, when the directory is unusable
    celery = make_celery(settings)
    memory_mb = settings.worker_memory_mb
    worker_process_init.connect(lambda **_: init_engine_process(memory_mb), weak=False)

    def one_stream(logger: logging.Logger, **_: Any) -> None:
        """Celery's handlers, with the request id of the job and the service's log format."""
        for handler in logger.handlers:
            decorate(handler, settings.log_format)

    after_setup_logger.connect(one_stream, weak=False)
    after_setup_task_logger.connect(one_stream, weak=False)
    processes = concurrency or settings.worker_concurrency or os.cpu_count() or 1
    celery.worker_main([
        "worker", "--loglevel", (loglevel or settings.log_level).upper(), "--concurrency", str(processes),
        "--queues", settings.jobs_queue, "--hostname", f"meshmark-{os.getpid()}@%h",
        "--pool", "prefork", "--optimization", "fair", "--prefetch-multiplier", "1",
        "--without-gossip", "--without-mingle", "--without-heartbeat",
    ])

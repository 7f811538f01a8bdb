"""One job of the Redis backend, as a worker runs it: input blob in, result blob and state out.

The API writes the job's *input* (the task's options, watermark key included, then the mesh bytes)
to the blob store and sends only the job id through the broker.  A worker:

1. *begins* the job in Redis (atomically: counts the attempt, skips a job that finished, was
   cancelled or deleted, and fails one whose worker already died ``MAX_ATTEMPTS`` times);
2. reads the input blob and runs the same engine call as the in-process pool, writing progress to
   Redis as it goes; a progress write that finds the job ``cancelled`` stops the run there
   (cooperative cancellation: Celery's ``revoke(terminate=True)`` may kill a process that has
   already moved on to another job, so it is not used);
3. writes the result blob, then *finishes* the job (refused when it was cancelled meanwhile), and
   deletes the input blob.

Failures map to the same problems as in the in-process pool (:mod:`app.workers.failures`).
"""

from __future__ import annotations

import json
import logging
from dataclasses import asdict
from typing import Any

import redis

from app.blobs import BlobNotFound, BlobStore
from app.problems import INTERNAL, ProblemError
from app.redis_jobs.store import JobRecords, input_key, result_key
from app.request_id import set_request_id
from app.results import Rendered
from app.tracing import CopyPlan
from app.workers import failures
from app.workers.tasks import Task, ThrottledProgress
from core.formats import Limits
from core.options import Options

log = logging.getLogger("meshmark.workers")


class JobCancelled(Exception):
    """The job was cancelled (or deleted) while it ran: stop, record nothing."""


def encode_input(task: Task) -> bytes:
    """The input blob: the kind, file name, options and limits as one line of JSON, then the mesh
    bytes as they were uploaded."""
    header = {"kind": task.kind, "filename": task.filename, "options": asdict(task.options),
              "limits": asdict(task.limits), "request_id": task.request_id}
    if isinstance(task.plan, CopyPlan):  # the only plan of a job kind
        plan = asdict(task.plan)
        plan["codeword"] = None if task.plan.codeword is None else task.plan.codeword.hex()
        header["copy_plan"] = plan
    return json.dumps(header, separators=(",", ":")).encode() + b"\n" + task.data


def decode_input(blob: bytes) -> Task:
    header, _, data = blob.partition(b"\n")
    fields: dict[str, Any] = json.loads(header)
    plan = fields.get("copy_plan")
    if plan is not None:
        codeword = None if plan["codeword"] is None else bytes.fromhex(plan["codeword"])
        plan = CopyPlan(**{**plan, "codeword": codeword})
    return Task(kind=fields["kind"], data=data, options=Options(**fields["options"]),
                filename=fields["filename"], limits=Limits(**fields["limits"]),
                request_id=fields.get("request_id"), plan=plan)


class _Progress(ThrottledProgress):
    """Writes progress to Redis and stops the run when the job is no longer running."""

    def __init__(self, records: JobRecords, job_id: str) -> None:
        super().__init__()
        self.records, self.job_id = records, job_id

    def emit(self, fraction: float) -> None:
        _unless_running(self.records.progress(self.job_id, fraction))


def _unless_running(state: str | None) -> None:
    """Stop the engine call (:class:`JobCancelled`) when the job's record no longer says
    ``running``: cancelled or deleted meanwhile."""
    if state != "running":
        raise JobCancelled(state)


def _run(records: JobRecords, blobs: BlobStore, job_id: str, *, timeout: float,
         memory_mb: int) -> tuple[str, dict[str, Any] | None, Rendered | None]:
    """The engine call: ``(outcome, problem, result)``, every failure mapped to its problem.  Only
    Redis errors (from the progress reports) get out: the job is then requeued, upload kept."""
    from celery.exceptions import SoftTimeLimitExceeded

    task: Task | None = None
    try:
        try:
            task = decode_input(blobs.get(input_key(job_id)))
            set_request_id(task.request_id)
        except BlobNotFound:
            # cancelled (or deleted) between this worker's start and its read: the cancel removes
            # the upload, so this is the cancel, not a lost blob
            _unless_running(records.state(job_id))
            log.error("job %s: input blob missing from the blob store", job_id)
            missing = ProblemError(INTERNAL, "the job's upload is missing from the blob store")
            return "failed", missing.to_dict(), None
        value = task.run(_Progress(records, job_id))
        return "succeeded", None, task.render(value)
    except JobCancelled:
        log.info("job %s stopped: no longer running", job_id)
        return "cancelled", None, None
    except SoftTimeLimitExceeded:
        log.warning("job %s timed out after %s s", job_id, timeout)
        return "failed", failures.timed_out(timeout).to_dict(), None
    except (redis.ConnectionError, redis.TimeoutError):
        raise
    except Exception as exc:
        failure = failures.capture(exc)
        key = task.key if task is not None else None
        if isinstance(failure, failures.WorkerBug):
            log.error("job %s failed: %s", job_id, failures.details(failure, key))
        problem = failures.problem(failure, memory_mb=memory_mb, timeout=timeout)
        return "failed", problem.to_dict(), None


def execute_job(records: JobRecords, blobs: BlobStore, job_id: str, *, worker: str, pid: int,
                timeout: float, memory_mb: int) -> str:
    """Run one delivered job; returns what happened (for the log and the tests): ``succeeded``,
    ``failed``, ``cancelled``, ``poisoned`` or ``skipped``.

    ``SoftTimeLimitExceeded`` (Celery's soft time limit, raised in this process) becomes a
    ``timed-out`` problem; the hard limit is recorded by the task's ``on_failure``.  The upload is
    deleted once the job's final state is recorded, not before: a run cut short by a Redis error
    is requeued and needs it again.
    """
    begin = records.begin(job_id, worker, pid)
    if begin.action == "poisoned":
        log.error("job %s: its worker died %d times; marked failed", job_id, begin.attempts - 1)
    elif begin.action == "skip":
        log.info("job %s is %s: skipped", job_id, begin.state)
    else:
        outcome, error, result = _run(records, blobs, job_id, timeout=timeout, memory_mb=memory_mb)
        if result is not None:
            blobs.put(result_key(job_id), result.body)
            if not records.finish(job_id, "succeeded", result=result, completed=True):
                blobs.delete(result_key(job_id))  # cancelled or deleted after its last report
                log.info("job %s was cancelled after its run ended: result dropped", job_id)
                outcome = "cancelled"
        elif error is not None:
            records.finish(job_id, "failed", error=error)
        blobs.delete(input_key(job_id))
        return outcome
    blobs.delete(input_key(job_id))
    return "poisoned" if begin.action == "poisoned" else "skipped"

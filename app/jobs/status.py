"""A job's status as the API shows it (``GET /v1/jobs/{id}``) and as a callback receives it."""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Any, Literal

from pydantic import BaseModel, Field

from app.jobs.store import Job, JobState
from app.workers.tasks import JOB_KINDS


class JobStatus(BaseModel):
    id: str
    kind: Literal[JOB_KINDS]  # type: ignore[valid-type]  # the job kinds of the task table
    state: JobState
    progress: float = Field(ge=0, le=1, description="Fraction done, relayed from the worker.")
    created: datetime
    started: datetime | None = None
    finished: datetime | None = None
    expires: datetime | None = Field(None, description="When the job and its result are forgotten "
                                     "(set when it finishes).")
    error: dict[str, Any] | None = Field(None, description="The problem, when the job failed.")
    request_id: str | None = Field(None, description="`X-Request-ID` of the request that created the job "
                                   "(the server's log lines of the job carry it).")

    @classmethod
    def of(cls, job: Job) -> JobStatus:
        def ts(t: float | None) -> datetime | None:
            return None if t is None else datetime.fromtimestamp(t, UTC)

        return cls(id=job.id, kind=job.kind, state=job.state, progress=job.progress,
                   created=datetime.fromtimestamp(job.created, UTC), started=ts(job.started),
                   finished=ts(job.finished), expires=ts(job.expires), error=job.error,
                   request_id=job.request_id)

    def body(self) -> bytes:
        """The JSON document, as sent (a callback's signature covers exactly these bytes)."""
        return self.model_dump_json().encode()

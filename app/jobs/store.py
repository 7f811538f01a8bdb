"""Where jobs and their results live between requests: the :class:`Job` record and the
:class:`JobStore` interface the routes and the runners use.

Implementations: :class:`app.memory_jobs.InMemoryJobStore` (this process; jobs vanish on restart
and are not shared between server processes) and :class:`app.redis_jobs.store.RedisJobStore`.
"""

from __future__ import annotations

import secrets
import time
from dataclasses import dataclass, field
from typing import Any, Literal, Protocol

from app.results import Rendered

JobState = Literal["queued", "running", "succeeded", "failed", "cancelled"]
#: every state, in the order a job goes through them
STATES: tuple[JobState, ...] = ("queued", "running", "succeeded", "failed", "cancelled")
FINISHED: frozenset[str] = frozenset({"succeeded", "failed", "cancelled"})


@dataclass(frozen=True)
class Job:
    """A job: ``kind`` is a job kind of :data:`app.workers.tasks.TASKS`.  Times are Unix
    seconds; ``expires`` is set when the job finishes."""

    id: str
    kind: str
    state: JobState = "queued"
    progress: float = 0.0
    created: float = field(default_factory=time.time)
    started: float | None = None
    finished: float | None = None
    expires: float | None = None
    error: dict[str, Any] | None = None
    request_id: str | None = None
    #: where the final status is POSTed (see :mod:`app.callbacks`)
    callback_url: str | None = None
    #: who may see the job: :func:`app.deps.caller_id` of the API key that created it (None
    #: without API keys); any other caller is answered 404, as for a job that does not exist
    owner: str | None = None
    result: Rendered | None = field(default=None, repr=False)

    @property
    def done(self) -> bool:
        return self.state in FINISHED


def new_job_id() -> str:
    """A job id: 128 random bits in hex (a UUID4 has 122)."""
    return secrets.token_hex(16)


class JobStore(Protocol):
    async def add(self, job: Job) -> None: ...

    async def get(self, job_id: str) -> Job | None:
        """The job, or None when unknown or expired."""

    async def update(self, job_id: str, **changes: Any) -> Job | None:
        """Apply ``changes`` to an existing job; returns the new job (None if it is gone)."""

    async def delete(self, job_id: str) -> None: ...

    async def count(self) -> dict[str, int]:
        """Live (unexpired) jobs by state."""

    async def result(self, job: Job) -> Rendered | None:
        """The answer of a succeeded job (None otherwise, or when it is gone)."""

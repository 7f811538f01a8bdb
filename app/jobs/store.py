"""Where jobs and their results live between requests.

:class:`JobStore` is the interface the routes and the runner use; :class:`InMemoryJobStore` keeps
everything in this process (jobs vanish on restart and are not shared between server processes).
:class:`app.jobs.redis_store.RedisJobStore` implements the same coroutines on Redis.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Any, Literal, Protocol

JobKind = Literal["embed", "detect"]
JobState = Literal["queued", "running", "succeeded", "failed", "cancelled"]
FINISHED: frozenset[str] = frozenset({"succeeded", "failed", "cancelled"})


@dataclass(frozen=True)
class JobResult:
    """A finished job's response, ready to send: body, media type, extra headers."""

    body: bytes
    media_type: str
    headers: dict[str, str] = field(default_factory=dict)


@dataclass(frozen=True)
class Job:
    """Times are Unix seconds; ``expires`` is set when the job finishes."""

    id: str
    kind: JobKind
    state: JobState = "queued"
    progress: float = 0.0
    created: float = field(default_factory=time.time)
    started: float | None = None
    finished: float | None = None
    expires: float | None = None
    error: dict[str, Any] | None = None
    result: JobResult | None = field(default=None, repr=False)

    @property
    def done(self) -> bool:
        return self.state in FINISHED


class JobStore(Protocol):
    async def add(self, job: Job) -> None: ...

    async def get(self, job_id: str) -> Job | None:
        """The job, or None when unknown or expired."""

    async def update(self, job_id: str, **changes: Any) -> Job | None:
        """Apply ``changes`` to an existing job; returns the new job (None if it is gone)."""

    async def delete(self, job_id: str) -> None: ...

    async def count(self) -> dict[str, int]:
        """Live (unexpired) jobs by state."""

    async def result(self, job: Job) -> JobResult | None:
        """The response of a succeeded job (None otherwise, or when it is gone)."""


class InMemoryJobStore:
    """A dict of immutable :class:`Job` values; expired jobs are dropped when touched or counted."""

    def __init__(self) -> None:
        self._jobs: dict[str, Job] = {}

    def _purge(self) -> None:
        now = time.time()
        for job_id in [j.id for j in self._jobs.values() if j.expires is not None and j.expires <= now]:
            del self._jobs[job_id]

    async def add(self, job: Job) -> None:
        self._jobs[job.id] = job

    async def get(self, job_id: str) -> Job | None:
        job = self._jobs.get(job_id)
        if job is not None and job.expires is not None and job.expires <= time.time():
            del self._jobs[job_id]
            return None
        return job

    async def update(self, job_id: str, **changes: Any) -> Job | None:
        job = await self.get(job_id)
        if job is None:
            return None
        job = self._jobs[job_id] = replace(job, **changes)
        return job

    async def delete(self, job_id: str) -> None:
        self._jobs.pop(job_id, None)

    async def result(self, job: Job) -> JobResult | None:
        return job.result

    async def count(self) -> dict[str, int]:
        self._purge()
        counts = dict.fromkeys(("queued", "running", "succeeded", "failed", "cancelled"), 0)
        for job in self._jobs.values():
            counts[job.state] += 1
        return counts

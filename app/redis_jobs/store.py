"""Jobs in Redis: the metadata of the distributed backend, shared by the API and the workers.

Redis holds what the status route shows (state, progress, timestamps, the problem of a failed job)
and a few counters; the bytes (upload and result) are in a :class:`~app.blobs.BlobStore`.
Every key starts with a *namespace*, the Celery queue's name, so that two deployments can share one
Redis database:

==================================  ==========================================================
``{ns}:job:{id}``                   hash: ``kind state progress created started finished
                                    expires ttl error result attempts completions worker pid``
``{ns}:jobs:{state}``               set of the ids in that state (``count()`` without a scan)
``{ns}:expiry``                     sorted set, id -> ``expires``: what to purge, blobs included
==================================  ==========================================================

State changes are Lua scripts, so a change is atomic and conditional: a job is only ever moved
*out of* ``queued`` or ``running``; a cancelled job cannot be revived by a worker that finishes it
later, and a redelivered job that already finished is skipped.  ``attempts`` counts deliveries to a
worker (a delivery beyond ``MAX_ATTEMPTS`` fails the job instead of running it: no poison loop) and
``completions`` counts runs that got to the end (exactly one for every succeeded job).

:class:`RedisJobStore` is the API's asynchronous :class:`~app.jobs.JobStore`;
:class:`JobRecords` is the workers' synchronous side.
"""

from __future__ import annotations

import asyncio
import json
import time
from collections.abc import AsyncIterator, Mapping
from contextlib import asynccontextmanager
from dataclasses import dataclass
from typing import Any

import redis
import redis.asyncio as aioredis
from redis.backoff import ExponentialBackoff
from redis.retry import Retry

from app.blobs import BlobStore
from app.jobs import STATES, Job
from app.problems import NOT_READY, ProblemError
from app.results import Rendered
from app.workers.failures import poisoned

#: deliveries of one job to a worker; the next one fails it ("its worker died N times")
MAX_ATTEMPTS = 2

#: a finished job's hash outlives ``expires`` by this much (seconds), so that whoever purges it
#: can still read it; the purge deletes it at ``expires``
EXPIRY_GRACE = 60

# Shared by the scripts: move the job in KEYS[1] (id ARGV[1]) to a final state.
# KEYS: job, expiry, then the sets of STATES in order.
_LUA_FINISH = """
local function finish(id, state, now, error, result)
  local current = redis.call('HGET', KEYS[1], 'state')
  local sets = {queued=KEYS[3], running=KEYS[4], succeeded=KEYS[5], failed=KEYS[6], cancelled=KEYS[7]}
  local expires = now + tonumber(redis.call('HGET', KEYS[1], 'ttl'))
  redis.call('HSET', KEYS[1], 'state', state, 'finished', now, 'expires', expires)
  if state == 'succeeded' then redis.call('HSET', KEYS[1], 'progress', '1') end
  if error ~= '' then redis.call('HSET', KEYS[1], 'error', error) end
  if result ~= '' then redis.call('HSET', KEYS[1], 'result', result) end
  redis.call('SREM', sets[current], id)
  redis.call('SADD', sets[state], id)
  redis.call('ZADD', KEYS[2], expires, id)
  redis.call('PEXPIREAT', KEYS[1], math.floor((expires + tonumber(ARGV[#ARGV])) * 1000))
end
"""

# ARGV: id, state, now, error json or '', result json or '', count a completion ('1'/'0'), grace
# -> nil (no such job), 'ok' (moved), or the job's state when it had already finished
_FINISH = _LUA_FINISH + """
local current = redis.call('HGET', KEYS[1], 'state')
if not current then return false end
if ARGV[6] == '1' then redis.call('HINCRBY', KEYS[1], 'completions', 1) end
if current ~= 'queued' and current ~= 'running' then return current end
finish(ARGV[1], ARGV[2], tonumber(ARGV[3]), ARGV[4], ARGV[5])
return 'ok'
"""

# ARGV: id, now, worker, pid, max attempts, error json of a poisoned job, grace
# -> {'run', attempts} | {'failed', attempts} (poisoned) | {state, 0} (skip) | {'gone', 0}
_BEGIN = _LUA_FINISH + """
local current = redis.call('HGET', KEYS[1], 'state')
if not current then return {'gone', 0} end
if current ~= 'queued' and current ~= 'running' then return {current, 0} end
local attempts = redis.call('HINCRBY', KEYS[1], 'attempts', 1)
if attempts > tonumber(ARGV[5]) then
  finish(ARGV[1], 'failed', tonumber(ARGV[2]), ARGV[6], '')
  return {'failed', attempts}
end
redis.call('HSET', KEYS[1], 'state', 'running', 'started', ARGV[2], 'worker', ARGV[3], 'pid', ARGV[4])
redis.call('SREM', KEYS[3], ARGV[1])
redis.call('SADD', KEYS[4], ARGV[1])
return {'run', attempts}
"""

# KEYS: job; ARGV: fraction -> the job's state (nil when gone); progress only ever grows
_PROGRESS = """
local v = redis.call('HMGET', KEYS[1], 'state', 'progress')
if not v[1] then return false end
if v[1] == 'running' and tonumber(ARGV[1]) > tonumber(v[2] or '0') then
  redis.call('HSET', KEYS[1], 'progress', ARGV[1])
end
return v[1]
"""


def input_key(job_id: str) -> str:
    return f"{job_id}.input"


def result_key(job_id: str) -> str:
    return f"{job_id}.result"


@dataclass(frozen=True)
class Keys:
    """The Redis keys of one namespace."""

    namespace: str

    def job(self, job_id: str) -> str:
        return f"{self.namespace}:job:{job_id}"

    def state(self, state: str) -> str:
        return f"{self.namespace}:jobs:{state}"

    @property
    def expiry(self) -> str:
        return f"{self.namespace}:expiry"

    def script_keys(self, job_id: str) -> list[str]:
        return [self.job(job_id), self.expiry, *(self.state(s) for s in STATES)]


def _float(value: str | None) -> float | None:
    return float(value) if value else None


def job_from_hash(job_id: str, fields: Mapping[str, str]) -> Job:
    return Job(id=job_id, kind=fields["kind"], state=fields["state"],  # type: ignore[arg-type]
               progress=float(fields.get("progress") or 0.0), created=float(fields["created"]),
               started=_float(fields.get("started")), finished=_float(fields.get("finished")),
               expires=_float(fields.get("expires")),
               error=json.loads(fields["error"]) if fields.get("error") else None,
               request_id=fields.get("request_id") or None, callback_url=fields.get("callback_url") or None,
               owner=fields.get("owner") or None)


def client_options() -> dict[str, Any]:
    """Short timeouts and few retries: a dead Redis must turn into a 503 quickly, not a hang."""
    return {"decode_responses": True, "socket_connect_timeout": 2, "socket_timeout": 10,
            "health_check_interval": 30,
            "retry": Retry(ExponentialBackoff(cap=0.5, base=0.05), retries=2)}


def unreachable() -> ProblemError:
    return ProblemError(NOT_READY, "the job queue (Redis) is unreachable; retry later",
                        headers={"Retry-After": "5"})


class RedisJobStore:
    """The API's view of the jobs in Redis (a :class:`~app.jobs.JobStore`).

    ``get`` and ``count`` drop expired jobs with their blobs, as :class:`InMemoryJobStore` does.
    A Redis that cannot be reached turns into a ``not-ready`` problem (503 with ``Retry-After``).
    """

    def __init__(self, client: aioredis.Redis, blobs: BlobStore, namespace: str, *, ttl: float) -> None:
        self.client: Any = client  # Any: redis-py's types do not follow decode_responses=True
        self.blobs, self.keys, self.ttl = blobs, Keys(namespace), ttl
        self._finish = client.register_script(_FINISH)

    @classmethod
    def from_url(cls, url: str, blobs: BlobStore, namespace: str, *, ttl: float) -> RedisJobStore:
        return cls(aioredis.Redis.from_url(url, **client_options()), blobs, namespace, ttl=ttl)

    @staticmethod
    @asynccontextmanager
    async def _redis() -> AsyncIterator[None]:
        try:
            yield
        except (redis.ConnectionError, redis.TimeoutError):
            raise unreachable() from None

    async def ping(self, timeout: float = 2.0) -> bool:
        try:
            return bool(await asyncio.wait_for(self.client.ping(), timeout))
        except (redis.RedisError, OSError, TimeoutError):
            return False

    async def add(self, job: Job) -> None:
        fields = {"kind": job.kind, "state": job.state, "progress": job.progress, "created": job.created,
                  "ttl": self.ttl, "attempts": 0, "completions": 0, "request_id": job.request_id or "",
                  "callback_url": job.callback_url or "", "owner": job.owner or ""}
        async with self._redis():
            await (self.client.pipeline(transaction=True)
                   .hset(self.keys.job(job.id), mapping=fields)
                   .sadd(self.keys.state(job.state), job.id)
                   .execute())

    async def get(self, job_id: str) -> Job | None:
        async with self._redis():
            fields = await self.client.hgetall(self.keys.job(job_id))
        if not fields or "state" not in fields:
            return None
        job = job_from_hash(job_id, fields)
        if job.expires is not None and job.expires <= time.time():
            await self.delete(job_id)
            return None
        return job

    async def fields(self, job_id: str) -> dict[str, str]:
        """Everything Redis holds about a job, counters included (for tests and operators)."""
        async with self._redis():
            fields: dict[str, str] = await self.client.hgetall(self.keys.job(job_id))
        return fields

    async def update(self, job_id: str, **changes: Any) -> Job | None:
        """Unconditional field changes, as :class:`~app.memory_jobs.LocalJobRunner` makes them (the
        Celery runner and the workers move jobs with the conditional scripts instead)."""
        job = await self.get(job_id)
        if job is None:
            return None
        result: Rendered | None = changes.pop("result", None)
        values = {k: json.dumps(v) if k == "error" else ("" if v is None else v) for k, v in changes.items()}
        if result is not None:
            await asyncio.to_thread(self.blobs.put, result_key(job_id), result.body)
            values["result"] = json.dumps([result.media_type, result.headers])
        async with self._redis():
            pipe = self.client.pipeline(transaction=True).hset(self.keys.job(job_id), mapping=values)
            if changes.get("state", job.state) != job.state:
                pipe.smove(self.keys.state(job.state), self.keys.state(changes["state"]), job_id)
            if changes.get("expires") is not None:
                pipe.zadd(self.keys.expiry, {job_id: changes["expires"]})
            await pipe.execute()
        return await self.get(job_id)

    async def finish(self, job_id: str, state: str, *, error: dict[str, Any] | None = None) -> bool:
        """Move a queued or running job to ``state``; False when it had finished or is gone."""
        args: list[str | float] = [job_id, state, time.time(), json.dumps(error) if error else "", "", "0",
                                   EXPIRY_GRACE]
        async with self._redis():
            outcome = await self._finish(keys=self.keys.script_keys(job_id), args=args)
        return bool(outcome == "ok")

    async def result(self, job: Job) -> Rendered | None:
        if job.state != "succeeded":
            return None
        async with self._redis():
            meta = await self.client.hget(self.keys.job(job.id), "result")
        if not meta:
            return None
        try:
            body = await asyncio.to_thread(self.blobs.get, result_key(job.id))
        except KeyError:
            return None
        media_type, headers = json.loads(meta)
        return Rendered(body, media_type, headers)

    async def delete(self, job_id: str) -> None:
        async with self._redis():
            pipe = self.client.pipeline(transaction=True).delete(self.keys.job(job_id))
            for state in STATES:
                pipe.srem(self.keys.state(state), job_id)
            await pipe.zrem(self.keys.expiry, job_id).execute()
        await asyncio.to_thread(self._delete_blobs, job_id)

    def _delete_blobs(self, job_id: str) -> None:
        self.blobs.delete(input_key(job_id))
        self.blobs.delete(result_key(job_id))

    async def purge(self) -> int:
        """Drop the jobs whose ``expires`` has passed (their hashes, set entries and blobs)."""
        async with self._redis():
            expired = await self.client.zrangebyscore(self.keys.expiry, "-inf", time.time())
        for job_id in expired:
            await self.delete(job_id)
        return len(expired)

    async def count(self) -> dict[str, int]:
        await self.purge()
        async with self._redis():
            pipe = self.client.pipeline(transaction=False)
            for state in STATES:
                pipe.scard(self.keys.state(state))
            counts = await pipe.execute()
        return dict(zip(STATES, counts, strict=True))

    async def close(self) -> None:
        await self.client.aclose()


@dataclass(frozen=True)
class Begin:
    """What a worker should do with a delivered job: ``action`` is ``run``, ``skip`` (the job
    finished, was cancelled or is gone) or ``poisoned`` (failed now: too many attempts)."""

    action: str
    attempts: int
    state: str


class JobRecords:
    """The workers' side: start, report progress, finish (synchronous; one per process)."""

    def __init__(self, client: redis.Redis, namespace: str) -> None:
        self.client: Any = client
        self.keys = Keys(namespace)
        self._begin = client.register_script(_BEGIN)
        self._finish = client.register_script(_FINISH)
        self._progress = client.register_script(_PROGRESS)

    @classmethod
    def from_url(cls, url: str, namespace: str) -> JobRecords:
        return cls(redis.Redis.from_url(url, **client_options()), namespace)

    def begin(self, job_id: str, worker: str, pid: int, max_attempts: int = MAX_ATTEMPTS) -> Begin:
        error = poisoned(max_attempts).to_dict()
        state, attempts = self._begin(keys=self.keys.script_keys(job_id),
                                      args=[job_id, time.time(), worker, pid, max_attempts,
                                            json.dumps(error), EXPIRY_GRACE])
        if state == "run":
            return Begin("run", int(attempts), "running")
        if state == "failed" and int(attempts) > 0:
            return Begin("poisoned", int(attempts), "failed")
        return Begin("skip", int(attempts), state)

    def progress(self, job_id: str, fraction: float) -> str | None:
        """Record progress; returns the job's state (``cancelled`` tells the worker to stop)."""
        state: str | None = self._progress(keys=[self.keys.job(job_id)], args=[fraction])
        return state

    def finish(self, job_id: str, state: str, *, error: dict[str, Any] | None = None,
               result: Rendered | None = None, completed: bool = False) -> bool:
        """Move the job to its final state unless it already has one; ``completed`` counts a run
        that got to the end (whether or not the job still wanted its result)."""
        meta = json.dumps([result.media_type, result.headers]) if result is not None else ""
        args: list[str | float] = [job_id, state, time.time(), json.dumps(error) if error else "", meta,
                                   "1" if completed else "0", EXPIRY_GRACE]
        return bool(self._finish(keys=self.keys.script_keys(job_id), args=args) == "ok")

    def fields(self, job_id: str) -> dict[str, str]:
        fields: dict[str, str] = self.client.hgetall(self.keys.job(job_id))
        return fields

    def state(self, job_id: str) -> str | None:
        state: str | None = self.client.hget(self.keys.job(job_id), "state")
        return state

    def close(self) -> None:
        self.client.close()

"""The worker pool: pebble processes behind admission control, with failures mapped to problems.

Why pebble: a worker that crashes, is killed or runs out of time fails only its own task and is
replaced (a stdlib ``ProcessPoolExecutor`` breaks every pending task when one worker dies).

All bookkeeping happens on the event loop thread; one reader thread turns worker messages into
``loop.call_soon_threadsafe`` calls.  The workers report over one shared pipe: ``("hello", None,
pid)`` when one starts, ``("start", task_id, pid)`` when it takes a task, ``("progress", task_id,
fraction)`` while it works.  Each message is a single small write, so writers need no lock and a
killed worker cannot leave the pipe half-written or locked.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import multiprocessing
import os
import threading
import time
import uuid
from collections import Counter
from collections.abc import Callable
from concurrent.futures import Future
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from typing import Any

import psutil
from pebble import ProcessExpired, ProcessPool

from app.problems import WORKER_FAILED, ProblemError
from app.request_id import set_request_id
from app.workers import failures
from app.workers.process import PRELOAD, init_engine_process, one_blas_thread
from app.workers.tasks import Task, ThrottledProgress

log = logging.getLogger("meshmark.workers")

ProgressCallback = Callable[[float], None]


@dataclass
class _Entry:
    task_id: str
    kind: str
    key: str | None
    future: Future[Any]
    on_progress: ProgressCallback | None
    submitted: float = field(default_factory=time.monotonic)
    started: float | None = None
    pid: int | None = None


def _mp_context() -> Any:
    if "forkserver" in multiprocessing.get_all_start_methods():
        ctx = multiprocessing.get_context("forkserver")
        ctx.set_forkserver_preload([*PRELOAD, __name__])  # and this module: the workers' functions
        return ctx
    return multiprocessing.get_context("spawn")


def _alive(pid: int) -> bool:
    """Running, not a zombie waiting for pebble to reap it."""
    try:
        return bool(psutil.Process(pid).status() != psutil.STATUS_ZOMBIE)
    except psutil.NoSuchProcess:
        return False


class WorkerPool:
    """Runs :class:`~app.workers.tasks.Task` s in worker processes.

    Parameters
    ----------
    workers : int
        Worker processes.
    slots : int
        Tasks admitted at once, running + waiting; one more gets a ``busy`` problem (429).
    timeout : float
        Seconds a task may run in a worker before the worker is killed (``timed-out``, 503).
    memory_mb : int
        RLIMIT_AS of each worker (0 = none).
    max_tasks : int
        Tasks before a worker is replaced by a fresh one (0 = never).
    """

    def __init__(self, *, workers: int, slots: int, timeout: float, memory_mb: int, max_tasks: int) -> None:
        self.workers, self.slots, self.timeout = workers, slots, timeout
        self.memory_mb, self.max_tasks = memory_mb, max_tasks
        self.restarts: Counter[str] = Counter()
        self.outcomes: Counter[tuple[str, str]] = Counter()
        self._entries: dict[str, _Entry] = {}
        self._pids: set[int] = set()
        self._mean_seconds = 1.0
        self._pool: ProcessPool | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._reader: Connection | None = None
        self._writer: Connection | None = None
        self._thread: threading.Thread | None = None
        self._watchdog: asyncio.Task[None] | None = None
        self._ctx = _mp_context()

    # -- life cycle ---------------------------------------------------------------------------

    async def start(self, ready_timeout: float = 30.0) -> None:
        """Start the workers and wait (up to ``ready_timeout``) until each has said hello."""
        self._loop = asyncio.get_running_loop()
        one_blas_thread()
        self._reader, self._writer = self._ctx.Pipe(duplex=False)
        self._thread = threading.Thread(target=self._read_messages, name="meshmark-worker-messages",
                                        daemon=True)
        self._thread.start()
        self._pool = await asyncio.to_thread(self._new_pool)
        deadline = time.monotonic() + ready_timeout
        while len(self.live_workers()) < self.workers and time.monotonic() < deadline:
            await asyncio.sleep(0.02)
        if len(self.live_workers()) < self.workers:
            log.warning("only %d of %d workers started", len(self.live_workers()), self.workers)
        self._watchdog = asyncio.ensure_future(self._watch())

    async def _watch(self, period: float = 1.0) -> None:
        """Replace a broken pebble pool even when no request comes (readiness depends on it)."""
        while True:
            await asyncio.sleep(period)
            pool = self._pool
            try:
                if pool is not None and not pool.active:
                    self._ensure_pool()
            except Exception:  # keep watching: the next round may manage
                log.exception("could not replace the worker pool")

    async def stop(self) -> None:
        if self._watchdog is not None:
            self._watchdog.cancel()
        for entry in list(self._entries.values()):
            entry.future.cancel()
        pool, self._pool = self._pool, None
        await asyncio.to_thread(self._shutdown, pool)

    def _new_pool(self) -> ProcessPool:
        pool = ProcessPool(max_workers=self.workers, max_tasks=self.max_tasks, initializer=_init_worker,
                           initargs=(self._writer, self.memory_mb), context=self._ctx)
        pool.active  # noqa: B018 -- starts the worker processes now rather than on first use
        return pool

    @staticmethod
    def _stop_pebble(pool: ProcessPool) -> None:
        pool.stop()
        with contextlib.suppress(Exception):
            pool.join(timeout=10)

    def _shutdown(self, pool: ProcessPool | None) -> None:
        if pool is not None:
            self._stop_pebble(pool)
        if self._writer is not None:
            self._writer.send(None)
        if self._thread is not None:
            self._thread.join(timeout=5)
        for conn in (self._reader, self._writer):
            if conn is not None:
                conn.close()

    def _ensure_pool(self) -> ProcessPool:
        """The running pebble pool; a pool pebble gave up on (all workers died while idle) is
        replaced on the spot."""
        if self._pool is None:
            raise ProblemError(WORKER_FAILED, "the worker pool is not running")
        if not self._pool.active:
            log.error("worker pool broken; starting a new one")
            self.restarts["pool-broken"] += 1
            broken, self._pool = self._pool, self._new_pool()
            threading.Thread(target=self._stop_pebble, args=(broken,), daemon=True).start()
        return self._pool

    # -- messages from workers ----------------------------------------------------------------

    def _read_messages(self) -> None:
        assert self._reader is not None and self._loop is not None
        while True:
            try:
                message = self._reader.recv()
            except (EOFError, OSError):
                return
            if message is None:
                return
            try:
                self._loop.call_soon_threadsafe(self._on_message, *message)
            except RuntimeError:  # loop closed
                return

    def _on_message(self, kind: str, task_id: str | None, value: float) -> None:
        if kind == "hello":
            self._pids.add(int(value))
            return
        entry = self._entries.get(task_id or "")
        if entry is None:
            return
        if kind == "start":
            entry.pid, entry.started = int(value), time.monotonic()
            value = 0.0
        if entry.on_progress is not None:
            entry.on_progress(float(value))

    # -- tasks --------------------------------------------------------------------------------

    @property
    def pending(self) -> int:
        """Tasks admitted and not finished (running + waiting)."""
        return len(self._entries)

    @property
    def running(self) -> int:
        return sum(1 for e in tuple(self._entries.values()) if e.started is not None)

    def live_workers(self) -> list[int]:
        pids = tuple(self._pids)  # one C-level copy: the pipe reader thread adds to the set
        alive = {pid for pid in pids if _alive(pid)}
        self._pids.difference_update(set(pids) - alive)
        return sorted(alive)

    def running_tasks(self) -> dict[str, int]:
        """Task id -> pid of the worker running it."""
        entries = tuple(self._entries.values())  # one C-level copy: safe to call from another thread
        return {e.task_id: e.pid for e in entries if e.pid is not None}

    def retry_after(self) -> int:
        """Seconds until a slot is likely free: the tasks admitted, at the mean time of a task,
        divided among the workers.  The mean is that of the tasks finished lately, or of those
        running now when they have already run longer (hostile uploads that each held a worker
        for 85 s were answered ``Retry-After: 2``)."""
        now = time.monotonic()
        running = [now - e.started for e in self._entries.values() if e.started is not None]
        mean = max(self._mean_seconds, sum(running) / len(running)) if running else self._mean_seconds
        return max(1, min(max(60, math.ceil(self.timeout)), math.ceil(mean * self.pending / self.workers)))

    def refusal(self) -> ProblemError | None:
        """The ``busy`` problem (429 with ``Retry-After``) when every slot is taken, else None."""
        return failures.busy(self.slots, self.retry_after()) if self.pending >= self.slots else None

    def submit(self, task: Task, *, task_id: str | None = None,
               on_progress: ProgressCallback | None = None) -> asyncio.Task[Any]:
        """Admit ``task`` and return an asyncio task with its result.

        Raises a ``busy`` :class:`ProblemError` (429 with ``Retry-After``) when all slots are taken.
        The returned task raises :class:`ProblemError` for every failure; cancelling it cancels
        the work (killing the worker if it had started).
        """
        refusal = self.refusal()
        if refusal is not None:
            raise refusal
        task_id = task_id or uuid.uuid4().hex
        try:
            future = self._ensure_pool().schedule(_execute, args=(task_id, task), timeout=self.timeout)
        except RuntimeError as exc:  # pebble could not start workers
            log.error("cannot schedule %s task: %s", task.kind, exc)
            raise ProblemError(WORKER_FAILED, "no worker process could be started; retry later",
                               headers={"Retry-After": "5"}) from None
        entry = _Entry(task_id, task.kind, task.key, future, on_progress)
        self._entries[task_id] = entry
        waiter = asyncio.ensure_future(self._wait(entry))
        waiter.add_done_callback(lambda _: self._finish(entry))
        return waiter

    async def run(self, task: Task) -> Any:
        return await self.submit(task)

    def cancel(self, task_id: str) -> bool:
        entry = self._entries.get(task_id)
        return entry is not None and entry.future.cancel()

    def _finish(self, entry: _Entry) -> None:
        if self._entries.get(entry.task_id) is entry:
            del self._entries[entry.task_id]
        if not entry.future.done():
            entry.future.cancel()
        if entry.future.cancelled() and entry.started is not None:
            self.restarts["cancelled"] += 1  # pebble stops a worker whose task is cancelled

    async def _wait(self, entry: _Entry) -> Any:
        try:
            result = await asyncio.wrap_future(entry.future)
        except asyncio.CancelledError:
            self.outcomes[(entry.kind, "cancelled")] += 1
            raise
        except Exception as exc:
            self._timed(entry)  # failures (time-outs above all) take worker time too
            problem = self._problem(entry, exc)
            self.outcomes[(entry.kind, problem.problem.slug)] += 1
            raise problem from None
        self._timed(entry)
        self.outcomes[(entry.kind, "ok")] += 1
        return result

    def _timed(self, entry: _Entry) -> None:
        if entry.started is not None:
            self._mean_seconds = 0.8 * self._mean_seconds + 0.2 * (time.monotonic() - entry.started)

    def _problem(self, entry: _Entry, exc: Exception) -> ProblemError:
        if isinstance(exc, ProcessExpired):
            self.restarts["crashed"] += 1
            log.warning("worker %s died (exit code %s) during %s task %s; replaced",
                        exc.pid, exc.exitcode, entry.kind, entry.task_id)
        elif isinstance(exc, TimeoutError):
            self.restarts["timeout"] += 1
            log.warning("%s task %s timed out after %s s; worker replaced", entry.kind, entry.task_id,
                        self.timeout)
        elif isinstance(exc, BrokenProcessPool | RuntimeError):
            log.error("worker pool failure during %s task %s: %s", entry.kind, entry.task_id, exc)
        elif not isinstance(exc, failures.EngineFailure | failures.WorkerOutOfMemory):
            log.error("%s task %s failed: %s", entry.kind, entry.task_id, failures.details(exc, entry.key))
        return failures.problem(exc, memory_mb=self.memory_mb, timeout=self.timeout)


# -- in the worker process ------------------------------------------------------------------------

_channel: Connection | None = None


def _init_worker(channel: Connection, memory_mb: int) -> None:
    """Pool initializer: the engine process set-up, then keep the pipe and say hello."""
    global _channel
    init_engine_process(memory_mb)
    _channel = channel
    _send("hello", None, os.getpid())


def _send(kind: str, task_id: str | None, value: float | int) -> None:
    if _channel is not None:
        _channel.send((kind, task_id, value))


class _Progress(ThrottledProgress):
    """Forwards progress to the parent over the workers' pipe."""

    def __init__(self, task_id: str) -> None:
        super().__init__()
        self.task_id = task_id

    def emit(self, fraction: float) -> None:
        _send("progress", self.task_id, fraction)


def _execute(task_id: str, task: Task) -> Any:
    """Run one task in the worker; the only function the pool schedules."""
    set_request_id(task.request_id)
    _send("start", task_id, os.getpid())
    try:
        return task.run(_Progress(task_id))
    except Exception as exc:
        raise failures.capture(exc) from None

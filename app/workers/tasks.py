"""What runs inside a worker process.

Tasks are small frozen dataclasses holding the uploaded bytes and the options (never trimesh or
numpy objects), so that sending one to a worker is one pickle of bytes.  Engine exceptions are
carried back as :class:`EngineFailure` (class + message), because some of them do not survive a
pickle round trip on their own.

The worker reports to the parent over one shared pipe: ``("hello", None, pid)`` when it starts,
``("start", task_id, pid)`` when it takes a task, ``("progress", task_id, fraction)`` while it
works.  Each message is a single small write, so writers need no lock and a killed worker cannot
leave the pipe half-written or locked.
"""

from __future__ import annotations

import os
import resource
import time
import traceback
from dataclasses import dataclass
from multiprocessing.connection import Connection
from typing import Any

from core import api
from core.allocator import tune_malloc
from core.errors import MeshMarkError
from core.formats import DEFAULT_LIMITS, Limits

_channel: Connection | None = None


class EngineFailure(Exception):
    """The engine rejected the input: ``exc_type`` is the :mod:`core.errors` class."""

    def __init__(self, exc_type: type[BaseException], message: str, extensions: dict[str, Any]) -> None:
        super().__init__(exc_type, message, extensions)
        self.exc_type, self.message, self.extensions = exc_type, message, extensions


class WorkerOutOfMemory(Exception):
    """The task hit the worker's address-space limit (RLIMIT_AS)."""


class WorkerBug(Exception):
    """Any other exception in the worker; ``details`` is the traceback text (for the log only)."""

    def __init__(self, summary: str, details: str) -> None:
        super().__init__(summary, details)
        self.summary, self.details = summary, details


@dataclass(frozen=True)
class EmbedTask:
    data: bytes
    options: api.Options
    filename: str | None = None
    limits: Limits = DEFAULT_LIMITS

    kind = "embed"

    @property
    def key(self) -> str | None:
        return _text_key(self.options)

    def run(self, progress: api.Progress) -> api.EmbeddedFile:
        return api.embed(self.data, self.options, filename=self.filename, limits=self.limits,
                         progress=progress)


@dataclass(frozen=True)
class DetectTask:
    data: bytes
    options: api.Options
    filename: str | None = None
    limits: Limits = DEFAULT_LIMITS

    kind = "detect"

    @property
    def key(self) -> str | None:
        return _text_key(self.options)

    def run(self, progress: api.Progress) -> api.DetectResult:
        return api.detect(self.data, self.options, filename=self.filename, limits=self.limits,
                          progress=progress)


@dataclass(frozen=True)
class CapacityTask:
    data: bytes
    options: api.Options
    filename: str | None = None
    limits: Limits = DEFAULT_LIMITS

    kind = "capacity"
    key = None

    def run(self, progress: api.Progress) -> api.CapacityReport:
        return api.capacity(self.data, self.options, filename=self.filename, limits=self.limits)


def _text_key(options: api.Options) -> str | None:
    return options.key if isinstance(options.key, str) else None


Task = EmbedTask | DetectTask | CapacityTask


#: CPU priority of the worker processes relative to the server process: when the workers saturate
#: the CPU, the HTTP process still gets it first (429s, health checks and uploads stay fast)
WORKER_NICENESS = 10

def init_worker(channel: Connection, memory_mb: int) -> None:
    """Pool initializer: lower the CPU priority, cap the address space, keep the pipe, say hello."""
    global _channel
    try:
        os.nice(WORKER_NICENESS)
    except OSError:  # not allowed here: run at the server's priority
        pass
    tune_malloc()
    if memory_mb > 0:
        limit = memory_mb * 1024 * 1024
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    _channel = channel
    _send("hello", None, os.getpid())


def _send(kind: str, task_id: str | None, value: float | int) -> None:
    if _channel is not None:
        _channel.send((kind, task_id, value))


class ThrottledProgress:
    """Monotonic progress, passed on at most every 50 ms unless it moved by 1 % (1.0 always);
    subclasses say where it goes in :meth:`emit`."""

    def __init__(self) -> None:
        self.last, self.at = 0.0, 0.0

    def __call__(self, fraction: float) -> None:
        fraction = min(max(float(fraction), 0.0), 1.0)
        now = time.monotonic()
        if fraction <= self.last or (fraction < 1.0 and fraction - self.last < 0.01 and now - self.at < 0.05):
            return
        self.last, self.at = fraction, now
        self.emit(fraction)

    def emit(self, fraction: float) -> None:
        raise NotImplementedError


class _Progress(ThrottledProgress):
    """Forwards progress to the parent over the workers' pipe."""

    def __init__(self, task_id: str) -> None:
        super().__init__()
        self.task_id = task_id

    def emit(self, fraction: float) -> None:
        _send("progress", self.task_id, fraction)


def execute(task_id: str, task: Task) -> Any:
    """Run one task in the worker; the only function the pool schedules."""
    _send("start", task_id, os.getpid())
    try:
        return task.run(_Progress(task_id))
    except MeshMarkError as exc:
        extensions = {k: v for k, v in vars(exc).items() if isinstance(v, int | str | None)}
        raise EngineFailure(type(exc), str(exc), extensions) from None
    except MemoryError:
        raise WorkerOutOfMemory() from None
    except Exception as exc:
        raise WorkerBug(type(exc).__name__, traceback.format_exc()) from None

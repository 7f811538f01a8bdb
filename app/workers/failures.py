"""Every way a task can fail, and the problem its caller gets, for both jobs backends.

In the engine process, :func:`capture` turns what the task raised into an exception that survives
the trip back to the parent (engine errors as class + message: some do not pickle on their own).
:func:`problem` turns that, or a failure of the process itself, into the caller's problem.
"""

from __future__ import annotations

import traceback
from concurrent.futures.process import BrokenProcessPool
from typing import Any

from pebble import ProcessExpired

from app.problems import (
    BUSY,
    INTERNAL,
    TIMED_OUT,
    WORKER_FAILED,
    ProblemError,
    problem_for_core_error,
    redact,
)
from core.errors import MeshMarkError


class EngineFailure(Exception):
    """The engine refused the input: ``exc_type`` is the :mod:`core.errors` class."""

    def __init__(self, exc_type: type[BaseException], message: str, extensions: dict[str, Any]) -> None:
        super().__init__(exc_type, message, extensions)
        self.exc_type, self.message, self.extensions = exc_type, message, extensions


class WorkerOutOfMemory(Exception):
    """The task hit the process's address-space limit (RLIMIT_AS)."""


class WorkerBug(Exception):
    """Any other exception in the task; ``details`` is the traceback text (for the log only)."""

    def __init__(self, summary: str, details: str) -> None:
        super().__init__(summary, details)
        self.summary, self.details = summary, details


def capture(exc: Exception) -> Exception:
    """What to raise in the parent's place for ``exc``, raised by a task (call it in the except
    clause, so that the traceback is the task's)."""
    if isinstance(exc, MeshMarkError):
        extensions = {k: v for k, v in vars(exc).items() if isinstance(v, int | str | None)}
        return EngineFailure(type(exc), str(exc), extensions)
    if isinstance(exc, MemoryError):
        return WorkerOutOfMemory()
    return WorkerBug(type(exc).__name__, traceback.format_exc())


def problem(failure: BaseException, *, memory_mb: int, timeout: float) -> ProblemError:
    """The caller's problem for a captured failure, or a failure of the worker process: the
    engine's message, or a fixed public message.  Logging is the caller's.

    The engine's messages are built from what it knows (counts, positions, names of its own
    fields), never from the file's text or the key, so nothing is cut out of them: cutting the
    key out by substring garbled details when the key was a common word ("56-bit [key]word") and
    missed it in escaped forms."""
    if isinstance(failure, EngineFailure):
        return problem_for_core_error(failure.exc_type, failure.message, failure.extensions)
    if isinstance(failure, WorkerOutOfMemory):
        return ProblemError(WORKER_FAILED, f"the worker ran out of memory (limit {memory_mb} MiB)")
    if isinstance(failure, ProcessExpired):
        return ProblemError(WORKER_FAILED, "the worker process died while handling this request; it has been "
                            "replaced, other requests are unaffected", headers={"Retry-After": "1"})
    if isinstance(failure, TimeoutError):
        return timed_out(timeout)
    if isinstance(failure, BrokenProcessPool | RuntimeError):
        return ProblemError(WORKER_FAILED, "the worker pool failed; retry later",
                            headers={"Retry-After": "1"})
    return ProblemError(INTERNAL, "internal error")


def details(failure: BaseException, key: str | None) -> str:
    """What to log of an unexpected failure (the key cut out)."""
    return redact(failure.details if isinstance(failure, WorkerBug) else repr(failure), key)


def timed_out(timeout: float) -> ProblemError:
    return ProblemError(TIMED_OUT, f"the work ran longer than {timeout:g} s and was stopped")


def busy(slots: int, retry_after: int) -> ProblemError:
    """Every task slot is taken."""
    return ProblemError(BUSY, f"all {slots} task slots are taken; retry later",
                        headers={"Retry-After": str(retry_after)})


def poisoned(attempts: int) -> ProblemError:
    """A job whose worker process died ``attempts`` times (Redis backend)."""
    return ProblemError(WORKER_FAILED, f"the worker process died {attempts} times while running this job "
                        "(killed, crashed or out of memory); it is not retried again", attempts=attempts)

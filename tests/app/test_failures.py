"""app.workers.failures: what each failure of a task answers, the same for both jobs backends."""

from __future__ import annotations

from concurrent.futures.process import BrokenProcessPool

from pebble import ProcessExpired

from app.workers import failures
from core.errors import CapacityError, MeshFormatError


def _captured(exc: Exception) -> Exception:
    try:
        raise exc
    except Exception as raised:
        return failures.capture(raised)


def test_engine_errors_keep_their_class_message_and_members() -> None:
    # the engine's messages hold no input (issue 15): they pass unchanged, nothing is cut out
    failure = _captured(CapacityError("12 carriers, 56 needed", carriers=12, needed=56))
    assert isinstance(failure, failures.EngineFailure) and failure.exc_type is CapacityError
    problem = failures.problem(failure, memory_mb=0, timeout=1)
    assert problem.to_dict() == {
        "type": "https://meshmark.dev/problems/too-little-capacity", "status": 422,
        "title": "Too little capacity for the watermark", "detail": "12 carriers, 56 needed",
        "carriers": 12, "needed": 56}
    located = failures.problem(_captured(MeshFormatError("bad", "line 3")), memory_mb=0, timeout=1)
    assert located.problem.slug == "malformed-mesh" and located.extensions == {"location": "line 3"}


def test_failures_of_the_process_have_fixed_public_messages() -> None:
    def detail(failure: BaseException) -> tuple[str, str]:
        problem = failures.problem(failure, memory_mb=512, timeout=2.5)
        return problem.problem.slug, problem.detail

    out_of_memory = ("worker-failed", "the worker ran out of memory (limit 512 MiB)")
    assert detail(_captured(MemoryError())) == out_of_memory
    assert detail(TimeoutError()) == ("timed-out", "the work ran longer than 2.5 s and was stopped")
    assert detail(ProcessExpired("gone", code=-9, pid=1))[0] == "worker-failed"
    assert detail(BrokenProcessPool())[1] == "the worker pool failed; retry later"
    bug = _captured(KeyError("k"))
    assert isinstance(bug, failures.WorkerBug) and "KeyError" in bug.details
    assert detail(bug) == ("internal-error", "internal error")


def test_the_log_line_of_a_bug_never_holds_the_key() -> None:
    bug = _captured(ValueError("bad value near the key hunter2-key"))
    assert "hunter2-key" not in failures.details(bug, "hunter2-key")
    assert "[key]" in failures.details(bug, "hunter2-key")


def test_busy_and_poisoned() -> None:
    busy = failures.busy(8, 3)
    assert (busy.status_code, busy.detail, busy.headers) == (
        429, "all 8 task slots are taken; retry later", {"Retry-After": "3"})
    assert failures.poisoned(2).extensions == {"attempts": 2}

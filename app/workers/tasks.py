"""The work the service does, one table: every task kind, what it runs in a worker and how its
value becomes an answer.  Job kinds (``/v1/jobs/{kind}``) are the kinds marked ``job``.

A :class:`Task` holds the uploaded bytes and the engine's :class:`~core.options.Options` (never
numpy or trimesh objects), so sending one to a worker process is one pickle of bytes.  A preview
may carry a second file, the ``original`` its mesh is compared with.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from app.results import Rendered, copy_result, embedded_result, json_answer, json_result, preview_result
from app.tracing import CopyPlan, TracePlan, current_registry, rank_copies, record_copy, run_copy, run_trace
from core import api
from core.fingerprint import Fingerprinted
from core.formats import DEFAULT_LIMITS, Limits
from core.preview import PreviewGeometry, preview_file


@dataclass(frozen=True)
class Task:
    """One engine call: ``kind`` is a key of :data:`TASKS`."""

    kind: str
    data: bytes
    options: api.Options
    filename: str | None = None
    limits: Limits = DEFAULT_LIMITS
    #: preview: the file ``data`` was watermarked from, and its name
    original: bytes | None = None
    original_filename: str | None = None
    #: the id of the request that asked for it (log lines, job status)
    request_id: str | None = None
    #: copy and trace: the codeword or the registered groups (:mod:`app.tracing`)
    plan: CopyPlan | TracePlan | None = None

    @property
    def key(self) -> str | None:
        """The watermark key (for log fingerprints and redaction), if any."""
        return self.options.key if isinstance(self.options.key, str) else None

    def run(self, progress: api.Progress) -> Any:
        """The engine call (in a worker process)."""
        return TASKS[self.kind].run(self, progress)

    def render(self, value: Any) -> Rendered:
        """The answer for the value :meth:`run` returned."""
        return TASKS[self.kind].render(self, value)


@dataclass(frozen=True)
class TaskKind:
    run: Callable[[Task, api.Progress], Any]
    render: Callable[[Task, Any], Rendered]
    #: offered as a background job (``POST /v1/jobs/{kind}``)
    job: bool


def _copy(task: Task, progress: api.Progress) -> Fingerprinted:
    assert isinstance(task.plan, CopyPlan)
    return run_copy(task.plan, task.data, task.options, filename=task.filename, limits=task.limits,
                    progress=progress)


def _trace(task: Task, progress: api.Progress) -> dict[tuple[str, int], Any]:
    assert isinstance(task.plan, TracePlan)
    return run_trace(task.plan, task.data, task.options.secret, filename=task.filename, limits=task.limits,
                     progress=progress)


def _rendered_copy(task: Task, value: Fingerprinted) -> Rendered:
    """The marked copy, once it is in the registry (where the answer is rendered)."""
    assert isinstance(task.plan, CopyPlan)
    stored = record_copy(current_registry(), task.plan, task.options, value)
    return copy_result(value.file, task.filename, stored.asset_id, stored.codeword_bits, value.score)


def _rendered_trace(task: Task, value: dict[tuple[str, int], Any]) -> Rendered:
    assert isinstance(task.plan, TracePlan)
    return json_answer(rank_copies(current_registry(), task.plan, value))


def _embed(task: Task, progress: api.Progress) -> api.EmbeddedFile:
    return api.embed(task.data, task.options, filename=task.filename, limits=task.limits, progress=progress)


def _detect(task: Task, progress: api.Progress) -> api.DetectResult:
    return api.detect(task.data, task.options, filename=task.filename, limits=task.limits, progress=progress)


def _capacity(task: Task, progress: api.Progress) -> api.CapacityReport:
    return api.capacity(task.data, task.options, filename=task.filename, limits=task.limits,
                        progress=progress)


def _preview(task: Task, progress: api.Progress) -> PreviewGeometry:
    return preview_file(task.data, filename=task.filename, original=task.original,
                        original_filename=task.original_filename, limits=task.limits)


def _rendered_embedding(task: Task, value: api.EmbeddedFile) -> Rendered:
    return embedded_result(value, task.filename)


def _rendered_json(task: Task, value: Any) -> Rendered:
    return json_result(value)


def _rendered_preview(task: Task, value: PreviewGeometry) -> Rendered:
    return preview_result(value)


TASKS: dict[str, TaskKind] = {
    "embed": TaskKind(_embed, _rendered_embedding, job=True),
    "detect": TaskKind(_detect, _rendered_json, job=True),
    "capacity": TaskKind(_capacity, _rendered_json, job=False),
    "preview": TaskKind(_preview, _rendered_preview, job=False),
    "copy": TaskKind(_copy, _rendered_copy, job=True),
    "trace": TaskKind(_trace, _rendered_trace, job=False),
}
JOB_KINDS = tuple(name for name, kind in TASKS.items() if kind.job)


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

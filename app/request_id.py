"""The id of the request being served, for log lines and job status.

It comes from the caller's ``X-Request-ID`` header when that is a sane token, else it is made here;
:class:`app.middleware.MetricsMiddleware` sets it for the request and answers it in the
``X-Request-ID`` header, and the job runners carry it (in :class:`~app.workers.tasks.Task`) into the
job's status and the worker processes.  It lives in a context variable, so that asyncio tasks
started for a request (the pool's waiter, the job's follower) keep it.
"""

from __future__ import annotations

import logging
import re
import uuid
from contextvars import ContextVar

REQUEST_ID_HEADER = "X-Request-ID"
#: what a caller's request id may be: a token that is safe in a log line and a header
_REQUEST_ID = re.compile(r"[A-Za-z0-9._:@/+=-]{1,128}")
_request_id: ContextVar[str | None] = ContextVar("meshmark_request_id", default=None)


def request_id_from(header: str | None) -> str:
    """The caller's request id when it is a sane token (1-128 characters), else a new one."""
    if header is not None and _REQUEST_ID.fullmatch(header):
        return header
    return uuid.uuid4().hex


def current_request_id() -> str | None:
    return _request_id.get()


def set_request_id(request_id: str | None) -> None:
    """Set for the current context (a request, a job in a worker)."""
    _request_id.set(request_id)


class RequestIdFilter(logging.Filter):
    """Adds ``request_id`` (``-`` outside a request) to every record it sees."""

    def filter(self, record: logging.LogRecord) -> bool:
        if not hasattr(record, "request_id"):
            record.request_id = _request_id.get() or "-"
        return True



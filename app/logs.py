"""One log stream for the server, the job runners and the workers: text or JSON lines, every
line with the id of the request it serves (:mod:`app.request_id`).

Also the one log line per engine call: what ran, on how many bytes, and a keyed fingerprint of the
watermark key (never the key: see :func:`app.inputs.key_fingerprint`).
"""

from __future__ import annotations

import logging
import sys
from typing import TYPE_CHECKING

from pythonjsonlogger.json import JsonFormatter

from app.inputs import key_fingerprint
from app.request_id import RequestIdFilter

if TYPE_CHECKING:
    from fastapi import Request

    from app.workers.tasks import Task

log = logging.getLogger("meshmark.app")

TEXT_FORMAT = "%(asctime)s %(levelname)s %(name)s [%(request_id)s] %(message)s"
#: the fields of a JSON line (python-json-logger), with their names in the line
JSON_FIELDS = "{asctime}{levelname}{name}{message}{request_id}"
JSON_NAMES = {"asctime": "time", "levelname": "level", "name": "logger"}


def formatter(log_format: str) -> logging.Formatter:
    if log_format == "json":
        return JsonFormatter(JSON_FIELDS, style="{", rename_fields=JSON_NAMES)
    return logging.Formatter(TEXT_FORMAT)


def decorate(handler: logging.Handler, log_format: str) -> None:
    """Give a handler (ours, or one Celery made) the request id and the chosen format."""
    handler.addFilter(RequestIdFilter())
    handler.setFormatter(formatter(log_format))


def configure_logging(level: str, log_format: str) -> None:
    """One handler on standard error for every logger, uvicorn's included (they propagate to the
    root once uvicorn is started with ``log_config=None``)."""
    handler = logging.StreamHandler(sys.stderr)
    decorate(handler, log_format)
    root = logging.getLogger()
    for old in list(root.handlers):
        root.removeHandler(old)
    root.addHandler(handler)
    root.setLevel(level.upper())
    for name in ("uvicorn", "uvicorn.error"):
        logging.getLogger(name).handlers.clear()
        logging.getLogger(name).propagate = True


def log_task(request: Request, task: Task, **fields: object) -> None:
    secret: bytes = request.app.state.fingerprint_secret
    fingerprint = key_fingerprint(task.key, secret) if task.key else "-"
    extra = " ".join(f"{k}={v}" for k, v in fields.items())
    log.info("%s key=%s bytes=%d %s", task.kind, fingerprint, len(task.data), extra)

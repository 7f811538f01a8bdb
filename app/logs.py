"""The one log line per engine call: what ran, on how many bytes, and a keyed fingerprint of the
watermark key (never the key: see :func:`app.inputs.key_fingerprint`)."""

from __future__ import annotations

import logging

from fastapi import Request

from app.inputs import key_fingerprint
from app.workers.tasks import Task

log = logging.getLogger("meshmark.app")


def log_task(request: Request, task: Task, **fields: object) -> None:
    secret: bytes = request.app.state.fingerprint_secret
    fingerprint = key_fingerprint(task.key, secret) if task.key else "-"
    extra = " ".join(f"{k}={v}" for k, v in fields.items())
    log.info("%s key=%s bytes=%d %s", task.kind, fingerprint, len(task.data), extra)

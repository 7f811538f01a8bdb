"""Pure ASGI middleware: the request-body cap and the per-request metrics and log line."""

from __future__ import annotations

import json
import logging
import time

from starlette.datastructures import Headers
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from app.metrics import Metrics
from app.problems import PROBLEM_MEDIA_TYPE, TOO_LARGE, ProblemError

log = logging.getLogger("meshmark.access")


class BodyTooLarge(ProblemError):
    def __init__(self, limit: int) -> None:
        super().__init__(TOO_LARGE, f"the request body exceeds {limit:,} bytes", max_body_bytes=limit)


class BodyLimitMiddleware:
    """Refuses a body above ``max_bytes``: at once when Content-Length says so, otherwise as soon
    as the bytes received pass the limit, before the multipart parser has seen them all."""

    def __init__(self, app: ASGIApp, max_bytes: int) -> None:
        self.app, self.max_bytes = app, max_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        declared = Headers(scope=scope).get("content-length")
        if declared is not None and declared.isdigit() and int(declared) > self.max_bytes:
            await self._reject(scope, send)
            return

        received = 0
        started = False

        async def limited_receive() -> Message:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.max_bytes:
                    raise BodyTooLarge(self.max_bytes)
            return message

        async def tracking_send(message: Message) -> None:
            nonlocal started
            started = started or message["type"] == "http.response.start"
            await send(message)

        try:
            await self.app(scope, limited_receive, tracking_send)
        except BodyTooLarge:
            if started:
                raise
            await self._reject(scope, send)

    async def _reject(self, scope: Scope, send: Send) -> None:
        body = json.dumps(BodyTooLarge(self.max_bytes).to_dict(scope.get("path"))).encode()
        await send({"type": "http.response.start", "status": 413, "headers": [
            (b"content-type", PROBLEM_MEDIA_TYPE.encode()), (b"content-length", str(len(body)).encode()),
            (b"connection", b"close")]})
        await send({"type": "http.response.body", "body": body})


class MetricsMiddleware:
    """Counts requests by route template and status, times them, and logs one line each (the
    route template, not the path: no job ids in metric labels, nothing from the query string).

    The time is until the last byte of the answer was handed to the server: work after it (a
    refused upload read and dropped in the background, see :mod:`app.forms`) does not count."""

    def __init__(self, app: ASGIApp, metrics: Metrics) -> None:
        self.app, self.metrics = app, metrics

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        start = time.perf_counter()
        status = 500
        answered: float | None = None

        async def recording_send(message: Message) -> None:
            nonlocal status, answered
            if message["type"] == "http.response.start":
                status = message["status"]
            await send(message)
            if message["type"] == "http.response.body" and not message.get("more_body", False):
                answered = time.perf_counter()

        self.metrics.in_progress += 1
        try:
            await self.app(scope, receive, recording_send)
        finally:
            self.metrics.in_progress -= 1
            elapsed = (time.perf_counter() if answered is None else answered) - start
            route = getattr(scope.get("route"), "path", None) or "unmatched"
            self.metrics.observe_request(scope["method"], route, status, elapsed)
            client = scope.get("client") or ("-", 0)
            log.info("%s %s %s %d %.1f ms", client[0], scope["method"], route, status, elapsed * 1000)

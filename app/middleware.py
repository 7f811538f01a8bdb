"""Pure ASGI middleware: the request-body cap, and the request id, metrics and log line of each
request."""

from __future__ import annotations

import json
import logging
import time

from starlette.datastructures import Headers, MutableHeaders
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from app.metrics import Metrics
from app.problems import PROBLEM_BASE, PROBLEM_MEDIA_TYPE, TOO_LARGE, ProblemError
from app.request_id import REQUEST_ID_HEADER, request_id_from, set_request_id

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
    """Gives each request its id, counts requests by route template and status, times them, and
    logs one access line each: route template (not the path: no job ids in metric labels, nothing
    from the query string), status, the problem type of an error answer, duration.

    The id is the caller's ``X-Request-ID`` when it is a sane token, else a new one; it is answered
    in ``X-Request-ID`` and set for everything the request does (:mod:`app.logs`).  The time is
    until the last byte of the answer was handed to the server: work after it (a refused upload
    read and dropped in the background, see :mod:`app.forms`) does not count."""

    def __init__(self, app: ASGIApp, metrics: Metrics) -> None:
        self.app, self.metrics = app, metrics

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        start = time.perf_counter()
        request_id = request_id_from(Headers(scope=scope).get(REQUEST_ID_HEADER))
        set_request_id(request_id)
        status = 500
        answered: float | None = None
        problem: bytearray | None = None

        async def recording_send(message: Message) -> None:
            nonlocal status, answered, problem
            if message["type"] == "http.response.start":
                status = message["status"]
                headers = MutableHeaders(scope=message)
                headers[REQUEST_ID_HEADER] = request_id
                if headers.get("content-type") == PROBLEM_MEDIA_TYPE:
                    problem = bytearray()
            elif message["type"] == "http.response.body" and problem is not None and len(problem) < 65536:
                problem += message.get("body", b"")
            await send(message)
            if message["type"] == "http.response.body" and not message.get("more_body", False):
                answered = time.perf_counter()

        self.metrics.in_progress.inc()
        try:
            await self.app(scope, receive, recording_send)
        finally:
            self.metrics.in_progress.dec()
            elapsed = (time.perf_counter() if answered is None else answered) - start
            route = getattr(scope.get("route"), "path", None) or "unmatched"
            self.metrics.observe_request(scope["method"], route, status, elapsed)
            client = scope.get("client") or ("-", 0)
            log.info("%s %s %s %d %s %.1f ms", client[0], scope["method"], route, status,
                     _problem_slug(problem), elapsed * 1000)


def _problem_slug(body: bytearray | None) -> str:
    """The problem type of an error answer, as its slug (``busy``), ``-`` for other answers."""
    if body is None:
        return "-"
    try:
        kind = str(json.loads(body).get("type", "about:blank"))
    except (ValueError, AttributeError):
        return "-"
    return kind.removeprefix(PROBLEM_BASE)

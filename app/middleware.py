"""Pure ASGI middleware: the request-body cap, and the request id, metrics and log line of each
request."""

from __future__ import annotations

import asyncio
import json
import logging
import time

from starlette.datastructures import Headers, MutableHeaders
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from app.metrics import Metrics
from app.overload import UploadBudget
from app.problems import BODY_TIMEOUT, BUSY, PROBLEM_BASE, PROBLEM_MEDIA_TYPE, TOO_LARGE, ProblemError
from app.request_id import REQUEST_ID_HEADER, request_id_from, set_request_id

log = logging.getLogger("meshmark.access")


class BodyRefused(ProblemError):
    """The body cannot be taken (too large, over the upload budget, too slow): answered at once."""


def _too_large(limit: int) -> BodyRefused:
    return BodyRefused(TOO_LARGE, f"the request body exceeds {limit:,} bytes", max_body_bytes=limit)


class BodyLimitMiddleware:
    """Refuses a body above ``max_bytes``: at once when Content-Length says so, otherwise as soon
    as the bytes received pass the limit, before the multipart parser has seen them all.

    With a ``budget``, every chunk received counts against the bytes all requests in progress may
    hold (given back when the request ends; beyond it: ``busy``), and with ``idle_timeout`` a body
    that stops arriving for that many seconds ends its request (408 ``body-timeout``): a stalled
    client held up to 16 MiB of the API's memory with no time limit (120 of them: 1.9 GB)."""

    def __init__(self, app: ASGIApp, max_bytes: int, budget: UploadBudget | None = None,
                 idle_timeout: float | None = None) -> None:
        self.app, self.max_bytes, self.budget, self.idle_timeout = app, max_bytes, budget, idle_timeout

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        declared = Headers(scope=scope).get("content-length")
        if declared is not None and declared.isdigit() and int(declared) > self.max_bytes:
            await self._reject(scope, send, _too_large(self.max_bytes))
            return

        received = 0
        started = False
        body_done = scope["method"] in ("GET", "HEAD", "DELETE", "OPTIONS") and declared in (None, "0")

        async def limited_receive() -> Message:
            nonlocal received, body_done
            if body_done or self.idle_timeout is None:
                message = await receive()
            else:
                try:
                    message = await asyncio.wait_for(receive(), self.idle_timeout)
                except TimeoutError:
                    raise BodyRefused(BODY_TIMEOUT, f"no byte of the request body for {self.idle_timeout:g} "
                                      "s", headers={"Connection": "close"}) from None
            if message["type"] == "http.request":
                chunk = len(message.get("body", b""))
                received += chunk
                body_done = not message.get("more_body", False)
                if received > self.max_bytes:
                    raise _too_large(self.max_bytes)
                if self.budget is not None and not self.budget.take(chunk):
                    received -= chunk
                    raise self.budget.refusal()
            return message

        async def tracking_send(message: Message) -> None:
            nonlocal started
            started = started or message["type"] == "http.response.start"
            await send(message)

        try:
            await self.app(scope, limited_receive, tracking_send)
        except BodyRefused as refusal:
            if started:
                raise
            await self._reject(scope, send, refusal)
        except ProblemError as refusal:  # the upload budget's busy
            if started or refusal.problem is not BUSY:
                raise
            await self._reject(scope, send, refusal)
        finally:
            if self.budget is not None:
                self.budget.give_back(received)

    @staticmethod
    async def _reject(scope: Scope, send: Send, refusal: ProblemError) -> None:
        body = json.dumps(refusal.to_dict(scope.get("path"))).encode()
        headers = [(k.lower().encode("latin-1"), v.encode("latin-1"))
                   for k, v in (refusal.headers or {}).items() if k.lower() != "connection"]
        await send({"type": "http.response.start", "status": refusal.status_code, "headers": [
            (b"content-type", PROBLEM_MEDIA_TYPE.encode()), (b"content-length", str(len(body)).encode()),
            (b"connection", b"close"), *headers]})
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

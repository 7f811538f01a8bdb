"""RFC 9457 problem details: the catalogue of problem types, the engine-exception table and the
exception handlers that turn both into ``application/problem+json``.

Every problem carries a public ``detail`` written for the caller; internal messages (tracebacks,
worker exit codes) go to the log only.  Nothing the caller sent is echoed, the key least of all.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from http import HTTPStatus
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import BaseModel, ConfigDict, Field
from starlette.exceptions import HTTPException

from core import errors

log = logging.getLogger("meshmark.app")

PROBLEM_BASE = "https://meshmark.dev/problems/"
PROBLEM_MEDIA_TYPE = "application/problem+json"


@dataclass(frozen=True)
class ProblemType:
    slug: str
    status: int
    title: str

    @property
    def uri(self) -> str:
        return PROBLEM_BASE + self.slug


BAD_FORM = ProblemType("bad-form", 422, "The request form is invalid")
UNSUPPORTED_FORMAT = ProblemType("unsupported-format", 415, "Unsupported mesh format")
NOT_MULTIPART = ProblemType("not-multipart", 415, "The request body must be multipart/form-data")
CALLBACK_NOT_ALLOWED = ProblemType("callback-not-allowed", 422, "This server may not call that callback URL")
MALFORMED_MESH = ProblemType("malformed-mesh", 422, "Malformed mesh file")
INVALID_INPUT = ProblemType("invalid-input", 422, "The engine rejected the input")
TOO_LARGE = ProblemType("too-large", 413, "Input too large")
TOO_LITTLE_CAPACITY = ProblemType("too-little-capacity", 422, "Too little capacity for the watermark")
DEGENERATE_MESH = ProblemType("degenerate-mesh", 422, "The mesh cannot carry a watermark")
BUSY = ProblemType("busy", 429, "Too many requests in progress")
TIMED_OUT = ProblemType("timed-out", 503, "The work took too long")
WORKER_FAILED = ProblemType("worker-failed", 503, "The worker process failed")
NOT_FOUND = ProblemType("not-found", 404, "No such job")
JOB_NOT_READY = ProblemType("job-not-ready", 409, "The job has not finished")
JOB_FAILED = ProblemType("job-failed", 409, "The job has no result")
UNAUTHORIZED = ProblemType("unauthorized", 401, "Missing or invalid API key")
NOT_READY = ProblemType("not-ready", 503, "The service is not ready")
BODY_TIMEOUT = ProblemType("body-timeout", 408, "The request body stopped arriving")
INTERNAL = ProblemType("internal-error", 500, "Internal server error")
COPY_CONFLICT = ProblemType("copy-conflict", 409, "The recipient's copy was issued otherwise")
NO_COPIES = ProblemType("no-copies", 404, "No copies registered")

PROBLEM_TYPES = (
    BAD_FORM, UNSUPPORTED_FORMAT, NOT_MULTIPART, MALFORMED_MESH, INVALID_INPUT, TOO_LARGE,
    TOO_LITTLE_CAPACITY, DEGENERATE_MESH, BUSY, TIMED_OUT, WORKER_FAILED, NOT_FOUND, JOB_NOT_READY,
    JOB_FAILED, UNAUTHORIZED, NOT_READY, INTERNAL, CALLBACK_NOT_ALLOWED, COPY_CONFLICT, NO_COPIES,
    BODY_TIMEOUT,
)

#: engine exception -> problem type; looked up along the exception's MRO
CORE_ERRORS: dict[type[errors.MeshMarkError], ProblemType] = {
    errors.UnsupportedFormatError: UNSUPPORTED_FORMAT,
    errors.MeshFormatError: MALFORMED_MESH,
    errors.LimitExceededError: TOO_LARGE,
    errors.DegenerateMeshError: DEGENERATE_MESH,
    errors.CapacityError: TOO_LITTLE_CAPACITY,
    errors.PayloadError: BAD_FORM,
    errors.MeshMarkError: INVALID_INPUT,
}


class Problem(BaseModel):
    """RFC 9457 problem details (extension members vary by type)."""

    model_config = ConfigDict(extra="allow")

    type: str = Field(examples=[BAD_FORM.uri])
    title: str
    status: int
    detail: str
    instance: str | None = None


class ProblemError(HTTPException):
    """An error with a public message, raised anywhere in the app and rendered as a problem.

    It is an ``HTTPException`` so that FastAPI passes it through body parsing untouched.
    """

    def __init__(self, problem: ProblemType, detail: str, *, headers: dict[str, str] | None = None,
                 **extensions: Any) -> None:
        super().__init__(problem.status, detail, headers)
        self.problem = problem
        self.extensions = extensions

    def to_dict(self, instance: str | None = None) -> dict[str, Any]:
        body: dict[str, Any] = {"type": self.problem.uri, "title": self.problem.title,
                                "status": self.problem.status, "detail": self.detail}
        if instance is not None:
            body["instance"] = instance
        body.update(self.extensions)
        return body


def problem_for_core_error(exc_type: type[BaseException], message: str,
                           extensions: dict[str, Any] | None = None) -> ProblemError:
    """The problem for an engine exception (by class), with the engine's message as detail."""
    for cls in exc_type.__mro__:
        if cls in CORE_ERRORS:
            return ProblemError(CORE_ERRORS[cls], message, **(extensions or {}))
    return ProblemError(INTERNAL, "internal error")


def redact(text: str, secret: str | None) -> str:
    """``text`` with ``secret`` cut out; drops the text entirely when the secret is too short to
    cut out safely (replacing every 'a' of a message would be worse than no message)."""
    if not secret or secret not in text:
        return text
    if len(secret) < 4:
        return "(detail withheld: it would reveal the key)"
    return text.replace(secret, "[key]")


def problem_response(exc: ProblemError, request: Request | None = None) -> JSONResponse:
    instance = request.url.path if request is not None else None
    return JSONResponse(exc.to_dict(instance), status_code=exc.status_code, headers=exc.headers,
                        media_type=PROBLEM_MEDIA_TYPE)


def problem_responses(*problems: ProblemType) -> dict[int | str, dict[str, Any]]:
    """OpenAPI ``responses`` entries for the given problem types (grouped by status)."""
    by_status: dict[int, list[ProblemType]] = {}
    for p in problems:
        by_status.setdefault(p.status, []).append(p)
    out: dict[int | str, dict[str, Any]] = {}
    for status, ps in sorted(by_status.items()):
        out[status] = {
            "description": "; ".join(f"`{p.slug}`: {p.title}" for p in ps),
            "content": {PROBLEM_MEDIA_TYPE: {"schema": {"$ref": "#/components/schemas/Problem"}}},
        }
    return out


async def _problem_error_handler(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, ProblemError)
    return problem_response(exc, request)


async def _validation_handler(request: Request, exc: Exception) -> JSONResponse:
    """FastAPI's 422 echoes ``input`` (which may be the key); this one names fields only."""
    assert isinstance(exc, RequestValidationError)
    fields = [{"loc": [str(x) for x in e.get("loc", ())], "msg": str(e.get("msg", "")),
               "type": str(e.get("type", ""))} for e in exc.errors()]
    names = ", ".join(sorted({f["loc"][-1] for f in fields if f["loc"]})) or "body"
    return problem_response(ProblemError(BAD_FORM, f"invalid or missing form fields: {names}",
                                         errors=fields), request)


_HTTP_METHODS = ("get", "put", "post", "delete", "options", "head", "patch", "trace")


def _template_regex(template: str) -> str:
    return "".join("[^/]+" if part.startswith("{") else re.escape(part)
                   for part in re.split(r"(\{[^/{}]+\})", template))


def _allowed_methods(request: Request) -> str | None:
    """The methods the OpenAPI document gives for this path.  Starlette's 405 names only the
    methods of the first route that fits the path (``GET /v1/jobs/{id}`` hides ``DELETE``).  As
    in OpenAPI, a literal path (``/v1/jobs/detect``) wins over a template it also fits."""
    paths: dict[str, dict[str, Any]] = request.app.openapi().get("paths", {})
    path = request.url.path
    item = paths.get(path)
    if item is None:
        item = next((candidate for template, candidate in paths.items()
                     if "{" in template and re.fullmatch(_template_regex(template), path)), None)
    methods = [m.upper() for m in _HTTP_METHODS if m in (item or {})]
    return ", ".join(methods) or None


async def _http_exception_handler(request: Request, exc: Exception) -> JSONResponse:
    """Starlette's own errors (unknown route, wrong method...): ``about:blank`` problems."""
    assert isinstance(exc, HTTPException)
    status = HTTPStatus(exc.status_code)
    body = {"type": "about:blank", "title": status.phrase, "status": status.value,
            "detail": exc.detail if isinstance(exc.detail, str) else status.description,
            "instance": request.url.path}
    headers = exc.headers
    if status == HTTPStatus.METHOD_NOT_ALLOWED:
        allowed = _allowed_methods(request)
        if allowed:
            headers = {**(headers or {}), "Allow": allowed}
    return JSONResponse(body, status_code=status.value, headers=headers, media_type=PROBLEM_MEDIA_TYPE)


async def _unhandled_handler(request: Request, exc: Exception) -> JSONResponse:
    log.error("unhandled error on %s %s", request.method, request.url.path,
              exc_info=(type(exc), exc, exc.__traceback__))
    return problem_response(ProblemError(INTERNAL, "internal error"), request)


def install_problem_handlers(app: FastAPI) -> None:
    app.add_exception_handler(ProblemError, _problem_error_handler)
    app.add_exception_handler(RequestValidationError, _validation_handler)
    app.add_exception_handler(HTTPException, _http_exception_handler)
    app.add_exception_handler(Exception, _unhandled_handler)

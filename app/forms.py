"""The multipart forms of ``/v1``: strict UTF-8 text fields and one dependency per form.

Starlette decodes a text field that is not valid UTF-8 as Latin-1 without a word, which would
silently turn a mangled key into a different key, and when a field comes twice it keeps the last
one (two keys, or two meshes, would be a silent choice).  :class:`StrictFormRoute` parses bodies
with :class:`app.multipart.FormParser`, which rejects both (``bad-form``, 422), with tight limits
(the route's ``max_files`` files, :data:`MAX_FORM_FIELDS` text fields of at most
:data:`MAX_TEXT_FIELD_BYTES` each), and answers a body that is not ``multipart/form-data`` with
``not-multipart`` (415) and what to send.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Coroutine
from typing import Annotated, Any

from fastapi import Depends, File, Form, Request, Response, UploadFile
from fastapi.routing import APIRoute
from python_multipart.multipart import parse_options_header
from starlette.background import BackgroundTask
from starlette.concurrency import run_in_threadpool
from starlette.datastructures import FormData
from starlette.types import Receive

from app.callbacks import CallbackRefused, check_url
from app.deps import OptionalWatermarkKey, SettingsDep, WatermarkKey, authenticate
from app.inputs import PAYLOAD_SCHEMA, STRENGTH_SCHEMA
from app.multipart import FormError, FormParser
from app.problems import BAD_FORM, CALLBACK_NOT_ALLOWED, NOT_MULTIPART, ProblemError, problem_response
from app.request_id import current_request_id
from app.tracing import (
    ASSET_ID_PATTERN,
    DEFAULT_THRESHOLD,
    DEFAULT_TOP,
    MAX_TOP,
    RECIPIENT_PATTERN,
    current_registry,
    plan_copy,
    plan_trace,
)
from app.workers.tasks import Task
from core.coding import MAX_PAYLOAD_BITS
from core.errors import PayloadError
from core.formats import FORMATS, spoken_list
from core.options import AUTO_METHOD, DEFAULT_METHOD, DEFAULT_STRENGTH, MAX_STRENGTH, METHODS, Options

#: text fields of one form (key, payload, method, strength and a few unknown ones, which are ignored)
MAX_FORM_FIELDS = 16
#: bytes of one text field: a key is at most 1024 characters (4 KiB of UTF-8)
MAX_TEXT_FIELD_BYTES = 64 * 1024
#: uploads up to this size stay in memory: the route reads the whole file into bytes for the
#: worker anyway, so spooling to disk at 1 MiB (Starlette's default) would only add a disk write
#: and read to every larger mesh
SPOOL_MAX_BYTES = 16 * 1024 * 1024
FORMAT_LABELS = [spec.label for spec in FORMATS.values()]
MAX_CALLBACK_URL = 2048
#: what a caller who sent something else should do instead
MULTIPART_HINT = ("send the mesh as a file part named 'mesh' and the options as text parts "
                  "(curl: -F mesh=@model.obj -F key=...; Python httpx: "
                  "files={'mesh': open(...)}, data={...})")


class StrictFormRequest(Request):
    """A request whose ``form()`` is parsed by :class:`app.multipart.FormParser`: multipart only,
    strict UTF-8, no field the route reads given twice, tight limits."""

    def __init__(self, scope: Any, receive: Receive, fields: frozenset[str], max_files: int = 1) -> None:
        super().__init__(scope, receive)
        self.fields, self.max_files = fields, max_files

    async def form(self, **_: Any) -> FormData:  # type: ignore[override]
        content_type = self.headers.get("content-type", "")
        kind, _params = parse_options_header(content_type)
        if kind != b"multipart/form-data":
            sent = kind.decode("latin-1") if kind else "a body without Content-Type"
            raise ProblemError(NOT_MULTIPART, f"this route takes a multipart/form-data form, not {sent}: "
                               f"{MULTIPART_HINT}")
        parser = FormParser(fields=self.fields, max_files=self.max_files, max_fields=MAX_FORM_FIELDS,
                            max_part_size=MAX_TEXT_FIELD_BYTES, spool_max_size=SPOOL_MAX_BYTES)
        try:
            form = await parser.parse(content_type, self.stream())
        except FormError as exc:
            raise ProblemError(BAD_FORM, f"invalid multipart body: {exc}") from None
        mesh = form.get("mesh")
        if "mesh" in self.fields and isinstance(mesh, str):
            await form.close()
            raise ProblemError(BAD_FORM, "form field 'mesh' is text, not a file: send the file's content "
                               "as a file part (curl: -F mesh=@model.obj, with the @)")
        return form


class StrictFormRoute(APIRoute):
    #: file fields a form of this route may carry
    max_files = 1

    def get_route_handler(self) -> Callable[[Request], Coroutine[Any, Any, Response]]:
        handler = super().get_route_handler()
        fields = _form_fields(self.dependant)

        async def strict_handler(request: Request) -> Response:
            refusal = self.authenticate(request) or _short_of_memory(request) or self.admit(request)
            if refusal is not None:
                # the upload is read and dropped, not parsed: closing a socket with unread data
                # makes the kernel reset the connection, and a client still sending could lose the
                # answer.  On a kept-alive connection the answer goes out first; when the client
                # asked to close, the server closes right after answering, so drop the body first.
                response = problem_response(refusal, request)
                if "close" in request.headers.get("connection", "").lower():
                    await _discard_body(request.receive)
                else:
                    response.background = BackgroundTask(_discard_body, request.receive)
                return response
            return await handler(StrictFormRequest(request.scope, request.receive, fields, self.max_files))

        return strict_handler

    def admit(self, request: Request) -> ProblemError | None:
        """Called before the body is read: a problem to answer instead of parsing the upload."""
        return None

    @staticmethod
    def authenticate(request: Request) -> ProblemError | None:
        """The API key, checked from the headers before any other refusal and before the body is
        read: a caller without a valid key learns nothing of the form or the load (no 422 or 429
        before 401) and costs no parsing (60 MB of form took 21 s of the server's CPU first)."""
        try:
            authenticate(request.app.state.settings, request.headers)
        except ProblemError as refusal:
            return refusal
        return None


def _short_of_memory(request: Request) -> ProblemError | None:
    guard = getattr(request.app.state, "memory_guard", None)
    return guard.refusal() if guard is not None else None


def _form_fields(dependant: Any) -> frozenset[str]:
    """Names of the form fields a route reads, through all its dependencies."""
    names: set[str] = set()
    todo = [dependant]
    while todo:
        current = todo.pop()
        names.update(field.alias for field in current.body_params)
        todo.extend(current.dependencies)
    return frozenset(names)


async def _discard_body(receive: Receive) -> None:
    try:
        while True:
            message = await receive()
            if message["type"] != "http.request" or not message.get("more_body", False):
                return
    except Exception:  # over the body limit, or the client went away: the server closes the connection
        return


class PooledFormRoute(StrictFormRoute):
    """A form route whose work goes to the worker pool: when every task slot is taken, the
    ``busy`` answer (429) goes out before the upload is parsed, so excess load costs the server
    little (the pool checks again, authoritatively, when the task is submitted)."""

    def admit(self, request: Request) -> ProblemError | None:
        pool = getattr(request.app.state, "pool", None)
        return pool.refusal() if pool is not None else None


class PreviewFormRoute(PooledFormRoute):
    """The preview's form carries two files: the mesh and the original it may be compared with."""

    max_files = 2


def _options(**fields: Any) -> Options:
    """The engine's options from the form's fields; a refusal is a ``bad-form`` problem."""
    try:
        return Options(**fields)
    except PayloadError as exc:
        raise ProblemError(BAD_FORM, str(exc)) from None


MeshFile = Annotated[UploadFile, File(description=f"The mesh: {spoken_list(FORMAT_LABELS)}.")]
OriginalFile = Annotated[UploadFile | None, File(
    description="The file `mesh` was watermarked from (optional). When both have the same parts, "
                "vertex counts and triangles, the answer carries each vertex's displacement.")]
Payload = Annotated[str | None, Form(description=f"Bitstring of 1-{MAX_PAYLOAD_BITS} '0'/'1'. Embed: the "
                                     "payload (default: a 32-bit code derived from the key). Detect: the "
                                     "expected payload, to get bit errors and a p-value.",
                                     json_schema_extra=PAYLOAD_SCHEMA)]
Strength = Annotated[float | None, Form(description=f"Boundary margin in (0, {MAX_STRENGTH:g}], as a "
                                        "fraction of the local neighbourhood scale (engine default "
                                        f"{DEFAULT_STRENGTH:g} if omitted).",
                                        json_schema_extra=STRENGTH_SCHEMA)]
_METHOD_SCHEMA = {"enum": list(METHODS)}
ChosenMethod = Annotated[str | None, Form(description=f"Embedding method (default: {AUTO_METHOD}).",
                                          json_schema_extra=_METHOD_SCHEMA)]


async def embed_task(
    settings: SettingsDep,
    mesh: MeshFile,
    key: WatermarkKey,
    payload: Payload = None,
    method: ChosenMethod = None,
    strength: Strength = None,
) -> Task:
    data = await mesh.read()
    options = _options(key=key, payload=payload, method=method, strength=strength)
    return Task("embed", data, options, filename=mesh.filename, limits=settings.limits(),
                request_id=current_request_id())


async def detect_task(
    settings: SettingsDep,
    mesh: MeshFile,
    key: WatermarkKey,
    payload: Payload = None,
    method: Annotated[str | None, Form(description="Method to look for (default: both).",
                                       json_schema_extra=_METHOD_SCHEMA)] = None,
) -> Task:
    data = await mesh.read()
    options = _options(key=key, payload=payload, method=method)
    return Task("detect", data, options, filename=mesh.filename, limits=settings.limits(),
                request_id=current_request_id())


async def capacity_task(
    settings: SettingsDep,
    mesh: MeshFile,
    key: OptionalWatermarkKey,
    method: ChosenMethod = None,
    strength: Strength = None,
) -> Task:
    """With the key, the carriers are exactly those an embedding with it will have."""
    data = await mesh.read()
    options = _options(key=key, method=method, strength=strength)
    return Task("capacity", data, options, filename=mesh.filename, limits=settings.limits(),
                request_id=current_request_id())


Recipient = Annotated[str, Form(description="Who the copy is for: any text of 1-500 characters without "
                                "control characters (opaque to MeshMark).",
                                json_schema_extra={"pattern": RECIPIENT_PATTERN, "minLength": 1,
                                                   "maxLength": 500})]
AssetId = Annotated[str | None, Form(description="The asset's id, 1-200 characters of letters, digits and "
                                     "`._:-` (default: `sha256:` and the SHA-256 of the uploaded file).",
                                     json_schema_extra={"pattern": ASSET_ID_PATTERN})]
_RECIPIENT, _ASSET_ID = re.compile(RECIPIENT_PATTERN), re.compile(ASSET_ID_PATTERN)


def _checked_asset_id(asset_id: str | None) -> str | None:
    if asset_id is not None and not _ASSET_ID.fullmatch(asset_id):
        raise ProblemError(BAD_FORM, "asset_id must be 1-200 characters of letters, digits and ._:-")
    return asset_id


async def copy_task(
    settings: SettingsDep,
    mesh: MeshFile,
    key: WatermarkKey,
    recipient: Recipient,
    asset_id: AssetId = None,
    method: Annotated[str, Form(json_schema_extra=_METHOD_SCHEMA)] = DEFAULT_METHOD,
    strength: Strength = None,
) -> Task:
    """A copy for ``recipient``: the codeword comes from the registry (the one issued before, or a
    fresh one)."""
    if not _RECIPIENT.fullmatch(recipient):
        raise ProblemError(BAD_FORM, "recipient must be 1-500 characters without control characters")
    data = await mesh.read()
    options = _options(key=key, method=method, strength=strength)
    asset = _checked_asset_id(asset_id)
    plan = await run_in_threadpool(lambda: plan_copy(current_registry(), data, options, recipient, asset))
    return Task("copy", data, options, filename=mesh.filename, limits=settings.limits(),
                request_id=current_request_id(), plan=plan)


async def trace_task(
    settings: SettingsDep,
    mesh: MeshFile,
    key: WatermarkKey,
    asset_id: Annotated[str | None, Form(description="Trace among the copies of this asset only (default: "
                                         "every copy registered).",
                                         json_schema_extra={"pattern": ASSET_ID_PATTERN})] = None,
    threshold: Annotated[float, Form(description="Accuse a recipient when the probability that an innocent "
                                     "scores as high is at most this, in (0, 0.5].",
                                     json_schema_extra={"exclusiveMinimum": 0, "maximum": 0.5})
                         ] = DEFAULT_THRESHOLD,
    top: Annotated[int, Form(description=f"Recipients listed, best first, 1-{MAX_TOP}.",
                             json_schema_extra={"minimum": 1, "maximum": MAX_TOP})] = DEFAULT_TOP,
) -> Task:
    if not (math.isfinite(threshold) and 0 < threshold <= 0.5):
        raise ProblemError(BAD_FORM, "threshold must be a number in (0, 0.5]")
    if not 1 <= top <= MAX_TOP:
        raise ProblemError(BAD_FORM, f"top must be 1 to {MAX_TOP}")
    data = await mesh.read()
    options = _options(key=key)
    asset = _checked_asset_id(asset_id)
    plan = await run_in_threadpool(lambda: plan_trace(current_registry(), asset, threshold, top))
    return Task("trace", data, options, filename=mesh.filename, limits=settings.limits(),
                request_id=current_request_id(), plan=plan)


async def preview_task(settings: SettingsDep, mesh: MeshFile, original: OriginalFile = None) -> Task:
    data = await mesh.read()
    before = None if original is None else await original.read()
    return Task("preview", data, Options(), filename=mesh.filename, original=before,
                original_filename=None if original is None else original.filename,
                limits=settings.limits(), request_id=current_request_id())


async def callback_url(
    settings: SettingsDep,
    callback_url: Annotated[str | None, Form(description="Where to POST the job's final status, signed "
                                              "(`X-MeshMark-Signature`); its host must be one the server "
                                              "allows (`MESHMARK_CALLBACK_HOSTS`, none by default).",
                                              json_schema_extra={"format": "uri",
                                                                 "maxLength": MAX_CALLBACK_URL})] = None,
) -> str | None:
    """The job's callback URL, when it names an allowed host (``bad-form`` otherwise)."""
    if not callback_url:
        return None
    if len(callback_url) > MAX_CALLBACK_URL:
        raise ProblemError(BAD_FORM, f"callback_url must be at most {MAX_CALLBACK_URL} characters")
    try:
        return check_url(callback_url, settings.callback_hosts)
    except CallbackRefused as exc:
        raise ProblemError(CALLBACK_NOT_ALLOWED, str(exc)) from None


EmbedForm = Annotated[Task, Depends(embed_task)]
DetectForm = Annotated[Task, Depends(detect_task)]
CapacityForm = Annotated[Task, Depends(capacity_task)]
PreviewForm = Annotated[Task, Depends(preview_task)]
CopyForm = Annotated[Task, Depends(copy_task)]
TraceForm = Annotated[Task, Depends(trace_task)]
CallbackUrl = Annotated[str | None, Depends(callback_url)]

"""The multipart forms of ``/v1``: strict UTF-8 text fields and one dependency per form.

Starlette decodes a text field that is not valid UTF-8 as Latin-1 without a word, which would
silently turn a mangled key into a different key, and when a field comes twice it keeps the last
one (two keys, or two meshes, would be a silent choice).  :class:`StrictFormRoute` parses
multipart bodies with a parser that rejects both (``bad-form``, 422), and with tight limits: one
file (the route's ``max_files``), :data:`MAX_FORM_FIELDS` text fields of at most
:data:`MAX_TEXT_FIELD_BYTES` each.
"""

from __future__ import annotations

from collections.abc import Callable, Coroutine
from typing import Annotated, Any

from fastapi import Depends, File, Form, Request, Response, UploadFile
from fastapi.routing import APIRoute
from python_multipart.multipart import parse_options_header
from starlette.background import BackgroundTask
from starlette.datastructures import FormData
from starlette.exceptions import HTTPException
from starlette.formparsers import MultiPartException, MultiPartParser
from starlette.types import Receive

from app.deps import SettingsDep, WatermarkKey
from app.inputs import PAYLOAD_SCHEMA, STRENGTH_SCHEMA
from app.problems import BAD_FORM, ProblemError, problem_response
from app.workers.tasks import Task
from core.coding import MAX_PAYLOAD_BITS
from core.errors import PayloadError
from core.formats import FORMATS, spoken_list
from core.options import DEFAULT_METHOD, DEFAULT_STRENGTH, MAX_STRENGTH, METHODS, Options

#: text fields of one form (key, payload, method, strength and a few unknown ones, which are ignored)
MAX_FORM_FIELDS = 16
#: bytes of one text field: a key is at most 1024 characters (4 KiB of UTF-8)
MAX_TEXT_FIELD_BYTES = 64 * 1024
#: the form fields of the routes; other names are not repeated in messages
FIELD_NAMES = ("mesh", "original", "key", "payload", "method", "strength")
FORMAT_LABELS = [spec.label for spec in FORMATS.values()]
_FORM_LIMITS = {"max_fields": MAX_FORM_FIELDS, "max_part_size": MAX_TEXT_FIELD_BYTES}


def _field_label(name: str) -> str:
    return f"form field '{name}'" if name in FIELD_NAMES else "a form field"


class _StrictUTF8Parser(MultiPartParser):
    #: uploads up to this size stay in memory: the route reads the whole file into bytes for the
    #: worker anyway, so Starlette's default (1 MiB, then a temporary file) would only add a disk
    #: write and read to every larger mesh
    spool_max_size = 16 * 1024 * 1024

    def __init__(self, *args: Any, fields: frozenset[str], **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._fields = fields  # the fields this route reads: those may not come twice
        self._seen: set[str] = set()
        self._open_parts = 0

    def on_part_begin(self) -> None:
        self._open_parts += 1
        super().on_part_begin()

    async def parse(self) -> FormData:
        """Starlette returns what it has when the body stops inside a part (no closing boundary),
        and leaves that part's spooled file open; this refuses such a body and closes the file."""
        try:
            form = await super().parse()
        except BaseException:
            self._close_files()
            raise
        if self._open_parts:
            self._close_files()
            raise ProblemError(BAD_FORM, "invalid multipart body: it ends inside a part "
                               "(no closing boundary)")
        return form

    def _close_files(self) -> None:
        for file in getattr(self, "_files_to_close_on_error", ()):
            file.close()

    def on_headers_finished(self) -> None:
        super().on_headers_finished()
        name = self._current_part.field_name
        if name in self._seen and name in self._fields:  # other fields are ignored, repeated or not
            raise ProblemError(BAD_FORM, f"{_field_label(name)} is given more than once")
        self._seen.add(name)

    def on_part_end(self) -> None:
        self._open_parts -= 1
        part = self._current_part
        if part.file is None:
            try:
                bytes(part.data).decode("utf-8")
            except UnicodeDecodeError:
                raise ProblemError(BAD_FORM, f"{_field_label(part.field_name)} is not valid UTF-8") from None
        super().on_part_end()


class StrictFormRequest(Request):
    def __init__(self, scope: Any, receive: Receive, fields: frozenset[str], max_files: int = 1) -> None:
        super().__init__(scope, receive)
        self.fields, self.max_files = fields, max_files

    async def form(self, **limits: Any) -> FormData:  # type: ignore[override]
        limits = {**limits, **_FORM_LIMITS, "max_files": self.max_files}
        content_type, _ = parse_options_header(self.headers.get("content-type", ""))
        if content_type != b"multipart/form-data":
            try:
                form = await super().form(**limits)
            except HTTPException as exc:  # Starlette's 400 for a broken url-encoded form
                raise ProblemError(BAD_FORM, f"invalid form body: {exc.detail}") from None
            names = [name for name, _ in form.multi_items()]
            for name in self.fields:
                if names.count(name) > 1:
                    raise ProblemError(BAD_FORM, f"{_field_label(name)} is given more than once")
            return form
        parser = _StrictUTF8Parser(self.headers, self.stream(), fields=self.fields, **limits)
        try:
            return await parser.parse()
        except MultiPartException as exc:
            raise ProblemError(BAD_FORM, f"invalid multipart body: {exc.message}") from None


class StrictFormRoute(APIRoute):
    #: file fields a form of this route may carry
    max_files = 1

    def get_route_handler(self) -> Callable[[Request], Coroutine[Any, Any, Response]]:
        handler = super().get_route_handler()
        fields = _form_fields(self.dependant)

        async def strict_handler(request: Request) -> Response:
            refusal = self.admit(request)
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


async def embed_task(
    settings: SettingsDep,
    mesh: MeshFile,
    key: WatermarkKey,
    payload: Payload = None,
    method: Annotated[str, Form(json_schema_extra=_METHOD_SCHEMA)] = DEFAULT_METHOD,
    strength: Strength = None,
) -> Task:
    data = await mesh.read()
    options = _options(key=key, payload=payload, method=method, strength=strength)
    return Task("embed", data, options, filename=mesh.filename, limits=settings.limits())


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
    return Task("detect", data, options, filename=mesh.filename, limits=settings.limits())


async def capacity_task(
    settings: SettingsDep,
    mesh: MeshFile,
    method: Annotated[str, Form(json_schema_extra=_METHOD_SCHEMA)] = DEFAULT_METHOD,
    strength: Strength = None,
) -> Task:
    data = await mesh.read()
    options = _options(method=method, strength=strength)
    return Task("capacity", data, options, filename=mesh.filename, limits=settings.limits())


async def preview_task(settings: SettingsDep, mesh: MeshFile, original: OriginalFile = None) -> Task:
    data = await mesh.read()
    before = None if original is None else await original.read()
    return Task("preview", data, Options(), filename=mesh.filename, original=before,
                original_filename=None if original is None else original.filename,
                limits=settings.limits())


EmbedForm = Annotated[Task, Depends(embed_task)]
DetectForm = Annotated[Task, Depends(detect_task)]
CapacityForm = Annotated[Task, Depends(capacity_task)]
PreviewForm = Annotated[Task, Depends(preview_task)]

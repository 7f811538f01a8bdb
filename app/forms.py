"""The multipart forms of ``/v1``: strict UTF-8 text fields and one dependency per form.

Starlette decodes a text field that is not valid UTF-8 as Latin-1 without a word, which would
silently turn a mangled key into a different key.  :class:`StrictFormRoute` parses multipart
bodies with a parser that rejects such fields instead (``bad-form``, 422).
"""

from __future__ import annotations

from collections.abc import Callable, Coroutine
from typing import Annotated, Any

from fastapi import Depends, File, Form, Request, Response, UploadFile
from fastapi.routing import APIRoute
from python_multipart.multipart import parse_options_header
from starlette.datastructures import FormData
from starlette.formparsers import MultiPartException, MultiPartParser

from app.deps import SettingsDep, WatermarkKey
from app.inputs import InputError, validate_method, validate_payload, validate_strength
from app.problems import BAD_FORM, ProblemError
from app.workers.tasks import CapacityTask, DetectTask, EmbedTask
from core.api import DEFAULT_METHOD, METHODS


class _StrictUTF8Parser(MultiPartParser):
    def on_part_end(self) -> None:
        part = self._current_part
        if part.file is None:
            try:
                bytes(part.data).decode("utf-8")
            except UnicodeDecodeError:
                raise ProblemError(BAD_FORM, f"form field '{part.field_name}' is not valid UTF-8") from None
        super().on_part_end()


class StrictFormRequest(Request):
    async def form(self, **limits: Any) -> FormData:  # type: ignore[override]
        content_type, _ = parse_options_header(self.headers.get("content-type", ""))
        if content_type != b"multipart/form-data":
            return await super().form(**limits)
        parser = _StrictUTF8Parser(self.headers, self.stream(), **limits)
        try:
            return await parser.parse()
        except MultiPartException as exc:
            raise ProblemError(BAD_FORM, f"invalid multipart body: {exc.message}") from None


class StrictFormRoute(APIRoute):
    def get_route_handler(self) -> Callable[[Request], Coroutine[Any, Any, Response]]:
        handler = super().get_route_handler()

        async def strict_handler(request: Request) -> Response:
            return await handler(StrictFormRequest(request.scope, request.receive))

        return strict_handler


def _check(value: Any, validate: Callable[..., Any], **kwargs: Any) -> Any:
    try:
        return validate(value, **kwargs)
    except InputError as exc:
        raise ProblemError(BAD_FORM, str(exc)) from None


MeshFile = Annotated[UploadFile, File(description="The mesh: OBJ, PLY, STL, OFF, GLB, glTF or 3DS.")]
Payload = Annotated[str | None, Form(description="Bitstring of 1-256 '0'/'1'. Embed: the payload "
                                     "(default: a 32-bit code derived from the key). Detect: the "
                                     "expected payload, to get bit errors and a p-value.")]
Strength = Annotated[float | None, Form(description="Boundary margin, > 0 (engine default if omitted).")]
_METHOD_SCHEMA = {"enum": list(METHODS)}


async def embed_task(
    settings: SettingsDep,
    mesh: MeshFile,
    key: WatermarkKey,
    payload: Payload = None,
    method: Annotated[str, Form(json_schema_extra=_METHOD_SCHEMA)] = DEFAULT_METHOD,
    strength: Strength = None,
) -> EmbedTask:
    return EmbedTask(
        data=await mesh.read(), key=key, filename=mesh.filename,
        payload=_check(payload, validate_payload), method=_check(method, validate_method),
        strength=_check(strength, validate_strength), limits=settings.limits(),
    )


async def detect_task(
    settings: SettingsDep,
    mesh: MeshFile,
    key: WatermarkKey,
    payload: Payload = None,
    method: Annotated[str | None, Form(description="Method to look for (default: both).",
                                       json_schema_extra=_METHOD_SCHEMA)] = None,
) -> DetectTask:
    return DetectTask(
        data=await mesh.read(), key=key, filename=mesh.filename,
        payload=_check(payload, validate_payload),
        method=None if method is None else _check(method, validate_method),
        limits=settings.limits(),
    )


async def capacity_task(
    settings: SettingsDep,
    mesh: MeshFile,
    method: Annotated[str, Form(json_schema_extra=_METHOD_SCHEMA)] = DEFAULT_METHOD,
    strength: Strength = None,
) -> CapacityTask:
    return CapacityTask(
        data=await mesh.read(), filename=mesh.filename, method=_check(method, validate_method),
        strength=_check(strength, validate_strength), limits=settings.limits(),
    )


EmbedForm = Annotated[EmbedTask, Depends(embed_task)]
DetectForm = Annotated[DetectTask, Depends(detect_task)]
CapacityForm = Annotated[CapacityTask, Depends(capacity_task)]

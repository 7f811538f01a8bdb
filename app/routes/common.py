"""What the routes share: the problems of an engine call and the answer of an embedding."""

from __future__ import annotations

from typing import Any

from fastapi import Response

from app.problems import (
    BAD_FORM,
    BODY_TIMEOUT,
    BUSY,
    DEGENERATE_MESH,
    MALFORMED_MESH,
    NOT_MULTIPART,
    TIMED_OUT,
    TOO_LARGE,
    UNAUTHORIZED,
    UNSUPPORTED_FORMAT,
    WORKER_FAILED,
)
from app.results import EMBED_HEADERS, MESH_MEDIA_TYPES, Rendered

#: problems of every route that runs the engine on an uploaded mesh
MESH_PROBLEMS = (BAD_FORM, UNSUPPORTED_FORMAT, NOT_MULTIPART, MALFORMED_MESH, DEGENERATE_MESH, TOO_LARGE,
                 BUSY, TIMED_OUT, WORKER_FAILED, UNAUTHORIZED, BODY_TIMEOUT)


def as_response(result: Rendered) -> Response:
    return Response(result.body, media_type=result.media_type, headers=result.headers)


def embed_openapi_response(description: str = "The watermarked mesh, in the format and encoding it was "
                           "uploaded in.", extra_content: dict[str, Any] | None = None,
                           ) -> dict[int | str, dict[str, Any]]:
    """OpenAPI ``responses`` entry of a watermarked-mesh answer, with its documented headers."""
    binary = {media_type: {"schema": {"type": "string", "format": "binary"}}
              for media_type in MESH_MEDIA_TYPES}
    headers = {"Content-Disposition": {"schema": {"type": "string"},
                                       "description": 'attachment; filename="<stem>.marked.<ext>"'}}
    headers.update({name: {"schema": {"type": "string"}, "description": text}
                    for name, text in EMBED_HEADERS.items()})
    return {200: {"description": description, "content": {**binary, **(extra_content or {})},
                  "headers": headers}}

"""``Annotated`` dependencies: settings, worker pool, jobs, caller authentication, watermark key.

All are ``async def`` although none awaits: FastAPI runs a plain ``def`` dependency in its thread
pool, and under load those hops (four per upload) cost the event loop more than the checks
themselves."""

from __future__ import annotations

import hashlib
import hmac
from typing import Annotated

from fastapi import Depends, Form, Header, Request
from fastapi.security import APIKeyHeader, HTTPAuthorizationCredentials, HTTPBearer
from starlette.datastructures import Headers

from app.config import Settings
from app.inputs import KEY_HEADER_SCHEMA, KEY_SCHEMA, key_from_header
from app.jobs import JobStore, Runner
from app.problems import BAD_FORM, NOT_READY, UNAUTHORIZED, ProblemError
from app.workers.pool import WorkerPool
from core.errors import PayloadError
from core.options import MAX_KEY_CHARS, check_key


async def get_settings(request: Request) -> Settings:
    settings: Settings = request.app.state.settings
    return settings


async def get_pool(request: Request) -> WorkerPool:
    pool: WorkerPool | None = getattr(request.app.state, "pool", None)
    if pool is None:
        raise ProblemError(NOT_READY, "the worker pool is not running")
    return pool


async def get_runner(request: Request) -> Runner:
    runner: Runner | None = getattr(request.app.state, "runner", None)
    if runner is None:
        raise ProblemError(NOT_READY, "the job runner is not running")
    return runner


async def get_store(runner: Annotated[Runner, Depends(get_runner)]) -> JobStore:
    return runner.store


SettingsDep = Annotated[Settings, Depends(get_settings)]
PoolDep = Annotated[WorkerPool, Depends(get_pool)]
RunnerDep = Annotated[Runner, Depends(get_runner)]
StoreDep = Annotated[JobStore, Depends(get_store)]

_bearer = HTTPBearer(auto_error=False, description="One of MESHMARK_API_KEYS (when set).")
_api_key = APIKeyHeader(name="X-API-Key", auto_error=False, description="Same keys as the bearer token.")


def caller_id(api_key: str) -> str:
    """Who a caller is, for job ownership: 128 bits of SHA-256 of the API key (the same in every
    API process; an API key is long and random, so its hash reveals nothing usable)."""
    return hashlib.sha256(api_key.encode()).hexdigest()[:32]


def authenticate(settings: Settings, headers: Headers) -> str | None:
    """The caller's :func:`caller_id`, from the request headers alone (None when
    ``MESHMARK_API_KEYS`` is not set: anyone may call); ``unauthorized`` without a valid key.

    Routes with a body call it before reading a byte of it (see :mod:`app.forms`)."""
    if not settings.api_keys:
        return None
    scheme, _, credentials = headers.get("authorization", "").partition(" ")
    given = credentials.strip() if scheme.lower() == "bearer" and credentials.strip() else None
    if given is None:
        given = headers.get("x-api-key")
    if given is not None:
        raw = given.encode()
        # compare with every key, without stopping early, so timing tells nothing
        matches = [hmac.compare_digest(raw, k.get_secret_value().encode()) for k in settings.api_keys]
        if any(matches):
            return caller_id(given)
    raise ProblemError(UNAUTHORIZED, "send a valid API key as 'Authorization: Bearer <key>' or 'X-API-Key'",
                       headers={"WWW-Authenticate": "Bearer"})


async def require_caller(
    request: Request,
    settings: SettingsDep,
    bearer: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
    api_key: Annotated[str | None, Depends(_api_key)],
) -> str | None:
    """The caller (see :func:`authenticate`); ``bearer`` and ``api_key`` declare the two ways in
    the OpenAPI document."""
    del bearer, api_key
    return authenticate(settings, request.headers)


Caller = Annotated[str | None, Depends(require_caller)]


_KEY_FIELD = Form(description=f"Secret watermark key, 1-{MAX_KEY_CHARS} characters, none a control, format "
                  "or separator character (Unicode Cc, Cf, Zl, Zp). Give it here or in the "
                  "X-Watermark-Key header: exactly one of the two.",
                  json_schema_extra=KEY_SCHEMA)
_KEY_HEADER = Header(description="The watermark key, instead of the `key` form field: its UTF-8 bytes (the "
                     "pattern reads them as Latin-1, as HTTP does); the characters the form field "
                     "refuses are refused here too.", json_schema_extra=KEY_HEADER_SCHEMA)


async def optional_watermark_key(
    key: Annotated[str | None, _KEY_FIELD] = None,
    x_watermark_key: Annotated[str | None, _KEY_HEADER] = None,
) -> str | None:
    """The watermark key from the form field or the header (not both), or None."""
    if not key and x_watermark_key is None:
        return None
    return await watermark_key(key, x_watermark_key)


async def watermark_key(
    key: Annotated[str | None, _KEY_FIELD] = None,
    x_watermark_key: Annotated[str | None, _KEY_HEADER] = None,
) -> str:
    """The watermark key from the form field or the header (exactly one of them)."""
    if key is not None and x_watermark_key is not None:
        raise ProblemError(BAD_FORM, "give the key once: the form field 'key' or the header X-Watermark-Key")
    if x_watermark_key is not None:
        key = key_from_header(x_watermark_key)
        if key is None:
            raise ProblemError(BAD_FORM, "the X-Watermark-Key header must be UTF-8")
    if not key:
        raise ProblemError(BAD_FORM, "a watermark key is required (form field 'key' or header "
                           "X-Watermark-Key)")
    try:
        check_key(key)
    except PayloadError as exc:
        raise ProblemError(BAD_FORM, str(exc)) from None
    return key


WatermarkKey = Annotated[str, Depends(watermark_key)]
OptionalWatermarkKey = Annotated[str | None, Depends(optional_watermark_key)]

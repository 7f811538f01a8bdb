"""The FastAPI application: ``create_app(settings)`` wires routes, problems, middleware and the
worker pool (started and stopped by the lifespan).  ``app`` is the default instance for uvicorn."""

from __future__ import annotations

import logging
import secrets
import tempfile
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

from fastapi import Depends, FastAPI
from fastapi_offline import FastAPIOffline

from app.blobs import LocalBlobStore
from app.config import Settings
from app.deps import require_caller
from app.jobs import Runner
from app.memory_jobs import InMemoryJobStore, LocalJobRunner
from app.metrics import Metrics
from app.middleware import BodyLimitMiddleware, MetricsMiddleware
from app.overload import MemoryGuard, UploadBudget, map_large_allocations
from app.problems import BAD_FORM, Problem, install_problem_handlers, problem_responses
from app.routes import V1_ROUTERS, health
from app.tracing import close_registry, configure_registry
from app.web import router as web_router
from app.workers.pool import WorkerPool
from meshmark import __version__

log = logging.getLogger("meshmark.app")

DESCRIPTION = """Hide a keyed bitstring in the geometry of a 3-D triangle mesh, and find it again
from the mesh and the key alone (blind detection).

Errors are RFC 9457 problem details (`application/problem+json`) whose `type` is one of the
`https://meshmark.dev/problems/<slug>` URIs listed in the README. The watermark key is never echoed
or logged."""


def callback_secret(settings: Settings) -> bytes:
    secret = settings.callback_secret
    return secret.get_secret_value().encode() if secret is not None else b""


def make_runner(settings: Settings, pool: WorkerPool) -> Runner:
    """The jobs backend of ``settings.jobs_backend``: this process's pool (``memory``), or Celery
    workers through Redis (``redis``; imported only then, so that a single machine needs neither
    Celery nor Redis installed)."""
    if settings.jobs_backend == "redis":
        from app.redis_jobs.runner import CeleryJobRunner

        return CeleryJobRunner.from_settings(settings)
    # a private directory of this process under blob_dir (checked: ours, mode 0700)
    result_dir = tempfile.mkdtemp(prefix="results-", dir=LocalBlobStore(settings.blob_dir).root)
    store = InMemoryJobStore(result_dir, max_result_bytes=settings.max_result_bytes)
    return LocalJobRunner(store, pool, ttl=settings.job_result_ttl_seconds,
                          max_jobs=settings.max_stored_jobs, callback_secret=callback_secret(settings))


@asynccontextmanager
async def lifespan(app: FastAPI) -> AsyncIterator[None]:
    settings: Settings = app.state.settings
    map_large_allocations()
    pool = WorkerPool(workers=settings.workers, slots=settings.admission_slots,
                      timeout=settings.job_timeout_seconds, memory_mb=settings.worker_memory_mb,
                      max_tasks=settings.worker_max_tasks)
    runner = make_runner(settings, pool)
    configure_registry(settings)
    await pool.start()
    app.state.pool, app.state.runner = pool, runner
    log.info("MeshMark ready: %d workers, %d task slots, %s jobs backend", settings.workers,
             settings.admission_slots, settings.jobs_backend)
    try:
        yield
    finally:
        app.state.pool = app.state.runner = None
        await runner.close()
        await pool.stop()
        close_registry()


def _form_fields_without_null(schemas: dict[str, Any], operation: dict[str, Any]) -> None:
    """A multipart form cannot send ``null``: an optional field is one that may be left out, so
    ``anyOf: [X, null]`` becomes ``X`` (FastAPI writes the former for ``X | None``)."""
    form = operation.get("requestBody", {}).get("content", {}).get("multipart/form-data", {})
    ref = form.get("schema", {}).get("$ref", "")
    body = schemas.get(ref.rsplit("/", 1)[-1], {}) if ref.startswith("#/components/schemas/") else {}
    for prop in body.get("properties", {}).values():
        branches = prop.get("anyOf", [])
        kept = [b for b in branches if b != {"type": "null"}]
        if len(kept) == 1 and len(branches) == 2:
            del prop["anyOf"]
            prop.update(kept[0])


def _document(schema: dict[str, Any]) -> dict[str, Any]:
    """FastAPI's document, told the truth: 422s are ``bad-form`` problems (see
    :mod:`app.problems`), form fields are never ``null`` and API keys are optional (only checked
    when configured)."""
    schemas = schema.setdefault("components", {}).setdefault("schemas", {})
    schemas["Problem"] = Problem.model_json_schema(ref_template="#/components/schemas/{model}")
    for name in ("HTTPValidationError", "ValidationError"):
        schemas.pop(name, None)
    bad_form = problem_responses(BAD_FORM)[BAD_FORM.status]
    for operations in schema.get("paths", {}).values():
        for operation in operations.values():
            _form_fields_without_null(schemas, operation)
            response = operation.get("responses", {}).get("422")
            if response is not None and "application/problem+json" not in response.get("content", {}):
                operation["responses"]["422"] = bad_form
            if operation.get("security"):
                operation["security"].append({})
    return schema


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or Settings()
    # /docs and /redoc from assets shipped in the fastapi-offline package: they work offline
    app = FastAPIOffline(title="MeshMark", version=__version__, description=DESCRIPTION, lifespan=lifespan)
    app.state.settings = settings
    secret = settings.log_fingerprint_secret
    app.state.fingerprint_secret = (secret.get_secret_value().encode() if secret is not None
                                    else secrets.token_bytes(32))
    app.state.metrics = Metrics()

    install_problem_handlers(app)
    for router in V1_ROUTERS:
        app.include_router(router, dependencies=[Depends(require_caller)])
    app.include_router(health.router)
    app.include_router(web_router)  # the page at /, open like /docs: its API calls carry the key

    app.state.upload_budget = UploadBudget(settings.upload_budget_bytes)
    app.state.memory_guard = MemoryGuard(settings.api_memory_mb * 1024 * 1024)
    app.state.metrics.watch(app.state.upload_budget, app.state.memory_guard)
    app.add_middleware(BodyLimitMiddleware, max_bytes=settings.max_body_bytes, budget=app.state.upload_budget,
                       idle_timeout=settings.body_timeout_seconds)
    app.add_middleware(MetricsMiddleware, metrics=app.state.metrics)  # outermost: sees the 413s too

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            app.openapi_schema = _document(FastAPI.openapi(app))
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]
    return app


app = create_app()

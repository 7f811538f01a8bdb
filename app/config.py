"""Service settings: one pydantic-settings class read from ``MESHMARK_*`` environment variables.

Every default here is also in the README's limits table; change both together.
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Annotated, Literal

from pydantic import Field, SecretStr, field_validator, model_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

from core.formats.base import Limits

MIB = 1024 * 1024

#: shortest caller API key accepted (a key is a password that anyone may try over the network)
MIN_API_KEY_CHARS = 16
#: admission slots per worker process when ``queue_size`` is not set
QUEUE_SLOTS_PER_WORKER = 8


class Settings(BaseSettings):
    """Limits and knobs of the HTTP service (the CLI's ``serve`` uses them too)."""

    model_config = SettingsConfigDict(env_prefix="MESHMARK_", extra="ignore")

    host: str = "127.0.0.1"
    port: int = Field(default=8000, ge=0, le=65535)
    log_level: Literal["debug", "info", "warning", "error"] = "info"
    log_format: Literal["text", "json"] = "text"  # json: one JSON object per line

    # worker processes doing the mesh work
    workers: int = Field(default=2, ge=1)
    worker_max_tasks: int = Field(default=100, ge=0)  # tasks before a worker is recycled; 0 = never
    worker_memory_mb: int = Field(default=2048, ge=0)  # RLIMIT_AS of each worker; 0 = no limit
    job_timeout_seconds: float = Field(default=120.0, gt=0)  # run time of one task in a worker
    queue_size: int | None = Field(default=None, ge=1)  # tasks running + waiting; None = 8 x workers

    # inputs
    max_upload_bytes: int = Field(default=64 * MIB, ge=1)
    max_vertices: int = Field(default=2_000_000, ge=1)
    max_faces: int = Field(default=4_000_000, ge=1)
    max_meshes: int = Field(default=256, ge=1)
    max_json_bytes: int = Field(default=16 * MIB, ge=1)  # glTF JSON chunk
    # the API process's own memory: bodies being received (all requests), a body that stops
    # arriving, resident memory before new work is refused, connections uvicorn keeps at once
    upload_budget_bytes: int = Field(default=512 * MIB, ge=1)
    body_timeout_seconds: float = Field(default=30.0, gt=0)
    api_memory_mb: int = Field(default=2048, ge=0)  # 0 = no cap
    max_connections: int = Field(default=1024, ge=1)

    # jobs
    job_result_ttl_seconds: float = Field(default=3600.0, gt=0)  # finished jobs are kept this long
    max_stored_jobs: int = Field(default=256, ge=1)  # jobs in the store, finished or not
    max_result_bytes: int = Field(default=2048 * MIB, ge=1)  # memory backend: results on disk, all jobs

    # where jobs run: "memory" (this process's pool) or "redis" (Celery workers: `meshmark worker`)
    jobs_backend: Literal["memory", "redis"] = "memory"
    redis_url: str = Field(default="redis://127.0.0.1:6379/0", pattern=r"^(rediss?|unix)://")
    jobs_queue: str = Field(default="meshmark", pattern=r"^[A-Za-z0-9_.-]{1,64}$")  # + Redis key prefix
    blob_dir: Path = Field(default_factory=lambda: Path(tempfile.gettempdir()) / "meshmark-blobs")
    worker_concurrency: int | None = Field(default=None, ge=1)  # `meshmark worker` processes; None = CPUs

    # leak tracing: the registry of issued copies, a SQLite file unless a database URL is given
    # (postgresql+psycopg://user:password@host/db; the URL wins over the path)
    registry_path: Path = Path("meshmark-registry.sqlite3")
    registry_url: SecretStr | None = None

    # security: caller API keys (comma-separated; empty = no authentication), and the HMAC secret of
    # the key fingerprints in logs (None = random per process)
    api_keys: Annotated[list[SecretStr], NoDecode] = Field(default_factory=list)
    log_fingerprint_secret: SecretStr | None = None

    # job callbacks: the hosts a callback_url may name (comma-separated; empty = callbacks off) and
    # the HMAC secret of their X-MeshMark-Signature (required when hosts are set)
    callback_hosts: Annotated[list[str], NoDecode] = Field(default_factory=list)
    callback_secret: SecretStr | None = None

    @field_validator("log_level", "log_format", mode="before")
    @classmethod
    def _lower(cls, value: object) -> object:
        return value.strip().lower() if isinstance(value, str) else value

    @field_validator("callback_hosts", mode="before")
    @classmethod
    def _split_hosts(cls, value: object) -> object:
        if isinstance(value, str):
            return [h.strip().lower() for h in value.split(",") if h.strip()]
        return value

    @model_validator(mode="after")
    def _budget_holds_one_upload(self) -> Settings:
        if self.upload_budget_bytes < self.max_body_bytes:
            raise ValueError(f"MESHMARK_UPLOAD_BUDGET_BYTES ({self.upload_budget_bytes:,}) must be at "
                             f"least one request body (MESHMARK_MAX_UPLOAD_BYTES + 64 KiB = "
                             f"{self.max_body_bytes:,})")
        return self

    @model_validator(mode="after")
    def _callbacks_need_a_secret(self) -> Settings:
        secret = self.callback_secret.get_secret_value() if self.callback_secret is not None else ""
        if self.callback_hosts and not secret:
            raise ValueError("MESHMARK_CALLBACK_SECRET is required when MESHMARK_CALLBACK_HOSTS is set "
                             "(receivers check the signature with it)")
        return self

    @field_validator("api_keys", mode="before")
    @classmethod
    def _split_api_keys(cls, value: object) -> object:
        if isinstance(value, str):
            keys = [k.strip() for k in value.split(",") if k.strip()]
            if value.strip() and not keys:  # " , " must not turn authentication off unnoticed
                raise ValueError("MESHMARK_API_KEYS is set but names no key (leave it empty to run "
                                 "without authentication)")
            return keys
        return value

    @field_validator("api_keys")
    @classmethod
    def _long_api_keys(cls, keys: list[SecretStr]) -> list[SecretStr]:
        short = sum(len(k.get_secret_value()) < MIN_API_KEY_CHARS for k in keys)
        if short:
            raise ValueError(f"{short} of the MESHMARK_API_KEYS {'is' if short == 1 else 'are'} shorter than "
                             f"{MIN_API_KEY_CHARS} characters: use long random keys (python -c 'import "
                             "secrets; print(secrets.token_urlsafe(24))')")
        return keys

    @property
    def admission_slots(self) -> int:
        """Tasks allowed in the pool at once (running + waiting) before answering 429."""
        return self.queue_size or QUEUE_SLOTS_PER_WORKER * self.workers

    @property
    def max_body_bytes(self) -> int:
        """Request body cap: the mesh limit plus room for the multipart envelope and text fields."""
        return self.max_upload_bytes + 64 * 1024

    def limits(self) -> Limits:
        """Engine limits checked before the engine allocates anything proportional to a count."""
        return Limits(
            max_bytes=self.max_upload_bytes,
            max_vertices=self.max_vertices,
            max_faces=self.max_faces,
            max_meshes=self.max_meshes,
            max_json_bytes=self.max_json_bytes,
        )

"""Settings from MESHMARK_* variables, and the limits handed to the engine."""

from __future__ import annotations

import os

import pytest
from pydantic import ValidationError

from app.config import Settings
from core.formats.base import Limits


def test_defaults(monkeypatch):
    for name in list(os.environ):
        if name.startswith("MESHMARK_"):
            monkeypatch.delenv(name)
    s = Settings()
    assert (s.host, s.port, s.workers) == ("127.0.0.1", 8000, 2)
    assert s.max_upload_bytes == 64 * 1024 * 1024
    assert (s.max_vertices, s.max_faces) == (2_000_000, 4_000_000)
    assert s.admission_slots == 16  # 8 per worker
    assert (s.job_timeout_seconds, s.worker_memory_mb, s.job_result_ttl_seconds) == (120, 2048, 3600)
    assert s.api_keys == [] and s.log_fingerprint_secret is None


def test_environment(monkeypatch):
    monkeypatch.setenv("MESHMARK_WORKERS", "3")
    monkeypatch.setenv("MESHMARK_QUEUE_SIZE", "5")
    monkeypatch.setenv("MESHMARK_MAX_UPLOAD_BYTES", "1000")
    monkeypatch.setenv("MESHMARK_MAX_VERTICES", "77")
    monkeypatch.setenv("MESHMARK_API_KEYS", "alpha-0123456789ab, bravo-0123456789ab,,charlie-0123456789")
    s = Settings()
    assert s.workers == 3 and s.admission_slots == 5
    assert [k.get_secret_value() for k in s.api_keys] == ["alpha-0123456789ab", "bravo-0123456789ab",
                                                          "charlie-0123456789"]
    assert "alpha" not in repr(s.api_keys)  # secrets stay masked in reprs and logs
    assert s.limits() == Limits(max_bytes=1000, max_vertices=77, max_faces=4_000_000, max_meshes=256,
                                max_json_bytes=16 * 1024 * 1024)
    assert s.max_body_bytes == 1000 + 64 * 1024


def test_invalid_values_are_refused(monkeypatch):
    monkeypatch.setenv("MESHMARK_WORKERS", "0")
    with pytest.raises(ValidationError):
        Settings()


@pytest.mark.parametrize(("value", "message"), [
    (" , ", "names no key"),  # used to turn authentication off without a word
    (",", "names no key"),
    ("a", "shorter than 16 characters"),  # one-character keys were accepted
    ("long-enough-key-0123, short", "1 of the MESHMARK_API_KEYS is shorter than 16"),
])
def test_api_keys_that_would_weaken_authentication_are_refused(monkeypatch, value, message):
    monkeypatch.setenv("MESHMARK_API_KEYS", value)
    with pytest.raises(ValidationError, match=message) as info:
        Settings()
    # the messages (what `meshmark serve` prints) do not echo the keys
    assert "short" not in " ".join(e["msg"] for e in info.value.errors()).replace("shorter", "")


def test_empty_api_keys_mean_no_authentication(monkeypatch):
    monkeypatch.setenv("MESHMARK_API_KEYS", "")
    assert Settings().api_keys == []


def test_the_upload_budget_holds_one_request_body():
    with pytest.raises(ValidationError, match="at least one request body"):
        Settings(max_upload_bytes=1_000_000, upload_budget_bytes=500_000)
    assert Settings(max_upload_bytes=1_000_000, upload_budget_bytes=1_000_000 + 64 * 1024).upload_budget_bytes

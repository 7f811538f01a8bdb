"""Validation of the text inputs shared by the HTTP forms and the CLI.

Messages never contain the offending value: a watermark key must not be echoed, and the other
fields are cheap enough to re-read on the client side.
"""

from __future__ import annotations

import hashlib
import hmac
import math
import re

from core.api import METHODS

MAX_KEY_CHARS = 1024
MAX_PAYLOAD_BITS = 256
_CONTROL = re.compile(r"[\x00-\x1f\x7f]")
_BITS = re.compile(r"[01]+")


class InputError(ValueError):
    """A text input is invalid; the message is safe to show to the caller."""


def validate_key(key: str | None) -> str:
    """The watermark key as the engine gets it: 1 to 1024 characters, no control characters.

    The key is used exactly as given (no trimming): a stray newline from ``curl -F key=<file``
    is rejected rather than silently making a different key.
    """
    if key is None or key == "":
        raise InputError("a watermark key is required (form field 'key' or header X-Watermark-Key)")
    if len(key) > MAX_KEY_CHARS:
        raise InputError(f"the key must be at most {MAX_KEY_CHARS} characters")
    if _CONTROL.search(key):
        raise InputError("the key must not contain control characters (newline, tab, NUL...)")
    return key


def key_from_header(raw: str) -> str:
    """A header value (decoded as Latin-1 by the server) re-read as the UTF-8 it must be."""
    try:
        return raw.encode("latin-1").decode("utf-8")
    except (UnicodeEncodeError, UnicodeDecodeError):
        raise InputError("the X-Watermark-Key header must be UTF-8") from None


def validate_payload(payload: str | None) -> str | None:
    if payload is None:
        return None
    if not 1 <= len(payload) <= MAX_PAYLOAD_BITS or not _BITS.fullmatch(payload):
        raise InputError(f"payload must be 1 to {MAX_PAYLOAD_BITS} characters, each '0' or '1'")
    return payload


def validate_method(method: str) -> str:
    if method not in METHODS:
        raise InputError(f"method must be one of: {', '.join(METHODS)}")
    return method


def validate_strength(strength: float | None) -> float | None:
    if strength is not None and not (math.isfinite(strength) and strength > 0):
        raise InputError("strength must be a finite number > 0")
    return strength


def key_fingerprint(key: str, secret: bytes) -> str:
    """First 8 hex digits of HMAC-SHA256(secret, key): lets logs correlate requests by key
    without letting anyone who reads them test guesses (the secret is not logged)."""
    return hmac.new(secret, key.encode("utf-8"), hashlib.sha256).hexdigest()[:8]

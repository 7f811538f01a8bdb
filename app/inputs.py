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
MAX_STRENGTH = 1.0
#: JSON Schema of the inputs above, for the OpenAPI document (an empty field counts as not sent)
KEY_SCHEMA = {"maxLength": MAX_KEY_CHARS, "pattern": "^[^\\u0000-\\u001f\\u007f]*$"}
# the header as it travels: Latin-1 text whose bytes are the key's UTF-8 (one character per group)
_UTF8_CHAR = ("(?:[\\x20-\\x7e]|[\\xc2-\\xdf][\\x80-\\xbf]|\\xe0[\\xa0-\\xbf][\\x80-\\xbf]"
              "|[\\xe1-\\xec\\xee\\xef][\\x80-\\xbf]{2}|\\xed[\\x80-\\x9f][\\x80-\\xbf]"
              "|\\xf0[\\x90-\\xbf][\\x80-\\xbf]{2}|[\\xf1-\\xf3][\\x80-\\xbf]{3}"
              "|\\xf4[\\x80-\\x8f][\\x80-\\xbf]{2})")
KEY_HEADER_SCHEMA = {"pattern": f"^{_UTF8_CHAR}{{0,{MAX_KEY_CHARS}}}$"}
PAYLOAD_SCHEMA = {"pattern": f"^([01]{{1,{MAX_PAYLOAD_BITS}}})?$"}
STRENGTH_SCHEMA = {"exclusiveMinimum": 0, "maximum": MAX_STRENGTH}
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
    if strength is not None and not (math.isfinite(strength) and 0 < strength <= MAX_STRENGTH):
        raise InputError(f"strength must be a number in (0, {MAX_STRENGTH:g}]")
    return strength


def key_fingerprint(key: str, secret: bytes) -> str:
    """First 8 hex digits of HMAC-SHA256(secret, key): lets logs correlate requests by key
    without letting anyone who reads them test guesses (the secret is not logged)."""
    return hmac.new(secret, key.encode("utf-8"), hashlib.sha256).hexdigest()[:8]

"""The text inputs as HTTP carries them: JSON Schemas for the OpenAPI document, the key header,
and the key's fingerprint for logs.  The inputs themselves are checked by :class:`core.options.Options`.
"""

from __future__ import annotations

import hashlib
import hmac

from core.coding import MAX_PAYLOAD_BITS
from core.options import KEY_PATTERN, MAX_KEY_CHARS, MAX_STRENGTH

#: JSON Schema of the inputs, for the OpenAPI document (an empty field counts as not sent)
KEY_SCHEMA = {"maxLength": MAX_KEY_CHARS, "pattern": KEY_PATTERN}
# the header as it travels: Latin-1 text whose bytes are the key's UTF-8 (one character per group)
_UTF8_CHAR = ("(?:[\\x20-\\x7e]|[\\xc2-\\xdf][\\x80-\\xbf]|\\xe0[\\xa0-\\xbf][\\x80-\\xbf]"
              "|[\\xe1-\\xec\\xee\\xef][\\x80-\\xbf]{2}|\\xed[\\x80-\\x9f][\\x80-\\xbf]"
              "|\\xf0[\\x90-\\xbf][\\x80-\\xbf]{2}|[\\xf1-\\xf3][\\x80-\\xbf]{3}"
              "|\\xf4[\\x80-\\x8f][\\x80-\\xbf]{2})")
KEY_HEADER_SCHEMA = {"pattern": f"^{_UTF8_CHAR}{{0,{MAX_KEY_CHARS}}}$"}
PAYLOAD_SCHEMA = {"pattern": f"^([01]{{1,{MAX_PAYLOAD_BITS}}})?$"}
STRENGTH_SCHEMA = {"exclusiveMinimum": 0, "maximum": MAX_STRENGTH}


def key_from_header(raw: str) -> str | None:
    """A header value (decoded as Latin-1 by the server) re-read as the UTF-8 it must be; ``None``
    when it is not UTF-8."""
    try:
        return raw.encode("latin-1").decode("utf-8")
    except (UnicodeEncodeError, UnicodeDecodeError):
        return None


def key_fingerprint(key: str, secret: bytes) -> str:
    """First 8 hex digits of HMAC-SHA256(secret, key): lets logs correlate requests by key
    without letting anyone who reads them test guesses (the secret is not logged)."""
    return hmac.new(secret, key.encode("utf-8"), hashlib.sha256).hexdigest()[:8]

"""What a caller may ask of the engine: method names, input limits, and :class:`Options`, the
validated choices of one call.

The service's forms and the command line build an :class:`Options` from what they were given, and
the engine's entry points take it as it is: every input is checked here, once, with one message.
Messages never contain the offending value (a watermark key must never be echoed).
"""

from __future__ import annotations

import math
import re
import unicodedata
from dataclasses import dataclass, field

import numpy as np

from core.coding import MAX_PAYLOAD_BITS
from core.errors import PayloadError
from core.tolerances import TOL

#: the embedding methods, by name (``planes``: Bors 2006 eqs. 15-20, ``ellipsoids``: eqs. 21-25)
METHODS = ("ellipsoids", "planes")
#: tried first when the caller names no method; the other one before a refusal (embed, and what
#: capacity offers): AUTO_METHOD says so to users
DEFAULT_METHOD = "ellipsoids"
AUTO_METHOD = "ellipsoids, or planes where only planes carries the payload"
DEFAULT_STRENGTH = TOL.strength
MAX_STRENGTH = 1.0
MAX_KEY_CHARS = 1024
#: a key given as bytes: at most the UTF-8 size of the longest text key
MAX_KEY_BYTES = 4 * MAX_KEY_CHARS

#: Unicode categories a key may not contain: control (Cc: NUL, newline, U+0085...), format (Cf:
#: zero-width and bidirectional marks...), line and paragraph separators (Zl, Zp), surrogates (Cs).
#: Each is invisible or reorders text: two keys that look the same could differ.
REFUSED_KEY_CATEGORIES = frozenset({"Cc", "Cf", "Zl", "Zp", "Cs"})
#: the same rule as a JSON Schema pattern: the code points of those categories in the Basic
#: Multilingual Plane (Unicode 14; surrogates cannot be sent as UTF-8 anyway).  The few format
#: characters above U+FFFF (U+110BD, U+E0001...) are refused by :func:`check_key` alone.
KEY_PATTERN = (
    "^[^\\u0000-\\u001f\\u007f-\\u009f\\u00ad\\u0600-\\u0605\\u061c\\u06dd\\u070f\\u0890\\u0891"
    "\\u08e2\\u180e\\u200b-\\u200f\\u2028-\\u202e\\u2060-\\u2064\\u2066-\\u206f\\ufeff\\ufff9-\\ufffb]*$"
)
_BITS = re.compile(r"[01]+")


def check_key(key: str | bytes) -> str | bytes:
    """The key, when it is 1 to :data:`MAX_KEY_CHARS` characters, none in :data:`REFUSED_KEY_CATEGORIES`.

    A key is used exactly as given (no trimming): a stray newline (``curl -F key=<file``) is
    refused rather than silently making a different key.  Bytes keys: 1 to :data:`MAX_KEY_BYTES`.
    """
    if isinstance(key, bytes | bytearray):
        if not 1 <= len(key) <= MAX_KEY_BYTES:
            raise PayloadError(f"a key given as bytes must be 1 to {MAX_KEY_BYTES} bytes")
        return bytes(key)
    if not isinstance(key, str) or key == "":
        raise PayloadError("a watermark key is required")
    if len(key) > MAX_KEY_CHARS:
        raise PayloadError(f"the key must be at most {MAX_KEY_CHARS} characters")
    if any(unicodedata.category(c) in REFUSED_KEY_CATEGORIES for c in key):
        raise PayloadError("the key must not contain control, format or separator characters "
                           "(newline, tab, NUL, U+0085, zero-width or bidirectional marks, U+2028...)")
    return key


def check_payload(payload: str | None) -> str | None:
    """A payload of 1 to :data:`MAX_PAYLOAD_BITS` characters ``0``/``1`` (or ``None``)."""
    if payload is None:
        return None
    if not (isinstance(payload, str) and 1 <= len(payload) <= MAX_PAYLOAD_BITS and _BITS.fullmatch(payload)):
        raise PayloadError(f"payload must be 1 to {MAX_PAYLOAD_BITS} characters, each '0' or '1'")
    return payload


def check_method(method: str | None) -> str | None:
    """One of :data:`METHODS` (or ``None``)."""
    if method is not None and method not in METHODS:
        raise PayloadError(f"method must be one of: {', '.join(METHODS)}")
    return method


def check_strength(strength: float | None) -> float | None:
    """A number in (0, :data:`MAX_STRENGTH`] (or ``None``), as a float."""
    if strength is None:
        return None
    value = float(strength)
    if not (math.isfinite(value) and 0 < value <= MAX_STRENGTH):
        raise PayloadError(f"strength must be a number in (0, {MAX_STRENGTH:g}]")
    return value


@dataclass(frozen=True)
class Options:
    """The caller's choices for one engine call, checked when the object is made (in the order
    key, payload, method, strength; the first fault raises :class:`~core.errors.PayloadError`).

    Attributes
    ----------
    key : str or bytes, optional
        The secret key (embed and detect need one).  Not shown by ``repr``.
    payload : str, optional
        Embed: the bits to hide (default: a 32-bit code derived from the key).  Detect: the
        expected payload, to get bit errors and a p-value.
    method : str, optional
        Embed and capacity: ``None`` leaves it to MeshMark (:data:`AUTO_METHOD`: :data:`DEFAULT_METHOD`
        first, the other one where only it carries the payload).  Detect: ``None`` tries every method.
    strength : float, optional
        Margin of the carriers after embedding, a fraction of the local scale;
        :data:`DEFAULT_STRENGTH` when ``None``.
    """

    key: str | bytes | None = field(default=None, repr=False)
    payload: str | None = None
    method: str | None = None
    strength: float | None = None

    def __post_init__(self) -> None:
        if self.key is not None:
            object.__setattr__(self, "key", check_key(self.key))
        check_payload(self.payload)
        check_method(self.method)
        object.__setattr__(self, "strength", check_strength(self.strength))

    @property
    def secret(self) -> str | bytes:
        """The key; :class:`~core.errors.PayloadError` when there is none."""
        if self.key is None:
            raise PayloadError("a watermark key is required")
        return self.key

    @property
    def payload_bits(self) -> np.ndarray | None:
        """The payload as a ``(n,)`` uint8 array of 0/1 (``None`` without a payload)."""
        if self.payload is None:
            return None
        return np.frombuffer(self.payload.encode("ascii"), np.uint8) - ord("0")

    @property
    def embed_method(self) -> str:
        """The method to embed with first (or to measure capacity for)."""
        return self.method or DEFAULT_METHOD

    @property
    def detect_methods(self) -> tuple[str, ...]:
        """The methods to look for."""
        return (self.method,) if self.method else METHODS

    @property
    def margin(self) -> float:
        """The strength to embed with."""
        return DEFAULT_STRENGTH if self.strength is None else self.strength

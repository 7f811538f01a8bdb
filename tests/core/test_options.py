"""core.options: every input checked once, in a fixed order, with messages that never echo it."""

from __future__ import annotations

import re
import unicodedata

import pytest

from core.errors import PayloadError
from core.options import (
    DEFAULT_STRENGTH,
    KEY_PATTERN,
    MAX_KEY_CHARS,
    METHODS,
    REFUSED_KEY_CATEGORIES,
    Options,
    check_key,
)
from core.tolerances import TOL


@pytest.mark.parametrize(("fields", "message"), [
    ({"key": ""}, "a watermark key is required"),
    ({"key": "k" * (MAX_KEY_CHARS + 1)}, f"the key must be at most {MAX_KEY_CHARS} characters"),
    ({"key": "line\n"}, "the key must not contain control, format or separator characters"),
    # control (U+0085 NEL, U+009B CSI), separator (U+2028), format (U+202E RLO, U+200B, U+E0001)
    *(({"key": f"ab{c}cd"}, "the key must not contain control") for c in
      ("\x85", "\x9b", "\u2028", "\u2029", "\u202e", "\u200b", "\ufeff", "\U000e0001")),
    ({"key": b""}, "a key given as bytes must be 1 to 4096 bytes"),
    ({"payload": ""}, "payload must be 1 to 256 characters, each '0' or '1'"),
    ({"payload": "0102"}, "payload must be 1 to 256 characters"),
    ({"payload": "1" * 257}, "payload must be 1 to 256 characters"),
    ({"method": "spheres"}, "method must be one of: ellipsoids, planes"),
    ({"strength": 0.0}, r"strength must be a number in \(0, 1\]"),
    ({"strength": float("nan")}, "strength must be a number"),
    ({"strength": 1.5}, "strength must be a number"),
])
def test_refusals(fields: dict[str, object], message: str) -> None:
    with pytest.raises(PayloadError, match=f"^{message}"):
        Options(**fields)  # type: ignore[arg-type]


def test_the_first_fault_is_reported_key_payload_method_strength() -> None:
    with pytest.raises(PayloadError, match="key"):
        Options(key="\t", payload="x", method="x", strength=-1)
    with pytest.raises(PayloadError, match="payload"):
        Options(key="k", payload="x", method="x", strength=-1)
    with pytest.raises(PayloadError, match="method"):
        Options(key="k", method="x", strength=-1)


def test_defaults_and_derived_values() -> None:
    options = Options(key="secret", payload="101")
    assert options.embed_method == "ellipsoids" and options.detect_methods == METHODS
    assert options.margin == DEFAULT_STRENGTH == TOL.strength
    assert options.payload_bits is not None and options.payload_bits.tolist() == [1, 0, 1]
    assert Options(method="planes", strength=1).margin == 1.0
    assert Options(method="planes").detect_methods == ("planes",)
    with pytest.raises(PayloadError, match="required"):
        Options().secret  # noqa: B018


def test_the_key_is_never_shown() -> None:
    options = Options(key="very secret key")
    assert "very secret" not in repr(options) and "very secret" not in str(options)
    assert check_key("é ☃") == "é ☃" and check_key(b"\x00\xff") == b"\x00\xff"


def test_key_pattern_states_the_rule_for_the_basic_plane() -> None:
    """KEY_PATTERN (the OpenAPI document's) refuses exactly the BMP characters check_key refuses."""
    pattern = re.compile(KEY_PATTERN)
    for code in range(0x10000):
        c = chr(code)
        if unicodedata.category(c) == "Cs":
            continue  # not UTF-8: refused before any key check
        refused = unicodedata.category(c) in REFUSED_KEY_CATEGORIES
        assert (pattern.fullmatch(c) is None) == refused, hex(code)

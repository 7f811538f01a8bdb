"""Mutations of file bytes, for the fuzz tests of the readers and of the upload path (and the
long fuzz runs of ``bench/``, which reuse them).

An operation is ``(name, where, blob)``: ``where`` in [0, 1] is a position relative to the current
size, ``blob`` the bytes it inserts or writes (a token that tends to matter to some parser, or
random bytes).
"""

from __future__ import annotations

#: tokens that tend to matter to a parser (counts, numbers, keywords, separators)
TOKENS = [
    b"nan",
    b"-1",
    b"0",
    b"4000000000",
    b"1e999",
    b"/",
    b"//",
    b"\r\n",
    b"\n",
    b"#",
    b"\x00",
    b" ",
    b"f",
    b"v",
    b"end_header\n",
    b"element face 3\n",
    b"255",
    b"-0",
    b"1.5",
    b"\xff",
    b'"',
    b"{",
    b"}",
    b"[",
    b"]",
    b'"uri":"../x.bin"',
    b"data:;base64,",
    b"\xff\xff\xff\xff",
    b"\x00\x00\x00\x80",
    b"glTF",
    b"MM",
    b"solid",
    b"facet",
]
OPS = ("flip", "truncate", "insert", "delete", "token", "duplicate", "int32")

Op = tuple[str, float, bytes]


def apply_ops(data: bytes, ops: list[Op]) -> bytes:
    """Apply mutation operators; ``where`` in [0, 1] is a position relative to the current size."""
    for op, where, blob in ops:
        i = min(int(where * len(data)), max(len(data) - 1, 0))
        if op == "flip" and data:
            data = data[:i] + bytes([data[i] ^ (blob[0] if blob and blob[0] else 1)]) + data[i + 1 :]
        elif op == "truncate":
            data = data[:i]
        elif op == "insert":
            data = data[:i] + blob + data[i:]
        elif op == "delete":
            data = data[:i] + data[i + max(1, len(blob)) :]
        elif op == "token":  # replace the whitespace-delimited token at i
            j = data.find(b" ", i)
            data = data[:i] + blob + (data[j:] if j >= 0 else b"")
        elif op == "duplicate":  # repeat a slice (lists, chunks, lines)
            n = 1 + len(blob) * 64
            data = data[:i] + data[i : i + n] * 4 + data[i + n :]
        elif op == "int32" and len(data) >= 4:  # overwrite a little-endian count or offset
            i = min(i, len(data) - 4)
            value = int.from_bytes((blob * 4)[:4] or b"\xff\xff\xff\xff", "little")
            data = data[:i] + value.to_bytes(4, "little") + data[i + 4 :]
    return data

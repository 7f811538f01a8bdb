"""Mutated and truncated OBJ/PLY/STL/OFF files only ever raise MeshMarkError subclasses."""

from __future__ import annotations

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from core.errors import MeshMarkError
from core.formats import read_mesh
from tests.conftest import MESHES_DIR
from tests.core.formats.test_text_formats import OBJ_CRLF, STL_ASCII, _ply_ascii, _ply_binary
from tests.core.formats.text_helpers import binary_stl

SMALL = [
    ("a.obj", OBJ_CRLF),
    ("a.ply", _ply_ascii()),
    ("a.ply", _ply_ascii("\r\n")),
    ("a.ply", _ply_binary("little", "float")),
    ("a.ply", _ply_binary("big", "double")),
    ("a.stl", STL_ASCII),
    ("a.stl", binary_stl(np.arange(18, dtype=float).reshape(2, 3, 3), header=b"solid x")),
    ("a.off", b"COFF\n# c\n4 2 0\n0 0 0 1 1 1 1\n1 0 0 1 1 1 1\n1 1 0 1 1 1 1\n0 1 0 1 1 1 1\n"
              b"3 0 1 2\n4 0 1 2 3 1 0 0\n"),
]
# real files small enough to parse many times (skipped silently when the set is absent)
REAL = [
    (n, (MESHES_DIR / n).read_bytes())
    for n in ("teapot.stl", "spot.obj", "fandisk.off", "horse.ply")
    if (MESHES_DIR / n).is_file()
]
SEEDS = SMALL + REAL

TOKENS = [b"nan", b"-1", b"0", b"4000000000", b"1e999", b"/", b"//", b"\r\n", b"\n", b"#", b"\x00",
          b" ", b"f", b"v", b"end_header\n", b"element face 3\n", b"255", b"-0", b"1.5", b"\xff"]

mutation = st.tuples(
    st.sampled_from(["flip", "truncate", "insert", "delete", "token"]),
    st.one_of(st.floats(0, 1), st.floats(0, 1).map(lambda w: w**6)),  # also near the header
    st.one_of(st.binary(min_size=1, max_size=6), st.sampled_from(TOKENS)),
)


def _mutate(data: bytes, ops: list[tuple[str, float, bytes]]) -> bytes:
    for op, where, blob in ops:
        i = int(where * len(data))
        if op == "flip" and data:
            i = min(i, len(data) - 1)
            data = data[:i] + bytes([data[i] ^ (blob[0] or 1)]) + data[i + 1 :]
        elif op == "truncate":
            data = data[:i]
        elif op == "insert":
            data = data[:i] + blob + data[i:]
        elif op == "delete":
            data = data[:i] + data[i + len(blob) :]
        else:  # replace the token at i
            j = data.find(b" ", i)
            data = data[:i] + blob + (data[j:] if j >= 0 else b"")
    return data


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, len(SEEDS) - 1), ops=st.lists(mutation, min_size=1, max_size=4))
def test_mutated_files_raise_only_meshmark_errors(seed: int, ops: list[tuple[str, float, bytes]]) -> None:
    name, original = SEEDS[seed]
    data = _mutate(original, ops)
    try:
        doc = read_mesh(data, filename=name)
    except MeshMarkError:
        return
    # whatever was accepted can be written back and read again
    new = [p.vertices * 1.001 + 1e-3 for p in doc.parts]
    out = doc.write(new)
    try:
        again = read_mesh(out, filename=name)
    except MeshMarkError:
        return
    assert (again.format, again.encoding) == (doc.format, doc.encoding)

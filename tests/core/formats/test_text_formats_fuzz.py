"""Mutated and truncated OBJ/PLY/STL/OFF files only ever raise MeshMarkError subclasses, and a file
that is accepted writes back to a file that reads back exactly as ``quantize`` predicts."""

from __future__ import annotations

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from core.errors import MeshMarkError
from core.formats import read_mesh
from tests.conftest import MESHES_DIR
from tests.core.formats.helpers import OCTAHEDRON, WRITERS, binary_stl
from tests.core.formats.test_ply_strips import _grid, _ply, _strip
from tests.core.formats.test_text_formats import OBJ_CRLF, STL_ASCII, _ply_ascii, _ply_binary
from tests.mutations import OPS, TOKENS, Op, apply_ops

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
    # triangle strips (a tristrips element, -1 between strips)
    ("s.ply", _ply(_grid(2, 3), [_strip(0, 3) + [-1] + _strip(1, 3)], "ascii")),
    ("s.ply", _ply(_grid(2, 3), [_strip(0, 3), [-1], _strip(1, 3)], "binary_little_endian")),
]
# real files small enough to parse many times (skipped silently when the set is absent)
REAL = [
    (n, (MESHES_DIR / n).read_bytes())
    for n in ("teapot.stl", "spot.obj", "fandisk.off", "horse.ply")
    if (MESHES_DIR / n).is_file()
]
# the named tiny meshes in every encoding of these formats
TINY_FILES = [(f"{OCTAHEDRON.name}.{fmt}", write(OCTAHEDRON)) for (fmt, _), write in WRITERS.items()
              if fmt in ("obj", "ply", "stl", "off")]
SEEDS = SMALL + TINY_FILES + REAL

mutation = st.tuples(
    st.sampled_from(OPS),
    st.one_of(st.floats(0, 1), st.floats(0, 1).map(lambda w: w**6)),  # also near the header
    st.one_of(st.binary(min_size=1, max_size=6), st.sampled_from(TOKENS)),
)


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, len(SEEDS) - 1), ops=st.lists(mutation, min_size=1, max_size=4))
def test_mutated_files_raise_only_meshmark_errors(seed: int, ops: list[Op]) -> None:
    name, original = SEEDS[seed]
    data = apply_ops(original, ops)
    try:
        doc = read_mesh(data, filename=name)
    except MeshMarkError:
        return
    # whatever was accepted can be written back, and reads back as quantize() said it would
    # (compared slot by slot: welding may join slots that the move made equal)
    new = [p.vertices * 0.999 for p in doc.parts]
    again = read_mesh(doc.write(new), filename=name)
    assert (again.format, again.encoding, len(again.parts)) == (doc.format, doc.encoding, len(doc.parts))
    for part, back, moved in zip(doc.parts, again.parts, new, strict=True):
        expected = doc.quantize(moved)[part.slot_to_vertex]
        assert np.array_equal(back.vertices[back.slot_to_vertex], expected)

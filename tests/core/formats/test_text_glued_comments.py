"""A "#" comment glued to a coordinate survives the rewrite of its line (fuzz finding).

``bench/fuzz_formats.py`` (seed 1, case 38980) inserted random bytes into a ``v`` line of
``rocker-arm.obj``: ``v -0.13389 0.16467 0.4955#*~...\\r...39``.  The reader strips the comment
and reads z = 0.4955, but the writer took the z token to run up to the next whitespace (the
``\\r``), so moving that vertex deleted part of the comment and the written file no longer
parsed.  Tokens now end at the comment for the writer as for the readers.
"""

from __future__ import annotations

import numpy as np
import pytest

from core.formats import read_mesh

GLUED = b"#glued \xe2\xaf\r\xcb\xb2~-,39"
CASES = [
    ("a.obj", b"v 1.5 2.5 3.5" + GLUED + b"\nv 0 1 0\nv 1 0 0 # spaced\nf 1 2 3\n"),
    ("a.off", b"OFF\n3 1 0\n1.5 2.5 3.5" + GLUED + b"\n0 1 0\n1 0 0\n3 0 1 2\n"),
    (
        "a.stl",
        b"solid t\nfacet normal 0 0 1\nouter loop\nvertex 1.5 2.5 3.5" + GLUED
        + b"\nvertex 0 1 0\nvertex 1 0 0\nendloop\nendfacet\nendsolid t\n",
    ),
    (  # the fuzz case's line
        "b.obj",
        b"v -0.13389 0.16467 0.4955#*~\xe2\xaf\xa3\xf4\x164\xbb4\x98\r\xcb\xb2~39\n"
        b"v 0 1 0\nv 1 0 0\nf 1 2 3\n",
    ),
]


@pytest.mark.parametrize(("name", "data"), CASES)
def test_glued_comment_is_kept_when_its_vertex_moves(name: str, data: bytes) -> None:
    doc = read_mesh(data, name)
    part = doc.parts[0]
    new = part.vertices * 1.25 + 0.125  # every vertex moves
    out = doc.write([new])
    comment = data[data.index(b"#") : data.index(b"\n", data.index(b"#"))]
    assert comment in out  # the whole comment, bytes after the "\r" included
    again = read_mesh(out, name).parts[0]
    assert np.array_equal(again.vertices, doc.quantize(new))
    assert np.array_equal(again.faces, part.faces)

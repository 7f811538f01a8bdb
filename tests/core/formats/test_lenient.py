"""Untidy but readable files: what is not a triangle is skipped, counted and carried through."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from core.errors import MeshFormatError
from core.formats import read_mesh
from core.pipeline import detect_file, embed_file
from tests.conftest import shared_mesh_path

OBJ = b"""# untidy
o thing
v 0 0 0
v 1 0 0
v 0 1 0
v 0 0 1
v 1 1 1
g group
f 1 2 3
f 1 2
f 4
f 2 3 3
f 1 2 4 5
l 1 2 3
p 5
f 1/1/1 3/1/1 4/1/1
"""


def test_obj_short_faces_lines_and_points_are_skipped_and_counted() -> None:
    doc = read_mesh(OBJ, "a.obj")
    part = doc.parts[0]
    # f 1 2 3, the quad (two triangles), f 1 3 4: four triangles; skipped: "f 1 2", "f 4",
    # "f 2 3 3" (two distinct corners), "l", "p"
    assert len(part.faces) == 4
    assert doc.skipped_elements == 5
    new = part.vertices.copy()
    new[part.slot_to_vertex[4]] += 0.25
    out = doc.write([new], decimals=2)
    before, after = OBJ.split(b"\n"), out.split(b"\n")
    assert [i for i, (a, b) in enumerate(zip(before, after, strict=True)) if a != b] == [6]  # "v 1 1 1"
    assert read_mesh(out, "a.obj").skipped_elements == 5


def ply_mixed(binary: bool) -> bytes:
    faces = [[0, 1, 2], [0, 1], [], [0, 2, 3, 4], [3, 3, 4]]
    verts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]], np.float32)
    fmt = "binary_little_endian" if binary else "ascii"
    head = (f"ply\nformat {fmt} 1.0\nelement vertex 5\nproperty float x\nproperty float y\n"
            "property float z\nproperty uchar red\nelement face 5\nproperty list uchar int vertex_indices\n"
            "end_header\n").encode()
    if binary:
        body = b"".join(struct.pack("<3fB", *v, 7) for v in verts)
        body += b"".join(struct.pack(f"<B{len(f)}i", len(f), *f) for f in faces)
    else:
        body = b"".join(f"{v[0]:g} {v[1]:g} {v[2]:g} 7\n".encode() for v in verts)
        body += b"".join((" ".join(map(str, [len(f), *f])) + "\n").encode() for f in faces)
    return head + body


@pytest.mark.parametrize("binary", [False, True])
def test_ply_mixed_polygons_with_short_faces(binary: bool) -> None:
    data = ply_mixed(binary)
    doc = read_mesh(data, "a.ply")
    assert len(doc.parts[0].faces) == 3  # the triangle and the quad's two
    assert doc.skipped_elements == 3  # the 2-corner face, the empty one, [3, 3, 4]
    new = doc.parts[0].vertices.copy()
    new[0] += 0.5
    out = doc.write([new])
    again = read_mesh(out, "a.ply")
    np.testing.assert_array_equal(again.parts[0].faces, doc.parts[0].faces)
    assert again.skipped_elements == 3
    assert len(out) == len(data) if binary else True


def test_off_points_and_edges_are_skipped() -> None:
    data = b"OFF\n4 4 0\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 1 2\n2 0 3\n1 3\n4 0 1 3 2\n"
    doc = read_mesh(data, "a.off")
    assert len(doc.parts[0].faces) == 3 and doc.skipped_elements == 2
    with pytest.raises(MeshFormatError):
        read_mesh(b"OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n-1 0 1 2\n", "a.off")


def test_truly_broken_files_are_still_refused() -> None:
    with pytest.raises(MeshFormatError):
        read_mesh(b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nl 1 9\nf 1 9\n", "a.obj")
    with pytest.raises(MeshFormatError):
        read_mesh(b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 x\n", "a.obj")


def test_real_mesh_with_edges_written_as_faces_embeds_and_detects() -> None:
    """spot.obj plus 300 two-corner ``f`` lines and ``l`` lines (as a CAD export writes its
    edges): embedded, the extra lines untouched, the report counts them, detected."""
    data = shared_mesh_path("spot.obj").read_bytes()
    extra = b"".join(f"f {i} {i + 1}\nl {i} {i + 2}\n".encode() for i in range(1, 301))
    untidy = data + extra
    payload = "1011001110001111"
    out = embed_file(untidy, "key", filename="spot.obj", payload=payload)
    assert out.report.skipped_elements == 600
    assert out.data.endswith(extra)
    found = detect_file(out.data, "key", filename="spot.obj")
    assert found.detected and found.payload == payload

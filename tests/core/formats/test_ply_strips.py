"""PLY files whose triangles are triangle strips (a ``tristrips`` element instead of ``face``).

Range-scan tools and Stanford's older models write them: ``igea.ply`` of alecjacobson's
common-3d-test-models (134,345 vertices, one record of strips joined by ``-1``) read as a point
cloud and was refused ("no faces").  Each test builds the strips of a grid of quads, whose
triangles are known without any strip logic.
"""

from __future__ import annotations

import struct

import numpy as np
import pytest

from core.api import detect_file, embed_file
from core.errors import MeshFormatError
from core.formats import read_mesh
from core.formats.base import strip_triangles

ROWS, COLS = 40, 60


def _grid(rows: int = ROWS, cols: int = COLS) -> np.ndarray:
    """``(rows + 1) * (cols + 1)`` vertices of a bumpy sheet, vertex ``r * (cols + 1) + c``."""
    r, c = np.meshgrid(np.arange(rows + 1), np.arange(cols + 1), indexing="ij")
    x, y = c.ravel() / cols, r.ravel() / rows
    z = 0.05 * np.sin(7 * x) * np.cos(5 * y) + 0.01 * np.sin(31 * x + 17 * y)
    return np.stack([x, y, z], axis=1)


def _expected(rows: int = ROWS, cols: int = COLS) -> np.ndarray:
    """The grid's triangles, quad by quad: ``(p, q, s)`` and ``(s, q, t)`` for the quad
    ``p = (r, c)``, ``s = (r, c + 1)``, ``q = (r + 1, c)``, ``t = (r + 1, c + 1)``."""
    w = cols + 1
    r, c = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
    p = (r * w + c).ravel()
    s, q = p + 1, p + w
    t = q + 1
    return np.concatenate([np.stack([p, q, s], 1), np.stack([s, q, t], 1)])


def _strip(row: int, cols: int = COLS) -> list[int]:
    """One row of quads as a strip: ``(r, 0), (r + 1, 0), (r, 1), (r + 1, 1), ...``."""
    w = cols + 1
    out = []
    for c in range(cols + 1):
        out += [row * w + c, (row + 1) * w + c]
    return out


def _records(layout: str) -> list[list[int]]:
    """The grid's strips as ``tristrips`` records: ``"restart"``: one record, rows joined by -1;
    ``"rows"``: a record per row; ``"joined"``: one strip, rows joined by repeated corners (the
    degenerate triangles writers use; an extra repeat where needed keeps the next row's parity)."""
    rows = [_strip(r) for r in range(ROWS)]
    if layout == "rows":
        return rows
    if layout == "restart":
        restart: list[int] = []
        for r in rows[:-1]:
            restart += r + [-1]
        return [restart + rows[-1]]
    one: list[int] = []
    for r in rows:
        if one:
            one += [one[-1], r[0]]
            if len(one) % 2:
                one.append(r[0])
        one += r
    return [one]


def _ply(vertices: np.ndarray, records: list[list[int]], fmt: str, index: str = "int") -> bytes:
    """A strip PLY; with an unsigned ``index`` type (``uint``, ``ushort``) a -1 of ``records`` is
    written as the type's largest value."""
    head = (f"ply\nformat {fmt} 1.0\ncomment strips\nelement vertex {len(vertices)}\nproperty float x\n"
            f"property float y\nproperty float z\nelement tristrips {len(records)}\n"
            f"property list int {index} vertex_indices\nend_header\n").encode()
    code = {"int": "i", "uint": "I", "ushort": "H"}[index]
    if code != "i":
        top = (1 << (8 * struct.calcsize(code))) - 1
        records = [[top if i < 0 else i for i in r] for r in records]
    if fmt == "ascii":
        lines = [" ".join(repr(float(x)) for x in v) for v in np.asarray(vertices, np.float32)]
        lines += [" ".join(map(str, [len(r), *r])) for r in records]
        return head + ("\n".join(lines) + "\n").encode()
    e = "<" if fmt == "binary_little_endian" else ">"
    body = [np.asarray(vertices, e + "f4").tobytes()]
    body += [struct.pack(f"{e}i{len(r)}{code}", len(r), *r) for r in records]
    return head + b"".join(body)


def _canonical(tri: np.ndarray) -> set[tuple[int, ...]]:
    """Triangles as a set, each rotated to start at its smallest index (orientation kept)."""
    out = set()
    for t in np.asarray(tri).tolist():
        k = t.index(min(t))
        out.add(tuple(t[k:] + t[:k]))
    return out


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian", "binary_big_endian"])
@pytest.mark.parametrize("layout", ["restart", "rows", "joined"])
def test_strips_read_as_the_grids_triangles_with_their_orientation(fmt: str, layout: str) -> None:
    v = _grid()
    doc = read_mesh(_ply(v, _records(layout), fmt), "strips.ply")
    part = doc.parts[0]
    assert len(part.vertices) == len(v)
    got = part.slot_to_vertex[np.arange(len(v))] if part.slot_to_vertex is not None else np.arange(len(v))
    # faces in the original vertex numbering (the weld keeps the order of first use here)
    back = np.empty(len(v), np.int64)
    back[got] = np.arange(len(v))
    assert _canonical(back[part.faces]) == _canonical(_expected())
    assert doc.skipped_elements == 0  # the joins' degenerate triangles are how strips are written


@pytest.mark.parametrize("fmt", ["ascii", "binary_big_endian"])
@pytest.mark.parametrize("index", ["uint", "ushort"])
def test_unsigned_strips_restart_at_the_largest_index(fmt: str, index: str) -> None:
    v = _grid()
    part = read_mesh(_ply(v, _records("restart"), fmt, index), "strips.ply").parts[0]
    back = np.empty(len(v), np.int64)
    back[part.slot_to_vertex] = np.arange(len(v))
    assert _canonical(back[part.faces]) == _canonical(_expected())


def test_strip_triangles_turns_every_other_triangle_and_restarts_at_minus_one() -> None:
    counts = np.array([7, 3])
    flat = np.array([0, 1, 2, 3, -1, 4, 5, 6, 7, 8])
    c, f, joins = strip_triangles(counts, flat)
    assert (c == 3).all() and joins == 0
    # 0 1 2 3: (0 1 2), (2 1 3); a strip "4 5" is too short; the second record "6 7 8": (6 7 8)
    assert f.reshape(-1, 3).tolist() == [[0, 1, 2], [2, 1, 3], [6, 7, 8]]


def test_a_strip_index_below_minus_one_or_past_the_vertices_is_refused() -> None:
    v = _grid(2, 2)
    with pytest.raises(MeshFormatError):
        read_mesh(_ply(v, [[0, 3, 1, -2, 4]], "binary_little_endian"), "bad.ply")
    with pytest.raises(MeshFormatError):
        read_mesh(_ply(v, [[0, 3, 1, 4, len(v)]], "ascii"), "bad.ply")
    with pytest.raises(MeshFormatError):
        read_mesh(_ply(v, [[0, 3, 1, -2, 4]], "ascii"), "bad.ply")


def test_a_strip_file_embeds_detects_and_keeps_its_strips_byte_for_byte() -> None:
    v = _grid()
    data = _ply(v, _records("restart"), "binary_little_endian")
    out = embed_file(data, "strip-key", filename="s.ply", payload="1011")
    assert len(out.data) == len(data)
    head = data.index(b"end_header\n") + len(b"end_header\n")
    vend = head + 12 * len(v)
    assert out.data[:head] == data[:head] and out.data[vend:] == data[vend:]  # header and strips
    moved = np.frombuffer(out.data[head:vend], "<f4") != np.frombuffer(data[head:vend], "<f4")
    assert moved.any()
    found = detect_file(out.data, "strip-key", filename="s.ply")
    assert found.detected and found.payload == "1011"
    assert not detect_file(data, "strip-key", filename="s.ply").detected


def _faces_and_strips(vertices: np.ndarray, faces: np.ndarray, strip: list[int]) -> bytes:
    """An ASCII PLY with a ``face`` element of ``faces`` (which may be empty) and a ``tristrips``
    element of one record, ``strip``."""
    head = (f"ply\nformat ascii 1.0\nelement vertex {len(vertices)}\nproperty float x\nproperty float y\n"
            f"property float z\nelement face {len(faces)}\nproperty list uchar int vertex_indices\n"
            "element tristrips 1\nproperty list int int vertex_indices\nend_header\n")
    lines = [" ".join(repr(float(x)) for x in p) for p in vertices]
    lines += [f"3 {a} {b} {c}" for a, b, c in np.asarray(faces).tolist()]
    lines.append(" ".join(map(str, [len(strip), *strip])))
    return (head + "\n".join(lines) + "\n").encode()


def test_a_face_element_wins_over_strips() -> None:
    v = _grid(2, 2)
    faces = _expected(2, 2)
    doc = read_mesh(_faces_and_strips(v, faces, [0, 3, 1, 4]), "both.ply")
    assert len(doc.parts[0].faces) == len(faces)


def test_strips_are_read_beside_an_empty_face_element() -> None:
    v = _grid(2, 2)
    strip = _strip(0, 2) + [-1] + _strip(1, 2)
    part = read_mesh(_faces_and_strips(v, np.zeros((0, 3), np.int64), strip), "empty-faces.ply").parts[0]
    back = np.empty(len(v), np.int64)
    back[part.slot_to_vertex] = np.arange(len(v))
    assert _canonical(back[part.faces]) == _canonical(_expected(2, 2))

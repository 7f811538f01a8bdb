"""3D Studio reader/writer: sink.3ds, synthetic files, hostile files and fuzzing."""

from __future__ import annotations

import os
import struct
import time
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from core.errors import DegenerateMeshError, LimitExceededError, MeshFormatError, MeshMarkError
from core.formats import DEFAULT_LIMITS, FORMATS, Limits, tds
from tests.conftest import MESHES_DIR, shared_mesh_path
from tests.core.formats.helpers import chunk, make_3ds, trimesh_chunk

FUZZ_EXAMPLES = int(os.environ.get("MESHMARK_FUZZ_EXAMPLES", "100"))

CUBE_V = np.array(
    [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], dtype="<f4"
)
CUBE_F = np.array(
    [[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
     [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]]
)


def small_3ds() -> bytes:
    # "box" repeats vertex 0 as slot 8 (a UV seam): welded to 8 vertices, 9 slots
    v = np.vstack([CUBE_V, CUBE_V[:1]])
    f = CUBE_F.copy()
    f[0, 0] = 8
    tri = np.array([[0, 1, 2]])
    return make_3ds([
        ("box", trimesh_chunk(v, f)),
        ("light", chunk(0x4600, b"\0" * 12)),  # a light: no mesh
        ("tri", trimesh_chunk(CUBE_V[:3] + 5, tri)),
    ])


def read(data: bytes, limits: Limits = DEFAULT_LIMITS) -> tds.TdsDocument:
    doc = tds.read(data, limits, "3ds")
    assert isinstance(doc, tds.TdsDocument)
    return doc


def chunk_offsets(data: bytes) -> list[tuple[int, int]]:
    """(id, offset) of every chunk on the mesh path, found by an independent minimal walk."""
    out: list[tuple[int, int]] = []

    def walk(start: int, end: int) -> None:
        while start < end:
            cid, length = struct.unpack_from("<HI", data, start)
            out.append((cid, start))
            body = start + 6
            if cid in (tds.MAIN, tds.EDITOR, tds.TRIMESH):
                walk(body, start + length)
            elif cid == tds.OBJECT:
                walk(data.index(b"\0", body) + 1, start + length)
            elif cid == tds.FACES:
                walk(body + 2 + 8 * struct.unpack_from("<H", data, body)[0], start + length)
            start += length

    walk(0, len(data))
    return out


def vertex_offsets(data: bytes) -> list[np.ndarray]:
    """Byte offset of every stored vertex of each mesh."""
    out = []
    for cid, at in chunk_offsets(data):
        if cid == tds.VERTICES:
            out.append(at + 8 + 12 * np.arange(struct.unpack_from("<H", data, at + 6)[0]))
    return out


def _offset_of(data: bytes, cid: int) -> int:
    """Offset of the first chunk with id ``cid``."""
    return next(at for c, at in chunk_offsets(data) if c == cid)


def move_some(doc: tds.TdsDocument, rng: np.random.Generator) -> list[np.ndarray]:
    new = []
    for part in doc.parts:
        v = part.vertices.copy()
        idx = rng.choice(len(v), max(1, len(v) // 20), replace=False)
        v[idx] += rng.normal(0.0, float(np.ptp(v, axis=0).max()) * 1e-3, (len(idx), 3))
        new.append(v)
    return new


def assert_patch_confined(doc: tds.TdsDocument, data: bytes, new: list[np.ndarray]) -> bytes:
    out = doc.write(new)
    assert len(out) == len(data)
    changed = np.flatnonzero(np.frombuffer(out, np.uint8) != np.frombuffer(data, np.uint8))
    allowed = []
    for part, v, offsets in zip(doc.parts, new, vertex_offsets(data), strict=True):
        moved = np.flatnonzero(np.any(v != part.vertices, axis=1))
        sel = offsets[np.isin(part.slot_to_vertex, moved)]
        allowed.append((sel[:, None] + np.arange(12)).ravel())
    assert changed.size > 0 and np.isin(changed, np.concatenate(allowed)).all()
    again = read(out)
    assert [p.name for p in again.parts] == [p.name for p in doc.parts]
    for part, part2, v in zip(doc.parts, again.parts, new, strict=True):
        np.testing.assert_array_equal(part2.faces, part.faces)
        np.testing.assert_array_equal(part2.slot_to_vertex, part.slot_to_vertex)
        np.testing.assert_array_equal(part2.vertices, doc.quantize(v))
    return out


# ---------------------------------------------------------------------------- real file


def test_sink_counts() -> None:
    data = shared_mesh_path("sink.3ds").read_bytes()
    assert tds.sniff(data, "3ds")
    doc = read(data)
    assert (doc.format, doc.encoding, FORMATS[doc.format].extension) == ("3ds", "binary", "3ds")
    assert doc.storage_dtype == np.float32
    got = [(p.name, len(p.slot_to_vertex), len(p.vertices), len(p.faces)) for p in doc.parts]
    assert got == [
        ("bar", 396, 396, 636), ("faucet", 174, 168, 265), ("fhan", 74, 74, 115), ("fbase", 40, 40, 52),
    ]
    assert sum(len(p.slot_to_vertex) for p in doc.parts) == 684
    assert sum(len(p.faces) for p in doc.parts) == 1068
    # 674 unique positions among referenced vertices over the whole file (the README count);
    # "bar" has 4 unreferenced vertices, which welding keeps (per part: 396 + 168 + 74 + 40 = 678)
    used = np.concatenate([p.vertices[np.unique(p.faces)] for p in doc.parts])
    assert len(np.unique(used, axis=0)) == 674


def test_sink_patch_confined() -> None:
    data = shared_mesh_path("sink.3ds").read_bytes()
    doc = read(data)
    assert_patch_confined(doc, data, move_some(doc, np.random.default_rng(11)))


# ---------------------------------------------------------------------------- synthetic


def test_small_roundtrip_and_weld() -> None:
    data = small_3ds()
    doc = read(data)
    assert [(p.name, len(p.slot_to_vertex), len(p.vertices), len(p.faces)) for p in doc.parts] == [
        ("box", 9, 8, 12), ("tri", 3, 3, 1),
    ]
    np.testing.assert_array_equal(doc.parts[0].slot_to_vertex, [0, 1, 2, 3, 4, 5, 6, 7, 0])
    assert doc.write([p.vertices.copy() for p in doc.parts]) == data
    new = [p.vertices.copy() for p in doc.parts]
    new[0][0] += 0.125  # both slots 0 and 8 are rewritten
    new[1][2] -= 0.5
    out = assert_patch_confined(doc, data, new)
    xyz = np.frombuffer(out, "<f4", 27, vertex_offsets(data)[0][0]).reshape(9, 3)
    np.testing.assert_array_equal(xyz[8], xyz[0])


def test_sniff() -> None:
    data = small_3ds()
    assert tds.sniff(data, "3ds")
    assert tds.sniff(data[:40], "3ds")  # truncated: claimed to report the truncation
    assert not tds.sniff(b"MM\x00\x00\x00\x01 some text file", "3ds")
    assert not tds.sniff(b"glTF\x02\x00\x00\x00", "3ds")
    assert not tds.sniff(b"MM", "3ds")


def test_no_mesh() -> None:
    with pytest.raises(DegenerateMeshError):
        read(make_3ds([("light", chunk(0x4600, b"\0" * 12))]))
    # vertices but no faces: nothing for the engine either
    vl = chunk(tds.VERTICES, struct.pack("<H", 3) + CUBE_V[:3].tobytes())
    with pytest.raises(DegenerateMeshError):
        read(make_3ds([("pts", chunk(tds.TRIMESH, vl))]))


# ---------------------------------------------------------------------------- hostile input


def fails_fast(data: bytes, exc: type[Exception] = MeshFormatError, limits: Limits = DEFAULT_LIMITS) -> str:
    start = time.perf_counter()
    with pytest.raises(exc) as info:
        tds.read(data, limits, "3ds")
    assert time.perf_counter() - start < 1.0
    return str(info.value)


def test_truncated() -> None:
    data = small_3ds()
    assert "truncated" in fails_fast(data[:-1])
    for cut in range(0, len(data), 7):
        fails_fast(data[:cut], MeshMarkError)


def test_truncated_sink() -> None:
    data = shared_mesh_path("sink.3ds").read_bytes()
    for cut in (5, 16, 500, len(data) // 2, len(data) - 1):
        assert "truncated" in fails_fast(data[:cut])


@pytest.mark.parametrize("cid", [tds.VERTICES, tds.FACES, tds.TRIMESH, tds.OBJECT, tds.EDITOR, 0x4130])
@pytest.mark.parametrize("length", [0, 3, 10**6, 2**32 - 1])
def test_chunk_length_beyond_parent(cid: int, length: int) -> None:
    data = bytearray(small_3ds())
    struct.pack_into("<I", data, _offset_of(bytes(data), cid) + 2, length)
    fails_fast(bytes(data))


def test_vertex_count_beyond_chunk() -> None:
    data = bytearray(small_3ds())
    struct.pack_into("<H", data, _offset_of(bytes(data), tds.VERTICES) + 6, 0xFFFF)
    assert "vertex count 65535 runs past its chunk" in fails_fast(bytes(data))


def test_face_count_beyond_chunk() -> None:
    data = bytearray(small_3ds())
    struct.pack_into("<H", data, _offset_of(bytes(data), tds.FACES) + 6, 5000)
    assert "face count" in fails_fast(bytes(data))


def test_face_index_out_of_range() -> None:
    data = bytearray(small_3ds())
    struct.pack_into("<H", data, _offset_of(bytes(data), tds.FACES) + 8, 9)
    assert "vertex count 9" in fails_fast(bytes(data))


def test_other_malformations() -> None:
    fails_fast(b"MM\x04\x00\x00\x00")  # main chunk shorter than its header
    fails_fast(b"\x02\x00\x06\x00\x00\x00")  # not a main chunk
    data = bytearray(make_3ds([("box", trimesh_chunk(CUBE_V, CUBE_F))]))
    at = _offset_of(bytes(data), tds.OBJECT)
    data[at + 6 : at + 10] = b"boxx"  # overwrite the NUL: name runs into the mesh chunk
    fails_fast(bytes(data), MeshMarkError)
    two_lists = chunk(tds.TRIMESH, trimesh_chunk(CUBE_V, CUBE_F)[6:] * 2)
    assert "several" in fails_fast(make_3ds([("twice", two_lists)]))
    short_matrix = chunk(tds.TRIMESH, trimesh_chunk(CUBE_V, CUBE_F)[6:] + chunk(tds.MATRIX, b"\0" * 8))
    fails_fast(make_3ds([("m", short_matrix)]))
    faces_only = chunk(tds.TRIMESH, chunk(tds.FACES, struct.pack("<H", 1) + b"\0" * 8))
    assert "no vertex list" in fails_fast(make_3ds([("f", faces_only)]))
    for bits in (0x7FC00000, 0x7F800001, 0xFFFF0000, 0x7F800000):  # quiet NaN, signalling NaN, -NaN, +Inf
        bad = CUBE_V.copy()
        bad.view("<u4")[3, 1] = bits
        assert "non-finite" in fails_fast(make_3ds([("nan", trimesh_chunk(bad, CUBE_F))]))


@pytest.mark.parametrize(
    "limits", [Limits(max_vertices=10), Limits(max_faces=12), Limits(max_meshes=1)]
)
def test_limits(limits: Limits) -> None:
    fails_fast(small_3ds(), LimitExceededError, limits)


# ---------------------------------------------------------------------------- fuzzing

_BASES = [small_3ds()]
if (MESHES_DIR / "sink.3ds").is_file():
    _BASES.append((MESHES_DIR / "sink.3ds").read_bytes())


@settings(max_examples=FUZZ_EXAMPLES, deadline=None)
@given(
    base=st.sampled_from(_BASES),
    ops=st.lists(
        st.tuples(
            st.sampled_from(["cut", "byte", "u16", "u32"]),
            st.floats(0, 1),
            st.integers(0, 255),
            st.sampled_from([0, 1, 5, 6, 7, 0x4D4D, 0x4110, 0xFFFF, 0x7FFFFFFF, 0xFFFFFFFF]),
        ),
        min_size=1,
        max_size=4,
    ),
)
def test_fuzz(base: bytes, ops: list[tuple[str, float, int, int]]) -> None:
    buf = bytearray(base)
    for op, where, byte, word in ops:
        at = min(int(where * len(buf)), max(len(buf) - 1, 0))
        if op == "cut":
            del buf[at:]
        elif op == "byte" and buf:
            buf[at] = byte
        elif op == "u16" and len(buf) >= 2:
            struct.pack_into("<H", buf, min(at, len(buf) - 2), word & 0xFFFF)
        elif op == "u32" and len(buf) >= 4:
            struct.pack_into("<I", buf, min(at, len(buf) - 4), word)
    data = bytes(buf)
    tds.sniff(data, "3ds")
    try:
        doc = tds.read(data, DEFAULT_LIMITS, "3ds")
    except MeshMarkError:
        return
    out: Any = doc.write([p.vertices + 1e-3 for p in doc.parts])
    tds.read(out, DEFAULT_LIMITS, "3ds")

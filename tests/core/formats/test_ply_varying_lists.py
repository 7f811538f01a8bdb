"""Binary PLY elements whose list lengths change from record to record (fuzz finding).

``bench/fuzz_formats.py`` (seed 1, case 74204) turned ``turbineblade.ply``'s face list type
``list uchar int`` into ``list uchar float64``: the 199,034 face records then have random
lengths, and the walk, which handled every run of equal lengths with several numpy calls, took
1.7-5 s (a hang under load) before failing.  Mixed triangles and quads, a legitimate file, cost
the same ~5 us per face.  Runs shorter than 32 records are now scanned record by record in
batches, and every binary element with a list property counts against the faces limit.
"""

from __future__ import annotations

import struct

import numpy as np
import pytest

from core.errors import LimitExceededError, MeshFormatError
from core.formats import Limits, ply, read_mesh
from tests.conftest import shared_mesh_path

NV = 500


def _polygons(n: int) -> list[np.ndarray]:
    """``n`` random triangles and quads of distinct vertices."""
    rng = np.random.default_rng(3)
    return [rng.integers(0, NV - 4) + np.arange(s) for s in rng.choice([3, 4], n)]


def _mixed(endian: str = "<", n_faces: int = 20_000, vertex_list: bool = False, n_junk: int = 3) -> bytes:
    """Binary PLY of random triangles and quads; with ``vertex_list``, a varying list between x and y."""
    nv = NV
    head = f"ply\nformat binary_{'little' if endian == '<' else 'big'}_endian 1.0\nelement vertex {nv}\n"
    head += "property float x\n" + ("property list uchar short extra\n" if vertex_list else "")
    head += "property float y\nproperty float z\n"
    head += f"element face {n_faces}\nproperty list uchar int vertex_indices\nproperty uchar flags\n"
    head += f"element junk {n_junk}\nproperty list ushort uchar stuff\nend_header\n"
    out = [head.encode()]
    for i in range(nv):
        out.append(struct.pack(endian + "f", i / 7))
        if vertex_list:
            k = i % 3
            out.append(struct.pack(f"{endian}B{k}h", k, *range(k)))
        out.append(struct.pack(endian + "ff", -i / 3, i / 11))
    for idx in _polygons(n_faces):
        out.append(struct.pack(f"{endian}B{len(idx)}iB", len(idx), *idx, 7))
    for j in range(n_junk):
        k = j % 3
        out.append(struct.pack(f"{endian}H{k}B", k, *range(k)))
    return b"".join(out)


def _ascii_twin(data: bytes) -> bytes:
    """The same mesh as ASCII PLY, from what the binary reader returned (faces are triangulated)."""
    part = read_mesh(data, "a.ply").parts[0]
    v, f = part.vertices, part.faces
    head = f"ply\nformat ascii 1.0\nelement vertex {len(v)}\nproperty float x\nproperty float y\n"
    head += f"property float z\nelement face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n"
    lines = [f"{x!r} {y!r} {z!r}" for x, y, z in v.tolist()] + [f"3 {a} {b} {c}" for a, b, c in f.tolist()]
    return (head + "\n".join(lines) + "\n").encode()


@pytest.mark.parametrize("endian", ["<", ">"])
@pytest.mark.parametrize("vertex_list", [False, True])
def test_varying_lists_read_and_write(endian: str, vertex_list: bool) -> None:
    data = _mixed(endian, 6_000, vertex_list)
    doc = read_mesh(data, "a.ply")
    part = doc.parts[0]
    assert np.array_equal(part.vertices[:, 0], (np.arange(NV) / 7).astype(np.float32))
    assert np.array_equal(part.vertices[:, 1], (-np.arange(NV) / 3).astype(np.float32))
    # the faces the records hold, quads fan-triangulated
    tris = [[idx[0], idx[k + 1], idx[k + 2]] for idx in _polygons(6_000) for k in range(len(idx) - 2)]
    assert np.array_equal(part.faces, part.slot_to_vertex[np.array(tris)])
    # write: only the moved coordinates change, and they read back
    new = part.vertices.copy()
    new[::3] += 0.5
    out = doc.write([new])
    assert len(out) == len(data)
    again = read_mesh(out, "a.ply").parts[0]
    assert np.array_equal(again.vertices, doc.quantize(new)) and np.array_equal(again.faces, part.faces)
    changed = np.flatnonzero(np.frombuffer(out, np.uint8) != np.frombuffer(data, np.uint8))
    assert changed.size <= 3 * 4 * len(new[::3])


def test_varying_lists_are_scanned_in_batches() -> None:
    data = _mixed("<", 50_000)
    _encoding, elements, body = ply._parse_header(data)
    vertex, face = elements[0], elements[1]
    pos = body + vertex.count * 12
    items = list(ply._runs(data, pos, face, "<"))
    # one item per run of equal lengths used to be yielded: ~25,000 here
    assert len(items) < 50
    assert sum(len(i.offsets) if isinstance(i, ply._Batch) else len(i[2]) for i in items) == 50_000
    assert np.array_equal(
        read_mesh(_ascii_twin(data), "b.ply").parts[0].faces, read_mesh(data, "a.ply").parts[0].faces
    )


def test_list_elements_count_against_the_faces_limit() -> None:
    data = _mixed("<", 100, n_junk=5_000)  # at most 200 triangles
    read_mesh(data, "a.ply", Limits(max_faces=5_100))  # 100 faces + 5,000 junk records
    with pytest.raises(LimitExceededError):
        read_mesh(data, "a.ply", Limits(max_faces=5_099))


def test_fuzz_case_turbineblade_float64_face_list() -> None:
    data = shared_mesh_path("turbineblade.ply").read_bytes()
    old, new = b"property list uchar int vertex_indices", b"property list uchar float64 vertex_indices"
    bad = data.replace(old, new, 1)
    assert bad != data
    with pytest.raises(MeshFormatError):
        read_mesh(bad, "turbineblade.ply")
    _encoding, elements, body = ply._parse_header(bad)
    face = next(e for e in elements if e.name == "face")
    pos = body + elements[0].count * elements[0].min_size()
    # the 199,034 records (most of them empty lists) are walked in a few dozen batches
    assert len(list(ply._runs(bad, pos, face, "<"))) < 100

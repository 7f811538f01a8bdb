"""OBJ, PLY, STL and OFF: real files, small synthetic files of every encoding, malformed input."""

from __future__ import annotations

import struct
import time
import tracemalloc

import numpy as np
import pytest

from core.errors import LimitExceededError, MeshFormatError, MeshMarkError, UnsupportedFormatError
from core.formats import FORMATS, Limits, detect_format, obj, off, ply, read_mesh, stl
from core.formats._text import format_coord, round_like_text
from tests.conftest import shared_mesh_path
from tests.core.formats.helpers import binary_stl
from tests.core.formats.text_helpers import (
    allowed_binary_bytes,
    assert_text_diff,
    coord_tokens,
    move_some,
    moved_slot_mask,
    reread,
    vertex_lines,
)

# file: format, encoding, stored vertex slots, welded vertices, referenced vertices, triangles
SHARED = {
    "teapot.stl": ("stl", "binary", 2682, 480, 480, 894),
    "spot.obj": ("obj", "ascii", 2930, 2930, 2930, 5856),
    "decimated-max.obj": ("obj", "ascii", 5272, 5272, 5272, 10540),
    "fandisk.off": ("off", "ascii", 7229, 7229, 7229, 14454),
    "rocker-arm.obj": ("obj", "ascii", 10044, 10044, 10044, 20088),
    # beetle: its 2 unreferenced vertices repeat referenced positions, so they weld away
    "beetle.off": ("off", "ascii", 19887, 19885, 19885, 38656),
    # bun_zipper: welding keeps its 1,113 unreferenced vertices (slot_to_vertex covers every slot)
    "bun_zipper.ply": ("ply", "ascii", 35947, 35947, 34834, 69451),
    "armadillo.obj": ("obj", "ascii", 43243, 43243, 43243, 86482),
    "horse.ply": ("ply", "binary_big_endian", 48485, 48485, 48485, 96966),
    "dragon.ply": ("ply", "binary_little_endian", 50000, 50000, 50000, 100000),
    "turbineblade.ply": ("ply", "binary_little_endian", 99519, 99519, 99519, 199034),
}
MEDIA = {"obj": "model/obj", "ply": "application/x-ply", "stl": "model/stl", "off": "application/off"}


# ---------------------------------------------------------------------------------------------
# real files


@pytest.mark.parametrize("name", list(SHARED))
def test_shared_read_write_reread(name: str) -> None:
    """Counts match the table; moving ~1 % of the vertices changes only their coordinate
    tokens/bytes; a second read gives the same faces and ``doc.quantize(new)``."""
    data = shared_mesh_path(name).read_bytes()
    fmt, encoding, slots, welded, referenced, triangles = SHARED[name]
    assert detect_format(data, name) == fmt
    doc = read_mesh(data, filename=name)
    part = doc.parts[0]
    spec = FORMATS[doc.format]
    assert (doc.format, doc.encoding, spec.extension, spec.media_type) == (fmt, encoding, fmt, MEDIA[fmt])
    assert len(doc.parts) == 1
    assert part.slot_to_vertex.shape == (slots,)
    assert part.vertices.shape == (welded, 3)
    assert np.unique(part.faces).size == referenced
    assert part.faces.shape == (triangles, 3)
    assert part.faces.dtype == np.int64 and part.vertices.dtype == np.float64
    if encoding == "ascii":
        assert doc.storage_dtype is None
    else:
        assert doc.storage_dtype == np.float32 and doc.decimals is None
    # the welded vertices are the stored positions
    assert np.array_equal(np.unique(part.slot_to_vertex), np.arange(welded))

    new, sel = move_some(doc, 0.01, seed=len(name))
    out = doc.write([new])
    slot_moved = np.flatnonzero(moved_slot_mask(doc, sel))
    if encoding == "ascii":
        lines = vertex_lines(fmt, data)
        assert len(lines) == slots
        assert_text_diff(data, out, {lines[i] for i in slot_moved}, coord_tokens(fmt))
    else:
        assert len(out) == len(data)
        a, b = np.frombuffer(data, np.uint8), np.frombuffer(out, np.uint8)
        changed = np.flatnonzero(a != b)
        assert changed.size > 0
        assert np.isin(changed, allowed_binary_bytes(fmt, data, slot_moved)).all()

    again = reread(out, name)
    assert np.array_equal(again.parts[0].faces, part.faces)
    assert np.array_equal(again.parts[0].slot_to_vertex, part.slot_to_vertex)
    assert np.array_equal(again.parts[0].vertices, doc.quantize(new))
    # unmoved vertices are bit-identical
    keep = np.ones(welded, bool)
    keep[sel] = False
    assert np.array_equal(again.parts[0].vertices[keep], part.vertices[keep])
    # nothing moved: the very same bytes
    assert doc.write([part.vertices.copy()]) == data


def test_shared_text_with_explicit_decimals() -> None:
    """Printing with an explicit number of decimals re-reads as ``quantize(new, decimals)``."""
    data = shared_mesh_path("decimated-max.obj").read_bytes()
    doc = obj.read(data, Limits(), "obj")
    assert doc.decimals == 19
    new, _ = move_some(doc, 0.05, seed=3)
    for d in (3, 6, 12, 15, 17):
        out = doc.write([new], decimals=d)
        assert np.array_equal(obj.read(out, Limits(), "obj").parts[0].vertices, doc.quantize(new, d))


def test_shared_truncated_binary_ply() -> None:
    data = shared_mesh_path("dragon.ply").read_bytes()
    for cut in (1, 13, 1000, len(data) // 2):
        with pytest.raises(MeshFormatError):
            ply.read(data[:-cut], Limits(), "ply")


def test_text_memory_is_bounded() -> None:
    """Peak traced memory of reading an ASCII PLY stays a few times the file size."""
    data = shared_mesh_path("bun_zipper.ply").read_bytes()
    ply.read(data, Limits(), "ply")
    tracemalloc.start()
    try:
        ply.read(data, Limits(), "ply")
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 8 * len(data)


# ---------------------------------------------------------------------------------------------
# printing and quantize


def test_round_like_text_matches_format_and_parse() -> None:
    rng = np.random.default_rng(7)
    for d in range(0, 24):
        x = rng.uniform(-1, 1, 3000) * 10.0 ** rng.integers(-8, 8, 3000)
        k = rng.integers(-(10 ** min(d + 3, 15)), 10 ** min(d + 3, 15), 3000)
        ties = (k + 0.5) / 10.0**d
        x = np.concatenate([x, ties, np.nextafter(ties, np.inf), np.nextafter(ties, -np.inf),
                            [2.675, 0.125, -0.0, 1e300, 5e-324, 0.5, 1.5]])
        expect = np.array([float(format_coord(t, d)) for t in x])
        assert np.array_equal(round_like_text(x, d), expect), d
    # numpy's round disagrees at this classic tie; the text rounding does not
    assert np.round(2.675, 2) != float(f"{2.675:.2f}") == round_like_text(np.array([2.675]), 2)[0]


def test_quantize_equals_reread_near_ties() -> None:
    """A value that ``np.round`` rounds the other way is quantized as the text re-reads."""
    data = b"v 0.000000 0.000000 0.000000\nv 1.000000 0 0\nv 0 1.000000 0\nf 1 2 3\n"
    doc = obj.read(data, Limits(), "obj")
    assert doc.decimals == 6
    new = doc.parts[0].vertices.copy()
    new[0] = [2.675, 1.0000005, -3.0000015]
    for d in (2, 6, None):
        out = doc.write([new], decimals=d)
        assert np.array_equal(obj.read(out, Limits(), "obj").parts[0].vertices, doc.quantize(new, d))
    out = doc.write([new])
    assert out.split(b"\n")[0] == b"v 2.675000 1.000001 -3.000002"  # printed with 6 decimals


def test_exponent_notation_prints_shortest_repr() -> None:
    data = b"OFF\n3 1 0\n1e-3 0 0\n0 1 0\n0 0 1.5E+00\n3 0 1 2\n"
    doc = off.read(data, Limits(), "off")
    assert doc.decimals is None
    new = doc.parts[0].vertices.copy()
    new[0] = [0.1 + 0.2, 1e-20, -0.0]
    out = doc.write([new])
    assert out.split(b"\n")[2] == b"0.30000000000000004 1e-20 -0.0"
    assert np.array_equal(off.read(out, Limits(), "off").parts[0].vertices, doc.quantize(new))


# ---------------------------------------------------------------------------------------------
# OBJ

OBJ_CRLF = (
    b"# exported\r\nmtllib scene.mtl\r\no Thing\r\n"
    b"v 0 0 0 1.0 0.5 0.25\r\nv 1 0 0\r\nv  1 1 0\r\nv 0 1 0 1\r\n"
    b"vt 0 0\r\nvt 1 0\r\nvt 1 1\r\nvt 0 1\r\nvn 0 0 1\r\n"
    b"usemtl red\r\ng grp\r\ns off\r\n"
    b"f 1 2 3\r\nf 1/1 3/3 4/4\r\nf 1//1 2//1 4//1 # comment\r\nf 1/1/1 2/2/1 3/3/1 4/4/1\r\n"
    b"f -4 -3 -1\r\n"
    b"v 0.5 0.5 1\r\nf -1 1 2\r\nf\t5/1/1\t3/3/1  4/4/1\r\n"
)


def test_obj_all_index_forms_negative_quads_crlf() -> None:
    assert obj.sniff(OBJ_CRLF, "obj") and detect_format(OBJ_CRLF, "a.obj") == "obj"
    doc = obj.read(OBJ_CRLF, Limits(), "obj")
    part = doc.parts[0]
    assert part.name == "Thing" and doc.mtllibs == ["scene.mtl"] and doc.decimals == 1
    assert part.vertices.tolist() == [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 0.5, 1]]
    assert part.faces.tolist() == [
        [0, 1, 2], [0, 2, 3], [0, 1, 3], [0, 1, 2], [0, 2, 3], [0, 1, 3], [4, 0, 1], [4, 2, 3],
    ]
    new = part.vertices.copy()
    new[0] += 0.25
    new[4] -= 0.5
    out = doc.write([new])
    assert out.split(b"\r\n")[3] == b"v 0.2 0.2 0.2 1.0 0.5 0.25"  # colour tokens kept, 1 decimal
    assert out.split(b"\r\n")[20] == b"v 0.0 0.0 0.5"
    assert_text_diff(OBJ_CRLF, out, {3, 20}, (1, 2, 3))
    again = obj.read(out, Limits(), "obj")
    assert np.array_equal(again.parts[0].vertices, doc.quantize(new))
    assert np.array_equal(again.parts[0].faces, part.faces)


def test_obj_without_o_and_without_final_newline() -> None:
    doc = obj.read(b"v 0 0 0\nv 1 0 0\nv 0 1 0\ng x\nf 1 2 3", Limits(), "obj")
    assert doc.parts[0].name == "mesh0" and doc.parts[0].faces.tolist() == [[0, 1, 2]]
    new = doc.parts[0].vertices + 1
    assert doc.write([new]) == b"v 1 1 1\nv 2 1 1\nv 1 2 1\ng x\nf 1 2 3"


def test_obj_bom_and_indented_statements() -> None:
    data = b"\xef\xbb\xbfv 0 0 0\n  v 1 0 0\n\tv 0 1 0\n   f 1 2 3\n"
    doc = read_mesh(data, filename="bom.obj")
    assert doc.parts[0].vertices.shape == (3, 3) and doc.parts[0].faces.tolist() == [[0, 1, 2]]
    new = doc.parts[0].vertices + 2
    assert doc.write([new]) == b"\xef\xbb\xbfv 2 2 2\n  v 3 2 2\n\tv 2 3 2\n   f 1 2 3\n"


def test_obj_sniff() -> None:
    assert obj.sniff(b"# Blender\n\nmtllib a.mtl\no Cube\nv 1 1 1\n", "obj")
    assert obj.sniff(b"\xef\xbb\xbfv 1 2 3\n", "obj")
    assert not obj.sniff(b"# only comments\n# here\n", "obj")
    assert not obj.sniff(b"hello world\nv 1 2 3\n", "obj")
    assert not obj.sniff(b"\xff\xd8\xff\xe0\x00\x10JFIF\x00", "obj")
    assert not obj.sniff(b"PK\x03\x04\x14\x00\x00\x00v 1 2 3", "obj")


# ---------------------------------------------------------------------------------------------
# PLY

PLY_HEADER = """ply
format {fmt} 1.0
comment made by a test
obj_info synthetic
element camera 1
property float view_px
property float view_py
element vertex 5
property uchar red
property {ctype} x
property {ctype} y
property {ctype} z
property uchar green
property float confidence
element face 3
property list {count} {index} vertex_indices
property int flags
element material 2
property list uchar char name
end_header
"""
VERTS = [(10, 0.0, 0.0, 0.0, 20, 0.5), (11, 1.0, 0.0, 0.0, 21, 0.25), (12, 1.0, 1.0, 0.0, 22, 1.0),
         (13, 0.0, 1.0, 0.0, 23, 0.75), (14, 0.5, 0.5, 1.0, 24, 0.125)]
FACES = [([0, 1, 2], 7), ([1, 2, 3, 4], -8), ([0, 2, 4], 9)]
TRIS = [[0, 1, 2], [1, 2, 3], [1, 3, 4], [0, 2, 4]]


def _ply_binary(endian: str, ctype: str = "double", count: str = "ushort", index: str = "uint") -> bytes:
    e = "<" if endian == "little" else ">"
    codes = {"float": "f", "double": "d", "ushort": "H", "uchar": "B", "uint": "I", "int": "i", "short": "h"}
    c = codes[ctype]
    out = [PLY_HEADER.format(fmt=f"binary_{endian}_endian", ctype=ctype, count=count, index=index).encode()]
    out.append(struct.pack(e + "ff", 1.5, -2.5))
    for r, x, y, z, g, conf in VERTS:
        out.append(struct.pack(f"{e}B{c}{c}{c}Bf", r, x, y, z, g, conf))
    for idx, flags in FACES:
        out.append(struct.pack(f"{e}{codes[count]}{len(idx)}{codes[index]}i", len(idx), *idx, flags))
    out.append(struct.pack(e + "B3b", 3, 65, 66, 67) + struct.pack(e + "B", 0))
    return b"".join(out)


def _ply_ascii(newline: str = "\n") -> bytes:
    lines = PLY_HEADER.format(fmt="ascii", ctype="float", count="uchar", index="int").splitlines()
    lines += ["1.5 -2.5"]
    lines += [f"{r} {x:.3f} {y:.3f} {z:.3f} {g} {conf}" for r, x, y, z, g, conf in VERTS]
    lines += [" ".join(map(str, [len(i), *i, f])) for i, f in FACES]
    lines += ["3 65 66 67", "0", ""]
    return newline.join(lines).encode() + newline.encode()


@pytest.mark.parametrize("endian", ["little", "big"])
@pytest.mark.parametrize("ctype", ["float", "double"])
def test_ply_binary_extra_elements_and_properties(endian: str, ctype: str) -> None:
    data = _ply_binary(endian, ctype)
    assert ply.sniff(data, "ply") and detect_format(data, "x.ply") == "ply"
    doc = ply.read(data, Limits(), "ply")
    part = doc.parts[0]
    assert doc.encoding == f"binary_{endian}_endian"
    assert doc.storage_dtype == (np.float32 if ctype == "float" else np.float64)
    assert doc.elements == [("camera", 1), ("vertex", 5), ("face", 3), ("material", 2)]
    assert part.vertices.tolist() == [list(v[1:4]) for v in VERTS]
    assert part.faces.tolist() == TRIS
    new = part.vertices.copy()
    new[3] = [0.1, 1.2, 1e-9]
    out = doc.write([new])
    a, b = np.frombuffer(data, np.uint8), np.frombuffer(out, np.uint8)
    size = 4 if ctype == "float" else 8
    rec = 1 + 3 * size + 1 + 4
    body = data.index(b"end_header\n") + 11 + 8
    allowed = body + 3 * rec + 1 + np.arange(3 * size)
    assert np.isin(np.flatnonzero(a != b), allowed).all() and (a != b).any()
    again = ply.read(out, Limits(), "ply")
    assert np.array_equal(again.parts[0].vertices, doc.quantize(new))
    assert again.parts[0].faces.tolist() == TRIS


def test_ply_binary_mixed_coordinate_types_and_index_types() -> None:
    data = _ply_binary("little", "double", count="uchar", index="short")
    data = data.replace(b"property double y", b"property float y ", 1)
    # rebuild the records for x double, y float, z double
    head = data[: data.index(b"end_header\n") + 11]
    recs = [struct.pack("<ff", 0, 0)]
    recs += [struct.pack("<BdfdBf", r, x, y, z, g, c) for r, x, y, z, g, c in VERTS]
    recs += [struct.pack(f"<B{len(i)}hi", len(i), *i, f) for i, f in FACES]
    recs.append(b"\x00\x00")
    data = head + b"".join(recs)
    doc = ply.read(data, Limits(), "ply")
    assert doc.storage_dtype is None  # mixed: quantize casts per column
    new = doc.parts[0].vertices + 0.1
    got = ply.read(doc.write([new]), Limits(), "ply").parts[0].vertices
    assert np.array_equal(got, doc.quantize(new))
    assert not np.array_equal(got[:, 1], new[:, 1]) and np.array_equal(got[:, 0], new[:, 0])


@pytest.mark.parametrize("newline", ["\n", "\r\n"])
def test_ply_ascii_extra_elements_and_properties(newline: str) -> None:
    data = _ply_ascii(newline)
    doc = ply.read(data, Limits(), "ply")
    part = doc.parts[0]
    assert doc.encoding == "ascii" and doc.decimals == 3 and doc.storage_dtype is None
    assert part.vertices.tolist() == [list(v[1:4]) for v in VERTS]
    assert part.faces.tolist() == TRIS
    new = part.vertices.copy()
    new[1] = [1.0004, -0.0006, 2.5]
    out = doc.write([new])
    line = 1 + data.decode().split(newline).index("1.5 -2.5") + 1
    assert out.split(newline.encode())[line] == b"11 1.000 -0.001 2.500 21 0.25"
    assert_text_diff(data, out, {line}, (1, 2, 3))
    again = ply.read(out, Limits(), "ply")
    assert np.array_equal(again.parts[0].vertices, doc.quantize(new))


def test_ply_vertex_index_name_and_no_faces() -> None:
    data = b"ply\nformat ascii 1.0\nelement vertex 3\nproperty double x\nproperty double y\n" \
           b"property double z\nelement face 1\nproperty list uchar uint vertex_index\nend_header\n" \
           b"0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n"
    assert ply.read(data, Limits(), "ply").parts[0].faces.tolist() == [[0, 1, 2]]
    cloud = b"ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty float x\n" \
            b"property float y\nproperty float z\nend_header\n" + np.zeros(6, "<f4").tobytes()
    doc = ply.read(cloud, Limits(), "ply")
    assert doc.parts[0].vertices.shape == (1, 3) and doc.parts[0].faces.shape == (0, 3)


def test_ply_binary_many_mixed_polygons() -> None:
    """Runs of triangles and quads in a binary face list (the run-walking path)."""
    rng = np.random.default_rng(1)
    nv, nf = 50, 400
    sizes = rng.choice([3, 4, 5], nf, p=[0.6, 0.3, 0.1])
    head = (f"ply\nformat binary_big_endian 1.0\nelement vertex {nv}\nproperty float x\nproperty float y\n"
            f"property float z\nelement face {nf}\nproperty list uchar int vertex_indices\nend_header\n")
    body = [rng.normal(size=(nv, 3)).astype(">f4").tobytes()]
    polys = [rng.choice(nv, k, replace=False) for k in sizes]
    body += [struct.pack(f">B{len(p)}i", len(p), *p) for p in polys]
    doc = ply.read(head.encode() + b"".join(body), Limits(), "ply")
    expect = [[p[0], p[j], p[j + 1]] for p in polys for j in range(1, len(p) - 1)]
    assert doc.parts[0].faces.tolist() == expect


# ---------------------------------------------------------------------------------------------
# STL

STL_ASCII = b"""solid part one
  facet normal 0 0 1
    outer loop
      vertex 0.000 0.000 0.000
      vertex 1.000 0.000 0.000
      vertex 1.000 1.000 0.000
    endloop
  endfacet
  facet normal 0 0 1
    outer loop
      vertex 0.000 0.000 0.000
      vertex 1.000 1.000 0.000
      vertex 0.000 1.000 0.000
    endloop
  endfacet
endsolid part one
"""


@pytest.mark.parametrize("variant", ["plain", "upper-crlf"])
def test_stl_ascii(variant: str) -> None:
    data = STL_ASCII if variant == "plain" else STL_ASCII.upper().replace(b"\n", b"\r\n")
    assert stl.sniff(data, "stl") and detect_format(data, "a.stl") == "stl"
    doc = stl.read(data, Limits(), "stl")
    part = doc.parts[0]
    assert doc.encoding == "ascii" and doc.decimals == 3 and doc.storage_dtype is None
    assert part.name == ("part one" if variant == "plain" else "PART ONE")
    assert part.vertices.tolist() == [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]]
    assert part.faces.tolist() == [[0, 1, 2], [0, 2, 3]]
    assert part.slot_to_vertex.tolist() == [0, 1, 2, 0, 2, 3]
    new = part.vertices.copy()
    new[2] = [1.0, 1.0, 0.0125]
    out = doc.write([new])
    nl = b"\n" if variant == "plain" else b"\r\n"
    assert_text_diff(data.replace(nl, b"\n"), out.replace(nl, b"\n"), {5, 11}, (1, 2, 3))
    assert out.split(nl)[5].strip() in (b"vertex 1.000 1.000 0.013", b"VERTEX 1.000 1.000 0.013")
    assert np.array_equal(stl.read(out, Limits(), "stl").parts[0].vertices, doc.quantize(new))


def test_stl_binary_header_starting_with_solid() -> None:
    tris = np.array([[[0, 0, 0], [1, 0, 0], [1, 1, 0]], [[0, 0, 0], [1, 1, 0], [0, 1, 0]]])
    data = binary_stl(tris, header=b"solid exported facet by a tool", attr=0xBEEF)
    assert stl.sniff(data, "stl") and detect_format(data, "a.stl") == "stl"
    doc = stl.read(data, Limits(), "stl")
    assert doc.encoding == "binary" and doc.storage_dtype == np.float32
    assert doc.parts[0].vertices.shape == (4, 3) and doc.parts[0].faces.tolist() == [[0, 1, 2], [0, 2, 3]]
    new = doc.parts[0].vertices.copy()
    new[0] = [0.1, 0.2, 0.3]
    out = doc.write([new])
    changed = np.flatnonzero(np.frombuffer(data, np.uint8) != np.frombuffer(out, np.uint8))
    assert np.isin(changed, allowed_binary_bytes("stl", data, np.array([0, 3]))).all()
    assert np.array_equal(stl.read(out, Limits(), "stl").parts[0].vertices, doc.quantize(new))


def test_stl_binary_size_must_match_count() -> None:
    tris = np.zeros((3, 3, 3))
    tris[:, :, 0] = np.arange(9).reshape(3, 3)
    data = binary_stl(tris)
    with pytest.raises(MeshFormatError, match="facets"):
        stl.read(data[:-1], Limits(), "stl")
    with pytest.raises(MeshFormatError):
        stl.read(data + b"\x00", Limits(), "stl")
    assert not stl.sniff(data[:-1], "stl")
    with pytest.raises(LimitExceededError):
        stl.read(data, Limits(max_faces=2), "stl")


# ---------------------------------------------------------------------------------------------
# OFF


@pytest.mark.parametrize(
    "data",
    [
        b"OFF\n# a square\n\n4 2 0\n0 0 0\n1 0 0\n1 1 0 # corner\n0 1 0\n3 0 1 2\n3 0 2 3\n",
        b"COFF 4 2 0\n0 0 0 255 0 0 255\n1 0 0 0 255 0 255\n1 1 0 0 0 255 255\n0 1 0 9 9 9 255\n"
        b"3 0 1 2 1 0 0\n3 0 2 3 0.5 0.5 0.5 1\n",
        b"NOFF\r\n4 1\r\n0 0 0 0 0 1\r\n1 0 0 0 0 1\r\n1 1 0 0 0 1\r\n0 1 0 0 0 1\r\n4 0 1 2 3\r\n",
    ],
    ids=["comments", "coff", "noff-crlf-quad"],
)
def test_off_variants(data: bytes) -> None:
    assert off.sniff(data, "off") and detect_format(data, "a.off") == "off"
    doc = off.read(data, Limits(), "off")
    part = doc.parts[0]
    assert part.vertices.tolist() == [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]]
    assert part.faces.tolist() == [[0, 1, 2], [0, 2, 3]]
    new = part.vertices.copy()
    new[2] += 0.5
    out = doc.write([new])
    lines = vertex_lines("off", data)
    nl = b"\r\n" if b"\r\n" in data else b"\n"
    assert_text_diff(data.replace(nl, b"\n"), out.replace(nl, b"\n"), {lines[2]}, (0, 1, 2))
    assert np.array_equal(off.read(out, Limits(), "off").parts[0].vertices, doc.quantize(new))


# ---------------------------------------------------------------------------------------------
# malformed input

_PLY_BIG = (b"ply\nformat {fmt} 1.0\nelement vertex {n}\nproperty float x\nproperty float y\n"
            b"property float z\nelement face {m}\nproperty list uchar int vertex_indices\nend_header\n")


def _big(fmt: bytes, n: int, m: int = 0) -> bytes:
    return _PLY_BIG.replace(b"{fmt}", fmt).replace(b"{n}", b"%d" % n).replace(b"{m}", b"%d" % m)


JPEG = bytes.fromhex("ffd8ffe000104a46494600010100000100010000ffdb004300") + bytes(range(256))
ZIP = b"PK\x03\x04\x14\x00\x00\x00\x08\x00" + bytes(range(200))

MALFORMED = {
    "ply-ascii-4e9-vertices": ("a.ply", _big(b"ascii", 4_000_000_000) + b"0 0 0\n", LimitExceededError),
    "ply-binary-4e9-vertices": ("a.ply", _big(b"binary_little_endian", 4_000_000_000) + bytes(12),
                                LimitExceededError),
    "ply-4e9-faces": ("a.ply", _big(b"binary_big_endian", 1, 4_000_000_000) + bytes(12), LimitExceededError),
    "ply-binary-count-over-bytes": ("a.ply", _big(b"binary_little_endian", 1000) + bytes(10),
                                    MeshFormatError),
    "ply-ascii-count-over-lines": ("a.ply", _big(b"ascii", 10) + b"0 0 0\n1 1 1\n", MeshFormatError),
    "ply-truncated-binary": ("a.ply", _ply_binary("little")[:-3], MeshFormatError),
    "ply-truncated-binary-in-vertices": (
        "a.ply", _ply_binary("big")[: _ply_binary("big").index(b"end_header") + 40], MeshFormatError),
    "ply-no-end-header": ("a.ply", b"ply\nformat ascii 1.0\nelement vertex 1\n", MeshFormatError),
    "ply-only-magic": ("a.ply", b"ply\n", MeshFormatError),
    "ply-bad-type": ("a.ply", _big(b"ascii", 1).replace(b"float x", b"flaot x") + b"0 0 0\n",
                     MeshFormatError),
    "ply-int-coordinates": ("a.ply", _big(b"ascii", 1).replace(b"float x", b"int x") + b"0 0 0\n",
                            MeshFormatError),
    "ply-bad-index": ("a.ply", _big(b"ascii", 3, 1) + b"0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n", MeshFormatError),
    "ply-negative-index": ("a.ply", _big(b"ascii", 3, 1) + b"0 0 0\n1 0 0\n0 1 0\n3 0 -1 2\n",
                           MeshFormatError),
    "ply-list-count-too-big": ("a.ply", _big(b"ascii", 3, 1) + b"0 0 0\n1 0 0\n0 1 0\n9 0 1 2\n",
                               MeshFormatError),
    "ply-huge-index-value": ("a.ply", _big(b"ascii", 3, 1) + b"0 0 0\n1 0 0\n0 1 0\n3 0 1 1e300\n",
                             MeshFormatError),
    "ply-inf-index-value": ("a.ply", _big(b"ascii", 3, 1) + b"0 0 0\n1 0 0\n0 1 0\n3 0 1 inf\n",
                            MeshFormatError),
    "ply-nan-ascii": ("a.ply", _big(b"ascii", 3, 1) + b"0 0 0\n1 nan 0\n0 1 0\n3 0 1 2\n", MeshFormatError),
    "ply-nan-binary": ("a.ply", _big(b"binary_little_endian", 1) + np.array([0, np.nan, 0], "<f4").tobytes(),
                       MeshFormatError),
    "ply-text-in-body": ("a.ply", _big(b"ascii", 1) + b"0 zero 0\n", MeshFormatError),
    "obj-index-out-of-range": ("a.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n", MeshFormatError),
    "obj-index-zero": ("a.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n", MeshFormatError),
    "obj-negative-before-any-v": ("a.obj", b"v 0 0 0\nf -1 -2 -3\nv 1 0 0\nv 0 1 0\n", MeshFormatError),
    "obj-huge-index": ("a.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 99999999999999999999999\n",
                       MeshFormatError),
    "obj-nan": ("a.obj", b"v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n", MeshFormatError),
    "obj-inf": ("a.obj", b"v 0 0 0\nv 1e999 0 0\nv 0 1 0\nf 1 2 3\n", MeshFormatError),
    "obj-two-coordinates": ("a.obj", b"v 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", MeshFormatError),
    "obj-two-corners-out-of-range": ("a.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 1 7\n",
                                     MeshFormatError),  # a skipped face is still checked
    "obj-junk-number": ("a.obj", b"v 0 0 0\nv 1 0x1 0\nv 0 1 0\nf 1 2 3\n", MeshFormatError),
    "obj-slash-only": ("a.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 /3\n", MeshFormatError),
    "obj-nul": ("a.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\x00\n" + b"v 1 1 1\n", UnsupportedFormatError),
    "off-index-out-of-range": ("a.off", b"OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 3\n", MeshFormatError),
    "off-negative-index": ("a.off", b"OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 -1 2\n", MeshFormatError),
    "off-fractional-index": ("a.off", b"OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1.5 2\n", MeshFormatError),
    "off-nan": ("a.off", b"OFF\n3 1 0\n0 0 0\n1 0 NaN\n0 1 0\n3 0 1 2\n", MeshFormatError),
    "off-too-few-lines": ("a.off", b"OFF\n3 1 0\n0 0 0\n1 0 0\n", MeshFormatError),
    "off-bad-counts": ("a.off", b"OFF\nthree 1 0\n", MeshFormatError),
    "off-huge-counts": ("a.off", b"OFF\n4000000000 1 0\n", LimitExceededError),
    "off-binary": ("a.off", b"OFF BINARY\n1 2 3\n", MeshFormatError),
    "off-4d": ("a.off", b"4OFF\n1 0 0\n0 0 0 0\n", MeshFormatError),
    "stl-ascii-nan": ("a.stl", STL_ASCII.replace(b"vertex 1.000 0.000", b"vertex nan 0.000"),
                      MeshFormatError),
    "stl-ascii-two-vertices": ("a.stl", STL_ASCII.replace(b"      vertex 1.000 0.000 0.000\n", b""),
                               MeshFormatError),
    "stl-ascii-bad-number": ("a.stl", STL_ASCII.replace(b"vertex 1.000 0.000", b"vertex 1.0.0 0.000"),
                             MeshFormatError),
    "stl-binary-nan": ("a.stl", binary_stl(np.full((1, 3, 3), np.nan)), MeshFormatError),
    "empty-obj": ("a.obj", b"", UnsupportedFormatError),
    "empty-ply": ("a.ply", b"", UnsupportedFormatError),
    "empty-stl": ("a.stl", b"", UnsupportedFormatError),
    "empty-off": ("a.off", b"", UnsupportedFormatError),
    "jpeg-named-obj": ("photo.obj", JPEG, UnsupportedFormatError),
    "zip-named-obj": ("model.obj", ZIP, UnsupportedFormatError),
    "zip-named-stl": ("model.stl", ZIP, UnsupportedFormatError),
    "ply-content-named-obj": ("model.obj", _ply_ascii(), UnsupportedFormatError),
}


@pytest.mark.parametrize("case", list(MALFORMED))
def test_malformed(case: str) -> None:
    name, data, error = MALFORMED[case]
    with pytest.raises(error) as info:
        read_mesh(data, filename=name)
    assert isinstance(info.value, MeshMarkError)


@pytest.mark.parametrize("fmt", [b"ascii", b"binary_little_endian"])
def test_declared_counts_fail_before_allocation(fmt: bytes) -> None:
    """With the vertex limit raised, a 4e9-vertex header still fails at once, on the bytes."""
    data = _big(fmt, 4_000_000_000, 1) + b"0 0 0\n"
    tracemalloc.start()
    t = time.perf_counter()
    try:
        with pytest.raises(MeshFormatError, match="file ends early"):
            ply.read(data, Limits(max_vertices=10**10, max_faces=10**10), "ply")
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert time.perf_counter() - t < 1.0
    assert peak < 1 << 20


def test_malformed_locations() -> None:
    with pytest.raises(MeshFormatError, match="line 3"):
        obj.read(b"v 0 0 0\nv 0 0 0\nv 1 x 0\n", Limits(), "obj")
    with pytest.raises(MeshFormatError, match="line 6"):
        obj.read(b"v 0 0 0\nv 1 0 0\nv 0 1 0\n# c\nf 1 2 3\nf 1 2 4\n", Limits(), "obj")
    with pytest.raises(MeshFormatError, match="line 11"):
        ply.read(_big(b"ascii", 3, 0) + b"0 0 0\n1 0 0 5\n0 1 0\n", Limits(), "ply")


def test_sniffers_reject_junk() -> None:
    rng = np.random.default_rng(0)
    junk = rng.integers(0, 256, 5000, dtype=np.uint8).tobytes()
    for data in (JPEG, ZIP, junk, b"", b"\x00" * 100, b"solid\x00\x00"):
        for module, key in ((obj, "obj"), (off, "off"), (ply, "ply"), (stl, "stl")):
            assert not module.sniff(data, key), (key, data[:10])

"""glTF 2.0 reader/writer: real GLBs, embedded .gltf, hostile files and fuzzing."""

from __future__ import annotations

import base64
import contextlib
import json
import os
import re
import struct
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from core.errors import DegenerateMeshError, LimitExceededError, MeshFormatError, MeshMarkError
from core.formats import DEFAULT_LIMITS, Limits, gltf
from tests.conftest import MESHES_DIR, shared_mesh_path
from tests.core.formats.helpers import data_uri, to_glb, to_gltf

# ---------------------------------------------------------------------------- builders

OCTA_POS = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype="<f4")
OCTA_IDX = np.array(
    [[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]], dtype="<u2"
)


def octahedron(**prim: Any) -> tuple[dict[str, Any], bytes]:
    """Minimal indexed glTF (JSON dict, binary buffer): positions then uint16 indices."""
    pos, idx = OCTA_POS.tobytes(), OCTA_IDX.tobytes()
    doc: dict[str, Any] = {
        "asset": {"version": "2.0", "generator": "test"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [{"name": "octa", "primitives": [{"attributes": {"POSITION": 0}, "indices": 1, **prim}]}],
        "accessors": [
            {
                "bufferView": 0, "componentType": 5126, "count": 6, "type": "VEC3",
                "min": [-1.0, -1.0, -1.0], "max": [1.0, 1.0, 1.0],
            },
            {"bufferView": 1, "componentType": 5123, "count": 24, "type": "SCALAR"},
        ],
        "bufferViews": [
            {"buffer": 0, "byteOffset": 0, "byteLength": len(pos)},
            {"buffer": 0, "byteOffset": len(pos), "byteLength": len(idx)},
        ],
        "buffers": [{"byteLength": len(pos) + len(idx)}],
    }
    return doc, pos + idx


def glb_parts(data: bytes) -> tuple[bytes, bytes, int, int]:
    """(JSON chunk data, BIN chunk data, BIN data offset, header length) of a GLB."""
    length = struct.unpack_from("<I", data, 8)[0]
    jl = struct.unpack_from("<I", data, 12)[0]
    js = 20
    bl = struct.unpack_from("<I", data, js + jl)[0]
    bs = js + jl + 8
    return data[js : js + jl], data[bs : bs + bl], bs, length


def read(data: bytes, name: str = "glb", limits: Limits = DEFAULT_LIMITS) -> gltf.GltfDocument:
    doc = gltf.read(data, limits, name)
    assert isinstance(doc, gltf.GltfDocument)
    return doc


def slot_offsets(meta: dict[str, Any], mesh: int) -> np.ndarray:
    """Byte offset in the buffer of every POSITION element of a mesh, independently of the reader."""
    out = []
    for prim in meta["meshes"][mesh]["primitives"]:
        if prim.get("mode", 4) not in (4, 5, 6):
            continue
        acc = meta["accessors"][prim["attributes"]["POSITION"]]
        view = meta["bufferViews"][acc["bufferView"]]
        stride = view.get("byteStride", 12)
        start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
        out.append(start + stride * np.arange(acc["count"]))
    return np.concatenate(out)


def move_some(doc: gltf.GltfDocument, rng: np.random.Generator, frac: float = 0.05) -> list[np.ndarray]:
    """New vertices: ``frac`` of each part's vertices moved by a small random offset."""
    new = []
    for part in doc.parts:
        v = part.vertices.copy()
        scale = float(np.ptp(v, axis=0).max()) * 1e-3
        idx = rng.choice(len(v), max(1, int(frac * len(v))), replace=False)
        v[idx] += rng.normal(0.0, scale, (len(idx), 3))
        new.append(v)
    return new


MINMAX_RE = re.compile(r'"(min|max)":\s*\[[^\]]*\]')


def assert_reread(doc: gltf.GltfDocument, out: bytes, new: list[np.ndarray], name: str) -> None:
    again = read(out, name)
    assert [p.name for p in again.parts] == [p.name for p in doc.parts]
    for part, part2, v in zip(doc.parts, again.parts, new, strict=True):
        np.testing.assert_array_equal(part2.faces, part.faces)
        np.testing.assert_array_equal(part2.slot_to_vertex, part.slot_to_vertex)
        np.testing.assert_array_equal(part2.vertices, doc.quantize(v))


def assert_minmax(meta: dict[str, Any], buffers: dict[int, bytes]) -> None:
    """Every POSITION accessor's min/max equals the extents of its float32 data."""
    for mesh in meta["meshes"]:
        for prim in mesh["primitives"]:
            acc = meta["accessors"][prim["attributes"]["POSITION"]]
            view = meta["bufferViews"][acc["bufferView"]]
            stride = view.get("byteStride", 12)
            start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
            buf = buffers[view["buffer"]]
            xyz = np.ndarray((acc["count"], 3), "<f4", buf, start, (stride, 4))
            np.testing.assert_array_equal(np.float32(acc["min"]), xyz.min(axis=0))
            np.testing.assert_array_equal(np.float32(acc["max"]), xyz.max(axis=0))


# ---------------------------------------------------------------------------- real GLBs

GLB_COUNTS = {
    # name: [(part name, stored slots, welded vertices, faces)]
    "monkey.glb": [("Suzanne", 1966, 505, 968)],
    "Duck.glb": [("LOD3spShape", 2399, 2108, 4212)],
    "CesiumMilkTruck.glb": [("Cesium_Milk_Truck", 2392, 1064, 2088), ("Wheels", 586, 388, 768)],
}


@pytest.mark.parametrize("name", sorted(GLB_COUNTS))
def test_real_glb_counts(name: str) -> None:
    data = shared_mesh_path(name).read_bytes()
    doc = read(data)
    assert (doc.format, doc.encoding, doc.extension, doc.media_type) == (
        "glb", "binary", "glb", "model/gltf-binary",
    )
    assert doc.storage_dtype == np.float32
    got = [(p.name, len(p.slot_to_vertex), len(p.vertices), len(p.faces)) for p in doc.parts]
    assert got == GLB_COUNTS[name]
    # cross-check stored vertices and triangles with trimesh (one geometry per primitive)
    trimesh = pytest.importorskip("trimesh")
    scene = trimesh.load(str(shared_mesh_path(name)), force="scene", process=False)
    stored = sum(len(p.slot_to_vertex) for p in doc.parts)
    assert sum(len(g.vertices) for g in scene.geometry.values()) == stored
    assert sum(len(g.faces) for g in scene.geometry.values()) == sum(len(p.faces) for p in doc.parts)


@pytest.mark.parametrize("name", sorted(GLB_COUNTS))
def test_real_glb_patch_confined(name: str) -> None:
    data = shared_mesh_path(name).read_bytes()
    doc = read(data)
    new = move_some(doc, np.random.default_rng(7))
    out = doc.write(new)

    json0, bin0, bs0, _ = glb_parts(data)
    json1, bin1, bs1, length1 = glb_parts(out)
    assert out[:8] == data[:8] and length1 == len(out)
    assert len(json1) % 4 == 0 and bs1 % 4 == 0
    assert out[bs1 + len(bin1) :] == data[bs0 + len(bin0) :]  # anything after BIN untouched
    # JSON: identical text except the min/max arrays (and the padding)
    text0, text1 = json0.decode().rstrip(" "), json1.decode().rstrip(" ")
    assert MINMAX_RE.sub("", text0) == MINMAX_RE.sub("", text1)
    meta0, meta1 = json.loads(text0), json.loads(text1)
    pos_acc = {p["attributes"]["POSITION"] for m in meta0["meshes"] for p in m["primitives"]}
    for i, (a0, a1) in enumerate(zip(meta0["accessors"], meta1["accessors"], strict=True)):
        if i not in pos_acc:
            assert a0 == a1
    assert_minmax(meta1, {0: bin1})
    # BIN: only the coordinates of moved vertices' slots changed
    assert len(bin0) == len(bin1)
    changed = np.flatnonzero(np.frombuffer(bin0, np.uint8) != np.frombuffer(bin1, np.uint8))
    allowed = []
    for mi, (part, v) in enumerate(zip(doc.parts, new, strict=True)):
        moved = np.flatnonzero(np.any(v != part.vertices, axis=1))
        offsets = slot_offsets(meta0, mi)[np.isin(part.slot_to_vertex, moved)]
        allowed.append((offsets[:, None] + np.arange(12)).ravel())
    allowed_bytes = np.concatenate(allowed)
    assert changed.size > 0 and np.isin(changed, allowed_bytes).all()
    assert_reread(doc, out, new, "glb")


def test_no_move_is_identity() -> None:
    data = to_glb(*octahedron())
    doc = read(data)
    assert doc.write([p.vertices.copy() for p in doc.parts]) == data


def test_interior_move_keeps_json() -> None:
    """A move that leaves the extents unchanged rewrites no JSON byte."""
    data = to_glb(*octahedron())
    doc = read(data)
    v = doc.parts[0].vertices.copy()
    v[4] = [0.5, 0.25, 1.0]  # was [0, 0, 1]
    out = doc.write([v])
    assert len(out) == len(data) and glb_parts(out)[0] == glb_parts(data)[0]
    diff = np.flatnonzero(np.frombuffer(out, np.uint8) != np.frombuffer(data, np.uint8))
    _, _, bs, _ = glb_parts(data)
    assert diff.min() >= bs + 48 and diff.max() < bs + 60


# ---------------------------------------------------------------------------- .gltf (embedded)


@pytest.mark.parametrize("indent", [None, 2])
def test_gltf_embedded_roundtrip(indent: int | None) -> None:
    meta, blob = octahedron()
    meta["images"] = [{"uri": "texture.png"}, {"uri": "file:///etc/passwd"}]
    data = to_gltf(meta, blob, indent=indent)
    assert gltf.sniff(data, "gltf") and not gltf.sniff(data, "glb")
    doc = read(data, "gltf")
    assert (doc.format, doc.extension, doc.media_type) == ("gltf", "gltf", "model/gltf+json")
    assert [(p.name, len(p.vertices), len(p.faces)) for p in doc.parts] == [("octa", 6, 8)]
    new = [doc.parts[0].vertices.copy()]
    new[0][1] = [-1.25, 0.1, 0.0]  # extends min x
    out = doc.write(new)
    text0, text1 = data.decode(), out.decode()
    uri_re = re.compile(r'"uri":\s*"data:[^"]*"')
    assert MINMAX_RE.sub("", uri_re.sub("", text0)) == MINMAX_RE.sub("", uri_re.sub("", text1))
    max_re = re.compile(r'"max":\s*\[[^\]]*\]')
    assert max_re.findall(text0) == max_re.findall(text1)  # extents unchanged there: text kept
    meta1 = json.loads(text1)
    assert meta1["images"] == meta["images"]  # image URIs carried through, never opened
    blob1 = base64.b64decode(meta1["buffers"][0]["uri"].split(",", 1)[1])
    assert meta1["buffers"][0]["uri"].startswith("data:application/octet-stream;base64,")
    diff = np.flatnonzero(np.frombuffer(blob, np.uint8) != np.frombuffer(blob1, np.uint8))
    assert diff.min() >= 12 and diff.max() < 24  # vertex 1 only
    assert meta1["accessors"][0]["min"] == [-1.25, -1.0, -1.0]
    assert_minmax(meta1, {0: blob1})
    assert_reread(doc, out, new, "gltf")


def test_gltf_from_real_glb_roundtrip() -> None:
    json0, bin0, _, _ = glb_parts(shared_mesh_path("monkey.glb").read_bytes())
    meta = json.loads(json0)
    data = to_gltf(meta, bin0[: meta["buffers"][0]["byteLength"]])
    doc = read(data, "gltf")
    assert [(len(p.vertices), len(p.faces)) for p in doc.parts] == [(505, 968)]
    new = move_some(doc, np.random.default_rng(3))
    out = doc.write(new)
    assert_reread(doc, out, new, "gltf")


# ---------------------------------------------------------------------------- features


def test_strip_fan_nonindexed_lines() -> None:
    pos = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [2, 0, 0]], dtype="<f4")
    blob = pos.tobytes()
    meta: dict[str, Any] = {
        "asset": {"version": "2.0"},
        "meshes": [
            {"primitives": [
                {"attributes": {"POSITION": 0}, "mode": 5},  # strip 0-1-2-3-4
                {"attributes": {"POSITION": 0}, "mode": 6},  # fan around 0
                {"attributes": {"POSITION": 0}, "mode": 1},  # lines: skipped
                {"attributes": {"POSITION": 0}, "mode": 0},  # points: skipped
            ]},
            {"primitives": [{"attributes": {"POSITION": 0}, "mode": 3}]},  # no triangles: no part
            {"name": "soup", "primitives": [{"attributes": {"POSITION": 1}}]},  # non-indexed triangles
        ],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": 5, "type": "VEC3"},
            {"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3", "byteOffset": 12},
        ],
        "bufferViews": [{"buffer": 0, "byteLength": len(blob)}],
        "buffers": [{"byteLength": len(blob)}],
    }
    doc = read(to_glb(meta, blob))
    assert [p.name for p in doc.parts] == ["mesh0", "soup"]
    strip_fan, soup = doc.parts
    # primitives of one mesh sharing a POSITION accessor share its slots (read once, not twice)
    assert len(strip_fan.slot_to_vertex) == 5 and len(strip_fan.vertices) == 5
    np.testing.assert_array_equal(
        strip_fan.faces, [[0, 1, 2], [2, 1, 3], [2, 3, 4], [0, 1, 2], [0, 2, 3], [0, 3, 4]]
    )
    np.testing.assert_array_equal(soup.faces, [[0, 1, 2]])
    # both parts share bytes (accessor 1 aliases accessor 0): the first part owns them
    v0, v1 = strip_fan.vertices.copy(), soup.vertices.copy()
    v0[1] += 0.5
    v1[0] -= 0.5  # same stored element as v0[1]: ignored, written once from part 0
    out = doc.write([v0, v1])
    again = read(out)
    np.testing.assert_array_equal(again.parts[0].vertices, doc.quantize(v0))
    np.testing.assert_array_equal(again.parts[1].vertices[0], v0[1])


def test_interleaved_stride_and_shared_accessor() -> None:
    """byteStride honoured; one POSITION accessor used by two primitives of one mesh."""
    pos = OCTA_POS
    inter = np.zeros((6, 6), "<f4")
    inter[:, :3] = pos
    inter[:, 3:] = 7.0  # "normals"
    idx = OCTA_IDX.tobytes()
    blob = inter.tobytes() + idx
    meta: dict[str, Any] = {
        "asset": {"version": "2.0"},
        "meshes": [{"primitives": [
            {"attributes": {"POSITION": 0, "NORMAL": 1}, "indices": 2},
            {"attributes": {"POSITION": 0, "NORMAL": 1}, "indices": 2},
        ]}],
        "accessors": [
            {
                "bufferView": 0, "componentType": 5126, "count": 6, "type": "VEC3",
                "min": [-1] * 3, "max": [1] * 3,
            },
            {"bufferView": 0, "byteOffset": 12, "componentType": 5126, "count": 6, "type": "VEC3"},
            {"bufferView": 1, "componentType": 5123, "count": 24, "type": "SCALAR"},
        ],
        "bufferViews": [
            {"buffer": 0, "byteLength": 144, "byteStride": 24},
            {"buffer": 0, "byteOffset": 144, "byteLength": len(idx)},
        ],
        "buffers": [{"byteLength": len(blob)}],
    }
    data = to_glb(meta, blob)
    doc = read(data)
    (part,) = doc.parts
    assert len(part.slot_to_vertex) == 6 and len(part.vertices) == 6 and len(part.faces) == 16
    v = part.vertices.copy()
    v[:, 2] += 0.125
    out = doc.write([v])
    _, bin1, _, _ = glb_parts(out)
    got = np.frombuffer(bin1[:144], "<f4").reshape(6, 6)
    np.testing.assert_array_equal(got[:, :3], v.astype("<f4"))
    np.testing.assert_array_equal(got[:, 3:], 7.0)
    assert bin1[144:] == blob[144:] + b"\0" * (-len(blob) % 4)
    assert json.loads(glb_parts(out)[0])["accessors"][0]["max"] == [1.0, 1.0, 1.125]
    assert_reread(doc, out, [v], "glb")


def test_sniff() -> None:
    glb = to_glb(*octahedron())
    assert gltf.sniff(glb, "glb") and not gltf.sniff(glb, "gltf")
    assert gltf.sniff(b' \n\t{ "asset" :\n {"version": "2.0"}}', "gltf")
    assert not gltf.sniff(b'{"scene": 0}', "gltf")
    assert not gltf.sniff(b"v 0 0 0\nf 1 2 3\n", "gltf")
    assert not gltf.sniff(b"ply\nformat ascii 1.0\n", "glb")


def test_detect_format_dispatch() -> None:
    for mod in ("ply", "stl", "off", "obj"):
        pytest.importorskip(f"core.formats.{mod}")
    from core.formats import read_mesh

    meta, blob = octahedron()
    assert read_mesh(to_glb(meta, blob), "x.glb").format == "glb"
    assert read_mesh(to_gltf(meta, blob), "x.gltf").format == "gltf"


# ---------------------------------------------------------------------------- hostile input


def fails_fast(data: bytes, exc: type[Exception] = MeshFormatError, name: str = "glb", **kw: Any) -> str:
    start = time.perf_counter()
    with pytest.raises(exc) as info:
        gltf.read(data, kw.get("limits", DEFAULT_LIMITS), name)
    assert time.perf_counter() - start < 1.0
    return str(info.value)


EXTERNAL_URIS = [
    "canary.bin", "./canary.bin", "../canary.bin", "sub/../canary.bin", "file:canary.bin",
    "file://{abs}", "file:///{abs}", "{abs}", "http://127.0.0.1:9/canary.bin",
    "https://example.invalid/canary.bin", "//example.invalid/canary.bin", "ftp://x/canary.bin",
]


@pytest.mark.parametrize("container", ["gltf", "glb"])
@pytest.mark.parametrize("uri", EXTERNAL_URIS)
def test_external_buffer_refused(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, uri: str, container: str
) -> None:
    meta, blob = octahedron()
    marker = b"CANARY-7f3a9c-DO-NOT-READ"
    canary = blob + marker  # a valid buffer: resolving it would make the read succeed
    (tmp_path / "sub").mkdir()
    for d in (tmp_path, tmp_path / "sub"):
        (d / "canary.bin").write_bytes(canary)
    monkeypatch.chdir(tmp_path / "sub")
    meta["buffers"][0]["uri"] = uri.format(abs=str(tmp_path / "canary.bin").lstrip("/"))
    if uri.startswith("{abs}"):
        meta["buffers"][0]["uri"] = str(tmp_path / "canary.bin")
    data = json.dumps(meta).encode() if container == "gltf" else to_glb(meta, None)
    message = fails_fast(data, name=container)
    assert "external buffer refused" in message
    assert marker.decode() not in message and blob.hex() not in message


def test_external_buffer_refused_even_if_unused() -> None:
    meta, blob = octahedron()
    meta["buffers"].append({"byteLength": 4, "uri": "https://example.invalid/x.bin"})
    fails_fast(to_glb(meta, blob))


def test_huge_count_without_buffer_view() -> None:
    meta, blob = octahedron()
    meta["accessors"][0] = {"componentType": 5126, "count": 2**40, "type": "VEC3"}
    assert "no bufferView" in fails_fast(to_glb(meta, blob))


def test_count_overruns_buffer_view_small_file() -> None:
    meta = {
        "asset": {"version": "2.0"},
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}],
        "accessors": [{"bufferView": 0, "componentType": 5126, "count": 10**9, "type": "VEC3"}],
        "bufferViews": [{"buffer": 0, "byteLength": 36}],
        "buffers": [{"byteLength": 36, "uri": data_uri(OCTA_POS.tobytes()[:36])}],
    }
    data = json.dumps(meta, separators=(",", ":")).encode()
    assert len(data) < 400
    assert "overrun" in fails_fast(data, name="gltf")


@pytest.mark.parametrize(
    "mutate",
    [
        lambda m: m["bufferViews"][0].update(byteStride=24),  # 6 x 24 > 72-byte view
        lambda m: m["accessors"][0].update(byteOffset=4),
        lambda m: m["bufferViews"][1].update(byteLength=4000),  # view past buffer
        lambda m: m["buffers"][0].update(byteLength=4000),  # buffer past BIN chunk
        lambda m: m["bufferViews"][0].update(byteStride=8),  # stride < element
        lambda m: m["accessors"][0].update(sparse={"count": 1}),
        lambda m: m["accessors"][0].update(componentType=5125),  # UNSIGNED_INT positions
        lambda m: m["accessors"][0].update(type="VEC2"),
        lambda m: m["accessors"][0].update(normalized=True),
        lambda m: m["accessors"][0].update(count=-1),
        lambda m: m["accessors"][0].update(count="6"),
        lambda m: m["accessors"][1].update(componentType=5126),
        lambda m: m["accessors"][1].update(type="VEC3"),
        lambda m: m["meshes"][0]["primitives"][0].update(indices=99),
        lambda m: m["meshes"][0]["primitives"][0].update(mode=9),
        lambda m: m["meshes"][0]["primitives"][0]["attributes"].update(POSITION=True),
        lambda m: m["bufferViews"][0].update(buffer=1),
        lambda m: m.update(meshes={"a": 1}),
        lambda m: m["accessors"][0].update(componentType=5126, normalized=True),
        lambda m: m["asset"].update(version="1.0"),
        lambda m: m["accessors"][1].update(bufferView=0, count=18),  # indices alias positions
        lambda m: m["accessors"].append(m["accessors"][0] | {"byteOffset": 4, "count": 5})
        or m["meshes"].append({"primitives": [{"attributes": {"POSITION": 2}}]}),  # partial overlap
    ],
)
def test_malformed_json_fields(mutate: Any) -> None:
    meta, blob = octahedron()
    mutate(meta)
    fails_fast(to_glb(meta, blob))


@pytest.mark.parametrize("bits", [0x7FC00000, 0x7F800001, 0xFFFF0000, 0xFF800000])
def test_non_finite_position(bits: int) -> None:
    meta, blob = octahedron()
    bad = bytearray(blob)
    struct.pack_into("<I", bad, 16, bits)
    assert "non-finite" in fails_fast(to_glb(meta, bytes(bad)))


def test_index_out_of_range() -> None:
    meta, blob = octahedron()
    bad = bytearray(blob)
    struct.pack_into("<H", bad, 72, 6)
    assert "POSITION count" in fails_fast(to_glb(meta, bytes(bad)))


@pytest.mark.parametrize(
    "mutate",
    [
        lambda d: d[:11],
        lambda d: d[:-8],  # header length > file
        lambda d: d[:4] + struct.pack("<I", 1) + d[8:],  # version 1
        lambda d: d[:12] + struct.pack("<I", 2**31) + d[16:],  # JSON chunk past the file
        lambda d: d[:16] + struct.pack("<I", gltf.CHUNK_BIN) + d[20:],  # first chunk not JSON
        lambda d: d + b"\x10\x00\x00\x00BIN\x00",  # chunk header past the declared length
        # an unknown trailing chunk (valid, ignored)
        lambda d: d[:8] + struct.pack("<I", len(d) + 8) + d[12:] + struct.pack("<II", 99, 0),
    ],
)
def test_malformed_glb_container(mutate: Any) -> None:
    data = mutate(to_glb(*octahedron()))
    start = time.perf_counter()
    with contextlib.suppress(MeshFormatError):  # the last case is valid (unknown chunk ignored)
        gltf.read(data, DEFAULT_LIMITS, "glb")
    assert time.perf_counter() - start < 1.0


def test_glb_chunk_length_beyond_file() -> None:
    data = bytearray(to_glb(*octahedron()))
    jl = struct.unpack_from("<I", data, 12)[0]
    struct.pack_into("<I", data, 20 + jl, 10**6)  # BIN chunk length
    assert "past the end" in fails_fast(bytes(data))


@pytest.mark.parametrize("name", ["glb", "gltf"])
def test_json_nesting_depth(name: str) -> None:
    deep = '{"asset":{"version":"2.0"},"extras":' + "[" * 10_000 + "]" * 10_000 + "}"
    data = deep.encode() if name == "gltf" else to_glb(json.loads('{"asset":{"version":"2.0"}}'), None)
    if name == "glb":
        body = deep.encode() + b" " * (-len(deep) % 4)
        data = b"glTF" + struct.pack("<IIII", 2, 20 + len(body), len(body), gltf.CHUNK_JSON) + body
    assert "nested deeper" in fails_fast(data, name=name)


@pytest.mark.parametrize(
    "text",
    [b'{"asset":{"version":"2.0"}', b'{"asset":{"version":"2.0"},"x":NaN}', b"[1]", b'{"asset": 1}',
     b'{"asset":{"version":"2.0"},"x":1' + b"0" * 5000 + b"}", b'{"asset":{"version":"2.0"}}\xff'],
)
def test_invalid_json(text: bytes) -> None:
    fails_fast(text, name="gltf")


def test_bad_data_uris() -> None:
    meta, blob = octahedron()
    for uri in ["data:application/octet-stream,abc", "data:;base64,@@@@", "data:;base64,QUJD\nRA=="]:
        meta["buffers"][0]["uri"] = uri
        fails_fast(json.dumps(meta).encode(), name="gltf")
    meta["buffers"][0]["uri"] = data_uri(blob[:40])  # shorter than byteLength
    assert "bytes stored" in fails_fast(json.dumps(meta).encode(), name="gltf")


def test_no_triangles() -> None:
    meta, blob = octahedron(mode=1)
    fails_fast(to_glb(meta, blob), DegenerateMeshError)


@pytest.mark.parametrize(
    "limits",
    [Limits(max_vertices=5), Limits(max_faces=7), Limits(max_meshes=0), Limits(max_json_bytes=100)],
)
def test_limits_glb(limits: Limits) -> None:
    fails_fast(to_glb(*octahedron()), LimitExceededError, limits=limits)


def test_limits_gltf() -> None:
    meta, blob = octahedron()
    data = to_gltf(meta, blob)
    fails_fast(data, LimitExceededError, name="gltf", limits=Limits(max_bytes=64))  # base64 payload
    read(data, "gltf", Limits(max_json_bytes=len(data) - 100))  # embedded data does not count as JSON
    fails_fast(data, LimitExceededError, name="gltf", limits=Limits(max_json_bytes=100))


# ---------------------------------------------------------------------------- fuzzing

_FUZZ_BASES: list[tuple[str, bytes]] = [
    ("glb", to_glb(*octahedron())),
    ("gltf", to_gltf(*octahedron())),
    ("glb", to_glb(*octahedron(mode=5))),
]
for _name in ("monkey.glb", "Duck.glb"):
    if (MESHES_DIR / _name).is_file():
        _FUZZ_BASES.append(("glb", (MESHES_DIR / _name).read_bytes()))

#: examples per fuzz test (raise it locally for a longer hunt)
FUZZ_EXAMPLES = int(os.environ.get("MESHMARK_FUZZ_EXAMPLES", "100"))
_U32 = st.sampled_from([0, 1, 3, 4, 12, 0xFF, 0xFFFF, 0x7FFFFFFF, 0xFFFFFFFF, 2**31])


def _exercise(data: bytes, name: str) -> None:
    """Read and write back; only MeshMarkError may escape."""
    try:
        doc = gltf.read(data, DEFAULT_LIMITS, name)
    except MeshMarkError:
        return
    out = doc.write([p.vertices + 1e-3 for p in doc.parts])
    with contextlib.suppress(MeshMarkError):
        gltf.read(out, DEFAULT_LIMITS, name)


@settings(max_examples=FUZZ_EXAMPLES, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    base=st.sampled_from(_FUZZ_BASES),
    ops=st.lists(
        st.tuples(st.sampled_from(["cut", "byte", "u32"]), st.floats(0, 1), st.integers(0, 255), _U32),
        min_size=1,
        max_size=4,
    ),
)
def test_fuzz_bytes(base: tuple[str, bytes], ops: list[tuple[str, float, int, int]]) -> None:
    name, data = base
    buf = bytearray(data)
    for op, where, byte, word in ops:
        at = min(int(where * len(buf)), max(len(buf) - 1, 0))
        if op == "cut":
            del buf[at:]
        elif op == "byte" and buf:
            buf[at] = byte
        elif op == "u32" and len(buf) >= 4:
            struct.pack_into("<I", buf, min(at, len(buf) - 4) & ~3, word)
    _exercise(bytes(buf), name)


_FIELDS = [
    ("accessors", 0, "count"), ("accessors", 0, "byteOffset"), ("accessors", 0, "bufferView"),
    ("accessors", 0, "componentType"), ("accessors", 0, "type"), ("accessors", 0, "min"),
    ("accessors", 1, "count"), ("accessors", 1, "componentType"), ("accessors", 1, "byteOffset"),
    ("bufferViews", 0, "byteStride"), ("bufferViews", 0, "byteLength"), ("bufferViews", 0, "byteOffset"),
    ("bufferViews", 1, "buffer"), ("bufferViews", 1, "byteLength"), ("buffers", 0, "byteLength"),
    ("buffers", 0, "uri"), ("meshes", 0, "primitives"), ("meshes", 0, "name"), ("asset", None, "version"),
]
_JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**70), 2**70) | st.floats(allow_nan=False)
    | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=4), inner, max_size=3),
    max_leaves=6,
)


@settings(max_examples=FUZZ_EXAMPLES, deadline=None)
@given(
    edits=st.lists(st.tuples(st.sampled_from(_FIELDS), _JSON_VALUES), min_size=1, max_size=3),
    mode=st.sampled_from([None, 4, 5, 6]),
    container=st.sampled_from(["glb", "gltf"]),
)
def test_fuzz_json_fields(
    edits: list[tuple[tuple[str, int | None, str], Any]], mode: int | None, container: str
) -> None:
    meta, blob = octahedron() if mode is None else octahedron(mode=mode)
    if container == "gltf":
        meta["buffers"][0]["uri"] = data_uri(blob)
    for (section, index, key), value in edits:
        target = meta[section] if index is None else meta[section][index]
        target[key] = value
    data = to_glb(meta, blob) if container == "glb" else json.dumps(meta).encode()
    _exercise(data, container)

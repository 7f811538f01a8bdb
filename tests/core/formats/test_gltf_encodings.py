"""glTF position encodings beyond plain float32: KHR_mesh_quantization, sparse accessors,
EXT/KHR_meshopt_compression and KHR_draco_mesh_compression; and what hostile streams get."""

from __future__ import annotations

import contextlib
import json
import struct
import time
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from core.errors import LimitExceededError, MeshFormatError, MeshMarkError
from core.formats import DEFAULT_LIMITS, Limits, gltf
from core.pipeline import detect_file, embed_file
from tests.conftest import shared_mesh_path
from tests.core.formats.helpers import to_glb

# (componentType, dtype, normalized, independent dequantization)
QUANTIZED = [
    (5120, "<i1", True, lambda c: np.maximum(c / 127.0, -1.0)),
    (5121, "<u1", True, lambda c: c / 255.0),
    (5122, "<i2", True, lambda c: np.maximum(c / 32767.0, -1.0)),
    (5123, "<u2", True, lambda c: c / 65535.0),
    (5120, "<i1", False, lambda c: c.astype(float)),
    (5121, "<u1", False, lambda c: c.astype(float)),
    (5122, "<i2", False, lambda c: c.astype(float)),
    (5123, "<u2", False, lambda c: c.astype(float)),
]


def grid(n: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """A wavy n x n grid in [-1, 1]^2 (float64) and its triangles."""
    x, y = np.meshgrid(np.linspace(-1, 1, n), np.linspace(-1, 1, n))
    v = np.c_[x.ravel(), y.ravel(), 0.3 * np.sin(2 * x.ravel()) * np.cos(3 * y.ravel())]
    f = []
    for i in range(n - 1):
        for j in range(n - 1):
            a = i * n + j
            f += [[a, a + 1, a + n], [a + 1, a + n + 1, a + n]]
    return v, np.array(f, dtype=np.int64)


def glb_with(stored: np.ndarray, faces: np.ndarray, ctype: int, normalized: bool,
             **accessor: Any) -> tuple[dict[str, Any], bytes]:
    """One-mesh GLB: positions stored as given (padded to a 4-byte stride), uint16 indices."""
    item = stored.dtype.itemsize
    stride = -(-3 * item // 4) * 4
    rows = np.zeros((len(stored), stride), np.uint8)
    rows[:, : 3 * item] = np.ascontiguousarray(stored).view(np.uint8).reshape(len(stored), -1)
    pos, idx = rows.tobytes(), np.asarray(faces, "<u2").tobytes()
    acc: dict[str, Any] = {"bufferView": 0, "componentType": ctype, "count": len(stored), "type": "VEC3",
                           "min": stored.min(axis=0).tolist(), "max": stored.max(axis=0).tolist()}
    if normalized:
        acc["normalized"] = True
    acc.update(accessor)
    meta = {
        "asset": {"version": "2.0"}, "extensionsUsed": ["KHR_mesh_quantization"],
        "extensionsRequired": ["KHR_mesh_quantization"],
        "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0, "scale": [0.01, 0.01, 0.01]}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
        "accessors": [acc, {"bufferView": 1, "componentType": 5123, "count": faces.size, "type": "SCALAR"}],
        "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": len(pos), "byteStride": stride},
                        {"buffer": 0, "byteOffset": len(pos), "byteLength": len(idx)}],
        "buffers": [{"byteLength": len(pos) + len(idx)}],
    }
    return meta, pos + idx


def stored_grid(dtype: str, normalized: bool) -> np.ndarray:
    v, _ = grid()
    info = np.iinfo(dtype)
    if normalized:
        top = info.max
        v = v if info.min < 0 else (v + 1) / 2
        return np.rint(v * top).astype(dtype)
    span = (info.max - max(info.min, -info.max)) / 2.2
    mid = (info.max + max(info.min, -info.max)) / 2
    return np.rint(mid + v * span).astype(dtype)


def json_of(data: bytes) -> dict[str, Any]:
    jl = struct.unpack_from("<I", data, 12)[0]
    out: dict[str, Any] = json.loads(data[20 : 20 + jl])
    return out


@pytest.mark.parametrize(("ctype", "dtype", "normalized", "dequant"), QUANTIZED)
def test_quantized_positions_read_and_write_back(ctype: int, dtype: str, normalized: bool,
                                                 dequant: Any) -> None:
    stored = stored_grid(dtype, normalized)
    _, faces = grid()
    meta, blob = glb_with(stored, faces, ctype, normalized)
    data = to_glb(meta, blob)
    doc = gltf.read(data, DEFAULT_LIMITS, "glb")
    part = doc.parts[0]
    np.testing.assert_array_equal(part.vertices[part.slot_to_vertex], dequant(stored.astype(np.float64)))
    # move interior vertices along x by a few grid steps (extents unchanged); quantize_part says
    # where they land
    step = (1 / np.iinfo(dtype).max) if normalized else 1.0
    idx = np.unique(part.slot_to_vertex[[i for i in range(13, 131) if i % 12 not in (0, 10, 11)]])
    new = part.vertices.copy()
    new[idx, 0] += 3.4 * step
    new[idx] = doc.quantize_part(0, idx, new[idx])
    out = doc.write([new])
    again = gltf.read(out, DEFAULT_LIMITS, "glb")
    np.testing.assert_array_equal(again.parts[0].vertices, new)
    assert json_of(out)["accessors"][0]["componentType"] == ctype
    assert len(out) == len(data)
    changed = np.flatnonzero(np.frombuffer(out, np.uint8) != np.frombuffer(data, np.uint8))
    bin_start = len(data) - len(blob)
    assert changed.size and changed.min() >= bin_start  # the JSON kept (extents unchanged), only positions
    stride = -(-3 * np.dtype(dtype).itemsize // 4) * 4
    assert set(((changed - bin_start) // stride).tolist()) <= set(part.slot_to_vertex[idx].tolist())


def test_quantized_extents_rewritten_as_integers() -> None:
    stored = stored_grid("<u2", False)
    _, faces = grid()
    data = to_glb(*glb_with(stored, faces, 5123, False))
    doc = gltf.read(data, DEFAULT_LIMITS, "glb")
    new = doc.parts[0].vertices.copy()
    top = int(np.argmax(new[:, 2]))
    new[top, 2] += 7
    out = doc.write([new])
    acc = json_of(out)["accessors"][0]
    assert acc["max"][2] == int(stored[:, 2].max()) + 7 and isinstance(acc["max"][2], int)


def test_sparse_positions_read_and_write() -> None:
    v, faces = grid(6)
    base = v.astype("<f4")
    subst = np.array([3, 10], dtype="<u2")
    values = (v[subst] + 0.25).astype("<f4")
    pos, idx = base.tobytes(), faces.astype("<u2").tobytes()
    sidx, sval = subst.tobytes() + b"\0\0", values.tobytes()
    blob = pos + idx + sidx + sval
    o = np.cumsum([0, len(pos), len(idx), len(sidx)])
    meta = {
        "asset": {"version": "2.0"},
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": len(v), "type": "VEC3",
             "sparse": {"count": 2, "indices": {"bufferView": 2, "componentType": 5123},
                        "values": {"bufferView": 3}}},
            {"bufferView": 1, "componentType": 5123, "count": faces.size, "type": "SCALAR"}],
        "bufferViews": [{"buffer": 0, "byteOffset": int(o[k]), "byteLength": n}
                        for k, n in enumerate([len(pos), len(idx), 4, len(sval)])],
        "buffers": [{"byteLength": len(blob)}],
    }
    data = to_glb(meta, blob)
    doc = gltf.read(data, DEFAULT_LIMITS, "glb")
    want = base.astype(np.float64)
    want[subst] = values
    part = doc.parts[0]
    np.testing.assert_array_equal(part.vertices[part.slot_to_vertex], want)
    new = part.vertices.copy()
    new[part.slot_to_vertex[3]] += 0.125
    out = doc.write([new])
    # the substituted value is rewritten where it is stored; the base element stays
    bs = len(data) - len(blob) - (len(blob) % 4 and 4 - len(blob) % 4)
    body = out[bs:]
    assert np.frombuffer(body, "<f4", 3, int(o[3]))[0] == np.float32(values[0, 0] + 0.125)
    assert body[: len(pos)] == pos


def test_sparse_without_buffer_view_pins_unstored() -> None:
    v, faces = grid(6)
    subst = np.arange(len(v), dtype="<u2")[::2]
    values = v[subst].astype("<f4")
    idx, sidx, sval = faces.astype("<u2").tobytes(), subst.tobytes(), values.tobytes()
    blob = idx + sidx + sval
    meta = {
        "asset": {"version": "2.0"},
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
        "accessors": [
            {"componentType": 5126, "count": len(v), "type": "VEC3",
             "sparse": {"count": len(subst), "indices": {"bufferView": 1, "componentType": 5123},
                        "values": {"bufferView": 2}}},
            {"bufferView": 0, "componentType": 5123, "count": faces.size, "type": "SCALAR"}],
        "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": len(idx)},
                        {"buffer": 0, "byteOffset": len(idx), "byteLength": len(sidx)},
                        {"buffer": 0, "byteOffset": len(idx) + len(sidx), "byteLength": len(sval)}],
        "buffers": [{"byteLength": len(blob)}],
    }
    doc = gltf.read(to_glb(meta, blob), DEFAULT_LIMITS, "glb")
    part = doc.parts[0]
    slots = part.slot_to_vertex
    stored_vertex, zero_vertex = slots[0], slots[1]
    both = np.array([stored_vertex, zero_vertex])
    moved = doc.quantize_part(0, both, part.vertices[both] + 0.5)
    assert moved[0, 0] == np.float32(part.vertices[stored_vertex, 0] + 0.5)
    np.testing.assert_array_equal(moved[1], part.vertices[zero_vertex])  # no storage: stays


# ------------------------------------------------------------------------------ compressed


def meshopt_glb(v: np.ndarray, faces: np.ndarray, extension: str = "EXT_meshopt_compression",
                version: int = 0, **override: Any) -> bytes:
    import meshoptimizer

    pos = np.zeros((len(v), 8), np.uint8)
    pos[:, :6] = np.rint(v * 1000 + 2000).astype("<u2").view(np.uint8).reshape(len(v), 6)
    meshoptimizer.encode_vertex_version(version)
    meshoptimizer.encode_index_version(1)
    cpos = meshoptimizer.encode_vertex_buffer(pos, len(v), 8)
    cidx = meshoptimizer.encode_index_buffer(faces.astype(np.uint32).ravel(), faces.size, len(v))
    n_pos = len(cpos)
    cpos += b"\0" * (-len(cpos) % 4)  # views start 4-aligned; byteLength is the stream's own
    ext_pos = {"buffer": 0, "byteOffset": 0, "byteLength": n_pos, "byteStride": 8, "mode": "ATTRIBUTES",
               "count": len(v)}
    ext_pos.update(override)
    meta = {
        "asset": {"version": "2.0"}, "extensionsUsed": [extension, "KHR_mesh_quantization"],
        "extensionsRequired": [extension, "KHR_mesh_quantization"],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
        "accessors": [{"bufferView": 0, "componentType": 5123, "count": len(v), "type": "VEC3"},
                      {"bufferView": 1, "componentType": 5123, "count": faces.size, "type": "SCALAR"}],
        "bufferViews": [
            {"buffer": 1, "byteOffset": 0, "byteLength": 8 * len(v), "byteStride": 8,
             "extensions": {extension: ext_pos}},
            {"buffer": 1, "byteOffset": 8 * len(v), "byteLength": 2 * faces.size,
             "extensions": {extension: {"buffer": 0, "byteOffset": len(cpos), "byteLength": len(cidx),
                                        "byteStride": 2, "mode": "TRIANGLES", "count": faces.size}}}],
        "buffers": [{"byteLength": len(cpos) + len(cidx)},
                    {"byteLength": 8 * len(v) + 2 * faces.size,
                     "extensions": {extension: {"fallback": True}}}],
    }
    return to_glb(meta, cpos + cidx)


def rotated(tri: np.ndarray) -> np.ndarray:
    """Triangles rotated to start at their smallest corner (the index codec may rotate them)."""
    k = np.argmin(tri, axis=1)
    rows = np.arange(len(tri))[:, None]
    return np.asarray(tri[rows, (k[:, None] + np.arange(3)) % 3])


@pytest.mark.parametrize(("extension", "version"), [("EXT_meshopt_compression", 0),
                                                    ("KHR_meshopt_compression", 1)])
def test_meshopt_read(extension: str, version: int) -> None:
    v, faces = grid()
    doc = gltf.read(meshopt_glb(v, faces, extension, version), DEFAULT_LIMITS, "glb")
    part = doc.parts[0]
    np.testing.assert_array_equal(part.vertices[part.slot_to_vertex], np.rint(v * 1000 + 2000))
    np.testing.assert_array_equal(rotated(part.slot_to_vertex[part.faces]), rotated(faces))
    assert "meshopt" in doc.encodings


def draco_glb(v: np.ndarray, faces: np.ndarray, stream: bytes | None = None) -> bytes:
    import DracoPy

    if stream is None:
        stream = DracoPy.encode(v.astype(np.float32), faces, quantization_bits=14)
    stream += b"\0" * (-len(stream) % 4)
    meta = {
        "asset": {"version": "2.0"}, "extensionsUsed": ["KHR_draco_mesh_compression"],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1, "extensions": {
            "KHR_draco_mesh_compression": {"bufferView": 0, "attributes": {"POSITION": 0}}}}]}],
        "accessors": [{"componentType": 5126, "count": len(v), "type": "VEC3"},
                      {"componentType": 5123, "count": faces.size, "type": "SCALAR"}],
        "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": len(stream)}],
        "buffers": [{"byteLength": len(stream)}],
    }
    return to_glb(meta, stream)


def test_draco_read() -> None:
    v, faces = grid()
    doc = gltf.read(draco_glb(v, faces), DEFAULT_LIMITS, "glb")
    part = doc.parts[0]
    assert len(part.faces) == len(faces)
    got = part.vertices[part.slot_to_vertex]  # edgebreaker reorders the vertices
    nearest = np.sqrt(((got[:, None, :] - v[None, :, :]) ** 2).sum(axis=2)).min(axis=1)
    assert nearest.max() < 2 * 2.6 / 2**14
    assert "draco" in doc.encodings


def test_a_dense_draco_stream_is_not_shared_data(monkeypatch: pytest.MonkeyPatch) -> None:
    """Draco stores a slot and its faces in a few bytes: a 40,000-vertex grid in a 25 KB GLB
    is one stream decoded once, not data reused for more work than the file holds
    (counted at 12 bytes a slot it was refused, and so was MeshMark's own Draco output of the
    48k-vertex horse)."""
    import DracoPy

    v, faces = grid(200)
    data = draco_glb(v, faces, DracoPy.encode(v.astype(np.float32), faces, quantization_bits=14,
                                              compression_level=7))
    assert (len(v) + len(faces)) > 8 * (len(data) // 12) + gltf.REUSE_ALLOWANCE  # over the plain rule
    assert len(gltf.read(data, DEFAULT_LIMITS, "glb").parts[0].faces) == len(faces)
    monkeypatch.setattr(gltf, "DRACO_DENSITY", 1)
    with pytest.raises(LimitExceededError, match="shared data"):
        gltf.read(data, DEFAULT_LIMITS, "glb")


def test_a_draco_stream_decoded_again_counts_in_full() -> None:
    """64 primitives on one Draco stream: only its first decode is discounted."""
    import DracoPy

    v, faces = grid(60)
    stream = DracoPy.encode(v.astype(np.float32), faces, quantization_bits=14)
    stream += b"\0" * (-len(stream) % 4)
    prim = {"attributes": {"POSITION": 0}, "indices": 1, "extensions": {
        "KHR_draco_mesh_compression": {"bufferView": 0, "attributes": {"POSITION": 0}}}}
    meta = {
        "asset": {"version": "2.0"}, "extensionsUsed": ["KHR_draco_mesh_compression"],
        "meshes": [{"primitives": [prim]} for _ in range(64)],
        "accessors": [{"componentType": 5126, "count": len(v), "type": "VEC3"},
                      {"componentType": 5123, "count": faces.size, "type": "SCALAR"}],
        "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": len(stream)}],
        "buffers": [{"byteLength": len(stream)}],
    }
    with pytest.raises(LimitExceededError, match="shared data"):
        gltf.read(to_glb(meta, stream), DEFAULT_LIMITS, "glb")


# ------------------------------------------------------------------------------ hostile streams


def refused_fast(data: bytes, exc: type[Exception] = MeshFormatError,
                 limits: Limits = DEFAULT_LIMITS) -> None:
    start = time.perf_counter()
    with pytest.raises(exc):
        gltf.read(data, limits, "glb")
    assert time.perf_counter() - start < 0.5


def test_meshopt_bomb_refused_before_decoding() -> None:
    v, faces = grid()
    refused_fast(meshopt_glb(v, faces, count=10**9), LimitExceededError)
    refused_fast(meshopt_glb(v, faces, count=100_000), LimitExceededError, Limits(max_vertices=50_000))


@pytest.mark.parametrize("override", [{"byteLength": 10}, {"byteOffset": 10**6}, {"byteStride": 6},
                                      {"mode": "TRIANGLES"}, {"filter": "OCTAHEDRAL", "mode": "INDICES"}])
def test_meshopt_bad_declarations_refused(override: dict[str, Any]) -> None:
    v, faces = grid()
    refused_fast(meshopt_glb(v, faces, **override))


def test_draco_bomb_and_garbage_refused() -> None:
    v, faces = grid()
    head = b"DRACO\x02\x02\x01\x00\x00\x00"
    big = bytes([0xFF, 0xFF, 0xFF, 0xFF, 0x0F])  # 2**32 - 1 faces, sequential connectivity
    refused_fast(draco_glb(v, faces, head + big + big + b"\0" * 16), LimitExceededError)
    refused_fast(draco_glb(v, faces, b"DRACO\x01\x02\x01\x00\x00\x00" + b"\0" * 16))  # old version
    refused_fast(draco_glb(v, faces, b"NOTDRACO" + b"\0" * 16))


@settings(max_examples=60, deadline=None)
@given(cut=st.integers(0, 10_000), flip=st.integers(0, 10_000), draco=st.booleans())
def test_truncated_or_flipped_compressed_streams(cut: int, flip: int, draco: bool) -> None:
    """Any damage to a compressed stream is a MeshMarkError (or still reads), quickly."""
    v, faces = grid()
    data = bytearray(draco_glb(v, faces) if draco else meshopt_glb(v, faces))
    start = len(data) - struct.unpack_from("<I", data, 20 + struct.unpack_from("<I", data, 12)[0])[0]
    stream = len(data) - start
    data[start + flip % stream] ^= 0x5A
    if cut % 3 == 0:  # truncate the stream (the JSON still claims the full length)
        body = bytes(data[start : start + cut % stream])
        data = bytearray(data[:start]) + body + b"\0" * (stream - len(body))
    t = time.perf_counter()
    with contextlib.suppress(MeshMarkError):
        gltf.read(bytes(data), DEFAULT_LIMITS, "glb")
    assert time.perf_counter() - t < 0.5


# ------------------------------------------------------------------------------ end to end


def test_quantized_real_mesh_embed_detect_keeps_encoding() -> None:
    """Duck.glb quantized to 14-bit USHORT (as gltfpack does): marked, still USHORT, detected."""
    path = shared_mesh_path("Duck.glb")
    src = gltf.read(path.read_bytes(), DEFAULT_LIMITS, "glb")
    part = src.parts[0]
    v = part.vertices[part.slot_to_vertex]
    lo, span = v.min(axis=0), float(np.ptp(v, axis=0).max())
    stored = np.rint((v - lo) / span * 16383).astype("<u2")
    first = np.unique(part.slot_to_vertex, return_index=True)[1]  # a stored slot of each vertex
    tri = first[part.faces]
    data = to_glb(*glb_with(stored, tri, 5123, False))
    payload = "1011001110001111"
    # planes only: ellipsoids on the 2,108-vertex Duck need moves past the displacement ceiling
    for method in ("planes",):
        out = embed_file(data, "key", filename="duck.glb", payload=payload, method=method)
        assert json_of(out.data)["accessors"][0]["componentType"] == 5123
        found = detect_file(out.data, "key", filename="duck.glb", method=method)
        assert found.detected and found.payload == payload


# ------------------------------------------------------------------------------ compressed write-back


def moved_interior(doc: gltf.GltfDocument, step: float) -> list[np.ndarray]:
    part = doc.parts[0]
    v = part.vertices
    inner = np.flatnonzero(np.all((v > v.min(axis=0)) & (v < v.max(axis=0)), axis=1))[::3]
    new = v.copy()
    new[inner] = doc.quantize_part(0, inner, v[inner] + step)
    return [new]


def test_meshopt_written_back_reencoded() -> None:
    v, faces = grid()
    data = meshopt_glb(v, faces, "KHR_meshopt_compression", 1)
    doc = gltf.read(data, DEFAULT_LIMITS, "glb")
    new = moved_interior(doc, 3.0)
    out = doc.write(new)
    assert doc.reencoded == ("meshopt",)
    again = gltf.read(out, DEFAULT_LIMITS, "glb")
    np.testing.assert_array_equal(again.parts[0].vertices, new[0])
    np.testing.assert_array_equal(again.parts[0].faces, doc.parts[0].faces)
    meta = json_of(out)
    ext = meta["bufferViews"][0]["extensions"]["KHR_meshopt_compression"]
    assert ext["mode"] == "ATTRIBUTES" and ext["byteStride"] == 8
    body = out[-meta["buffers"][0]["byteLength"] :]
    assert body[ext["byteOffset"]] == 0xA1  # the same vertex codec version
    idx = meta["bufferViews"][1]["extensions"]["KHR_meshopt_compression"]
    assert idx["byteOffset"] % 4 == 0


def test_draco_written_back_reencoded_on_the_same_grid() -> None:
    v, faces = grid()
    data = draco_glb(v, faces)
    doc = gltf.read(data, DEFAULT_LIMITS, "glb")
    step = 2.6 / (2**14 - 1)
    new = moved_interior(doc, 3 * step)
    assert not np.array_equal(new[0], doc.parts[0].vertices)
    out = doc.write(new)
    assert doc.reencoded == ("draco",)
    again = gltf.read(out, DEFAULT_LIMITS, "glb")
    got = again.parts[0].vertices[again.parts[0].slot_to_vertex]
    want = new[0][doc.parts[0].slot_to_vertex]
    assert sorted(map(tuple, got.tolist())) == sorted(map(tuple, want.tolist()))


def test_compressed_real_mesh_compress_embed_detect() -> None:
    """Duck.glb compressed with Draco and with meshopt here, then marked: still compressed,
    payload found (planes: ellipsoids on the Duck need moves past the displacement ceiling)."""
    import DracoPy

    src = gltf.read(shared_mesh_path("Duck.glb").read_bytes(), DEFAULT_LIMITS, "glb")
    part = src.parts[0]
    v, f = part.vertices, part.faces
    payload = "1011001110001111"
    draco = draco_glb(v, f, DracoPy.encode(v.astype(np.float32), f, quantization_bits=14))
    lo, span = v.min(axis=0), float(np.ptp(v, axis=0).max())
    meshopt = meshopt_glb((v - lo) / span * 15, f)
    for data, kind in ((draco, "draco"), (meshopt, "meshopt")):
        for method in ("planes",):
            out = embed_file(data, "key", filename="duck.glb", payload=payload, method=method)
            assert out.report.reencoded == [kind]
            assert kind in gltf.read(out.data, DEFAULT_LIMITS, "glb").encodings
            found = detect_file(out.data, "key", filename="duck.glb", method=method)
            assert found.detected and found.payload == payload


def test_draco_grid_refused_where_float32_cannot_hold_it() -> None:
    """Fuzz case: a damaged stream decoded to coordinates near 6e17 whose 'grid' step was below
    float32's spacing there; no grid is claimed, so those positions are never re-encoded."""
    from core.formats.gltf_codecs import draco_grid

    v, _ = grid()
    huge = (v * 1e5 + 6e17).astype(np.float32)
    assert draco_grid(huge) is None
    step = np.float32(2.0 / 1023)
    origin = v.min(axis=0).astype(np.float32)  # per axis, as Draco's quantizer
    q = np.clip(np.rint((v - origin) / float(step)), 0, 1023).astype(np.float32)
    on_grid = q * step + origin  # float32 arithmetic, as Draco's decoder
    found = draco_grid(on_grid)
    assert found is not None and found.bits <= 10
    np.testing.assert_array_equal(found.encode(on_grid), on_grid)


def test_draco_stream_with_repeated_points_accessors_follow() -> None:
    """Fuzz case: a stream whose points repeat (written in order, sequential): edgebreaker merges
    them on re-encoding, and the accessor counts follow the new stream."""
    import DracoPy

    v, faces = grid()
    v = v.copy()
    v[5] = v[6]  # two points with the same position, in different triangles
    stream = DracoPy.encode(v.astype(np.float32), faces, quantization_bits=14, preserve_order=True)
    doc = gltf.read(draco_glb(v, faces, stream), DEFAULT_LIMITS, "glb")
    new = moved_interior(doc, 3 * 2.6 / (2**14 - 1))
    out = doc.write(new)
    again = gltf.read(out, DEFAULT_LIMITS, "glb")
    n = len(again.parts[0].slot_to_vertex)
    assert json_of(out)["accessors"][0]["count"] == n
    got = {tuple(r) for r in again.parts[0].vertices.tolist()}
    assert got == {tuple(r) for r in new[0].tolist()}


@settings(max_examples=200, deadline=None)
@given(kind=st.sampled_from(QUANTIZED), values=st.lists(st.floats(-300, 70000, allow_nan=False), min_size=3,
                                                        max_size=30))
def test_quantize_is_what_storing_gives(kind: Any, values: list[float]) -> None:
    """Encoding.quantize is idempotent and equals reading back the stored components."""
    from core.formats.gltf_accessors import Encoding

    _, dtype, normalized, dequant = kind
    enc = Encoding(np.dtype(dtype), normalized)
    v = np.array(values[: len(values) // 3 * 3], np.float64).reshape(-1, 3)
    if normalized:
        v = v / 70000.0
    stored = enc.encode(v)
    assert stored.dtype == np.dtype(dtype)
    np.testing.assert_array_equal(enc.quantize(v), dequant(stored.astype(np.float64)))
    np.testing.assert_array_equal(enc.quantize(enc.quantize(v)), enc.quantize(v))


def seam_vertices(part: Any, halves: list[np.ndarray]) -> np.ndarray:
    """Welded vertices with slots in both primitives (slots: first primitive's points first)."""
    n0 = len(np.unique(halves[0]))
    return np.intersect1d(part.slot_to_vertex[:n0], part.slot_to_vertex[n0:])


def test_draco_primitives_of_one_mesh_weld_across_their_seam() -> None:
    """Each Draco primitive has its own grid, so a vertex two primitives share (a material
    border) is stored twice, slightly apart: the reader closes the seam, and writing keeps it."""
    import DracoPy

    v, faces = grid()
    halves = [faces[: len(faces) // 2], faces[len(faces) // 2 :]]
    streams, accessors, prims = [], [], []
    for k, half in enumerate(halves):
        used = np.unique(half)
        local = np.searchsorted(used, half)
        s = DracoPy.encode(v[used].astype(np.float32), local, quantization_bits=11)
        streams.append(s + b"\0" * (-len(s) % 4))
        accessors += [{"componentType": 5126, "count": len(used), "type": "VEC3"},
                      {"componentType": 5123, "count": half.size, "type": "SCALAR"}]
        prims.append({"attributes": {"POSITION": 2 * k}, "indices": 2 * k + 1, "extensions": {
            "KHR_draco_mesh_compression": {"bufferView": k, "attributes": {"POSITION": 0}}}})
    meta = {"asset": {"version": "2.0"}, "meshes": [{"primitives": prims}], "accessors": accessors,
            "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": len(streams[0])},
                            {"buffer": 0, "byteOffset": len(streams[0]), "byteLength": len(streams[1])}],
            "buffers": [{"byteLength": len(streams[0]) + len(streams[1])}]}
    doc = gltf.read(to_glb(meta, streams[0] + streams[1]), DEFAULT_LIMITS, "glb")
    part = doc.parts[0]
    assert len(part.vertices) == len(v)  # the 12 seam vertices are one vertex each again
    seam = np.intersect1d(np.unique(halves[0]), np.unique(halves[1]))
    assert len(seam) == 12
    # seam vertices move too, on their first primitive's grid, and read back as quantize_part says
    moved = doc.quantize_part(0, np.arange(len(part.vertices)), part.vertices + 0.01)
    out = doc.write([moved])
    again = gltf.read(out, DEFAULT_LIMITS, "glb")
    assert len(again.parts[0].vertices) == len(v)
    got = sorted(map(tuple, again.parts[0].vertices.tolist()))  # edgebreaker reorders points
    assert got == sorted(map(tuple, moved.tolist()))
    assert not np.array_equal(moved[seam_vertices(part, halves)], part.vertices[seam_vertices(part, halves)])
